"""An HTTP proxy in front of an S3 server (moto) that holds each response's first byte ``delay_ms``
(one cloud round trip), counts requests by kind (HEAD, GET, LIST, PUT: every write, multipart parts
included) and the bytes of GET bodies, and can answer a seeded share of requests with 503 SlowDown
or drop their connections, or refuse every request with an S3 error code (``refuse``). Used by
``tests/test_object_reads.py`` and ``bench/bench_object_storage.py``.

    with LatencyProxy(upstream="http://127.0.0.1:5000", delay_ms=50) as proxy:
        env["AWS_ENDPOINT_URL"] = proxy.url
"""

from __future__ import annotations

import asyncio
import collections
import logging
import random
import socket
import threading
from urllib.parse import parse_qs, urlsplit

import aiohttp
from aiohttp import web

_HOP_HEADERS = {"host", "content-length", "transfer-encoding", "connection", "keep-alive"}
SLOW_DOWN = (
    b'<?xml version="1.0" encoding="UTF-8"?>\n<Error><Code>SlowDown</Code>'
    b"<Message>Please reduce your request rate.</Message></Error>"
)


def request_kind(method: str, path_qs: str) -> str:
    """HEAD, GET (an object), LIST (a bucket's listing), PUT (any write) or OTHER."""
    parts = urlsplit(path_qs)
    query = parse_qs(parts.query, keep_blank_values=True)
    if method == "HEAD":
        return "HEAD"
    if method == "GET":
        if "list-type" in query or parts.path.strip("/").count("/") == 0:
            return "LIST"
        return "GET"
    if method in ("PUT", "POST", "DELETE"):
        return "PUT" if method != "DELETE" else "DELETE"
    return "OTHER"


class LatencyProxy:
    """The proxy, served from a thread of this process (see the module docstring).

    Attributes:
        counts: requests by kind; ``keys``: requests by (kind, path) (to find objects fetched twice).
        bytes_out: bytes of GET response bodies.
    """

    def __init__(
        self,
        upstream: str,
        delay_ms: float = 0.0,
        slow_down: float = 0.0,
        drop: float = 0.0,
        seed: int = 0,
        refuse: str | None = None,
    ) -> None:
        self.upstream = upstream.rstrip("/")
        self.refuse = refuse
        self.unsigned: collections.Counter = collections.Counter()  #: requests without credentials, by kind
        self.signed_paths: set[str] = set()  #: the paths of the requests with credentials
        self.order: list[tuple[str, str]] = []  #: (kind, path) of every request, in arrival order
        self.delay_s = delay_ms / 1000.0
        self.slow_down, self.drop = slow_down, drop
        self._random = random.Random(seed)
        self.counts: collections.Counter = collections.Counter()
        self.keys: collections.Counter = collections.Counter()
        self.bytes_out = 0
        self.busy_s = 0.0  #: summed request durations: ÷ wall = requests in flight on average
        self.faults: collections.Counter = collections.Counter()
        self._lock = threading.Lock()
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            self.port = s.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def reset(self) -> None:
        with self._lock:
            self.counts.clear()
            self.keys.clear()
            self.faults.clear()
            self.unsigned.clear()
            self.signed_paths.clear()
            self.order.clear()
            self.bytes_out = 0
            self.busy_s = 0.0

    def __enter__(self) -> LatencyProxy:
        self._thread.start()
        if not self._ready.wait(30):
            raise RuntimeError("the latency proxy did not start")
        return self

    def __exit__(self, *exc) -> None:
        async def close() -> None:
            await self._session.close()
            await self._runner.cleanup()

        asyncio.run_coroutine_threadsafe(close(), self._loop).result(30)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)

    def _serve(self) -> None:
        asyncio.set_event_loop(self._loop)
        logging.getLogger("aiohttp.server").setLevel(logging.CRITICAL)  # a dropped connection is on purpose
        app = web.Application(client_max_size=2**31)
        app.router.add_route("*", "/{tail:.*}", self._handle)
        self._runner = web.AppRunner(app, access_log=None)
        self._loop.run_until_complete(self._runner.setup())
        self._loop.run_until_complete(web.TCPSite(self._runner, "127.0.0.1", self.port).start())

        async def client() -> aiohttp.ClientSession:
            return aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0), auto_decompress=False)

        self._session = self._loop.run_until_complete(client())
        self._ready.set()
        self._loop.run_forever()

    def _fault(self) -> str | None:
        with self._lock:
            r = self._random.random()
        if r < self.slow_down:
            return "503"
        if r < self.slow_down + self.drop:
            return "drop"
        return None

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        started = self._loop.time()
        try:
            return await self._answer(request)
        finally:
            with self._lock:
                self.busy_s += self._loop.time() - started

    async def _answer(self, request: web.Request) -> web.StreamResponse:
        kind = request_kind(request.method, request.path_qs)
        body = await request.read()
        path = urlsplit(request.path_qs).path
        with self._lock:
            self.counts[kind] += 1
            self.keys[(kind, path)] += 1
            self.order.append((kind, path))
            if "Authorization" not in request.headers and "X-Amz-Signature" not in request.query:
                self.unsigned[kind] += 1
            else:
                self.signed_paths.add(path)
        if self.refuse is not None:
            status = 400 if self.refuse == "ExpiredToken" else 403
            body = f"<Error><Code>{self.refuse}</Code><Message>refused by the proxy</Message></Error>"
            return web.Response(status=status, body=body.encode(), content_type="application/xml")
        fault = self._fault()
        if fault == "503":
            with self._lock:
                self.faults["503"] += 1
            await asyncio.sleep(self.delay_s)
            return web.Response(status=503, body=SLOW_DOWN, content_type="application/xml")
        if fault == "drop":
            with self._lock:
                self.faults["drop"] += 1
            request.transport.close()  # the connection ends with no response
            raise ConnectionResetError("dropped by the proxy")
        headers = {k: v for k, v in request.headers.items() if k.lower() not in _HOP_HEADERS}
        headers["Host"] = request.headers.get("Host", "")
        async with self._session.request(
            request.method, self.upstream + request.path_qs, headers=headers, data=body, allow_redirects=False
        ) as upstream:
            data = await upstream.read()
            reply_headers = {k: v for k, v in upstream.headers.items() if k.lower() not in _HOP_HEADERS}
            if request.method == "HEAD" and "Content-Length" in upstream.headers:  # the object's size
                reply_headers["Content-Length"] = upstream.headers["Content-Length"]
            status = upstream.status
        await asyncio.sleep(self.delay_s)  # the first byte leaves one round trip late
        if kind == "GET":
            with self._lock:
                self.bytes_out += len(data)
        return web.Response(status=status, body=data, headers=reply_headers)
