"""Source files fetched ahead: one listing per folder, one whole-object GET per file, checked.

Every per-frame loop of a conversion (sweeps, images, the ego-mask sample, the calibration sweeps,
the label jobs' sweeps, validation's source side) takes its bytes from :func:`read_ahead`, which
fetches the files it will be asked for next while the caller works on the current one.

- **Remote** (``s3://``, or any async fsspec store): the fetches are coroutines on fsspec's own
  event loop, so many are in flight at once; each is one GET of the whole object. On S3 the GET
  carries the listing's ETag as ``If-Match``, so an object replaced since the listing is refused by
  the store (412) instead of being read; on every store the body's length must equal the
  listing's size. Either failure is a ``SourceError`` naming the object.
- **Local**: a small thread pool reads ahead (``LOCAL_THREADS``), so disk reads overlap the CPU work.

Sizes and ETags come from :func:`list_folder` (one LIST per folder; no HEAD per file). What is held
ahead is bounded in bytes (this process's share of ``--read-ahead-mb``, :func:`budget_bytes`) and in
files (``MAX_AHEAD``).

**Once per log.** A remote file that a later job of the same log will read again (a sweep: the
lidar job, the label jobs and validation read it; an image of the ego-mask sample: its camera's
job copies it) is fetched with ``keep=True``: its checked bytes are also written to the run's
spool on local disk (``$NCORE_CONVERT_SPOOL``, a folder the command makes per run; per process
otherwise), where every process of the run on this machine finds it by the object's path and
ETag. A log's spooled files are removed when the log ends (:func:`release`). The spool holds about
``SPOOL_BUDGET_BYTES`` at most; a file past that is fetched again when needed, counted
(``Counts.not_kept``) and reported in the log's warnings (:func:`not_kept_since`). Requests, bytes
and spool hits are counted per process (:data:`COUNTS`).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import os
import shutil
import tempfile
import threading
from collections.abc import Iterable, Iterator
from pathlib import Path

from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.files import COUNTS, ObjectInfo, checked, get_remote, key, read_bytes
from ncore_convert.storage import is_local

DEFAULT_RUN_BUDGET_MB = 256  #: ``--read-ahead-mb``: bytes held ahead by a run's processes on one machine
BUDGET_ENV = "NCORE_CONVERT_READ_AHEAD_BYTES"  #: this process's share (set by the command for its processes)
DEFAULT_BUDGET_BYTES = DEFAULT_RUN_BUDGET_MB * 2**20  #: a process's share when no command set one
MAX_AHEAD = 64  #: files in flight or held ahead per reader
LOCAL_THREADS = 4  #: threads reading local files ahead
UNKNOWN_SIZE = 8 * 2**20  #: what a file not in any listing counts against the budget
SPOOL_ENV = "NCORE_CONVERT_SPOOL"  #: the run's spool folder (set by the command for its processes)
SPOOL_BUDGET_BYTES = 4 * 2**30  #: bytes the run's spool holds at most (about: each process measures it)


_lock = threading.RLock()  #: re-entrant: the spool bound measures the spool under it
_spool = {"root": None, "written": 0}


def share_budget(budget_bytes: int) -> None:
    """The bytes a reader of this process, and of the processes it starts after this, may hold
    ahead (its share of ``--read-ahead-mb``)."""
    os.environ[BUDGET_ENV] = str(max(1, int(budget_bytes)))


def budget_bytes() -> int:
    """This process's read-ahead share, in bytes."""
    return int(os.environ.get(BUDGET_ENV) or DEFAULT_BUDGET_BYTES)


def list_folder(directory: UPath) -> dict[str, ObjectInfo]:
    """The files directly in ``directory`` with their sizes and ETags, from one listing (remote; no
    request per file; the store's pages of 1,000 keys followed), keyed by :func:`key`; {} for a
    local folder (the OS checks local reads) and for a remote one that does not exist."""
    if is_local(directory):
        return {}
    with _lock:
        COUNTS.lists += 1
    try:
        entries = directory.fs.ls(directory.path, detail=True, refresh=True)
    except FileNotFoundError:
        return {}
    out = {}
    for entry in entries:
        if entry.get("type") == "file":
            etag = entry.get("ETag") or entry.get("etag")
            path = UPath(f"{directory.protocol}://{entry['name']}", **directory.storage_options)
            out[key(path)] = ObjectInfo(int(entry.get("size") or 0), etag)
    return out


def file_names(directory: UPath, listing: dict[str, ObjectInfo] | None = None) -> list[str]:
    """The names of the files in a folder ([] without it): a local folder's entries, or a remote
    folder's one listing, whose sizes and ETags are added to ``listing``."""
    if is_local(directory):
        return [p.name for p in directory.iterdir()] if directory.is_dir() else []
    found = list_folder(directory)
    if listing is not None:
        listing.update(found)
    return [name.rsplit("/", 1)[-1] for name in found]


def spool_root() -> Path:
    """The run's spool folder (``$NCORE_CONVERT_SPOOL``), or this process's own, made on first use."""
    with _lock:
        if _spool["root"] is None:
            root = os.environ.get(SPOOL_ENV) or tempfile.mkdtemp(prefix=f"ncore-convert-spool-{os.getpid()}-")
            _spool["root"] = Path(root)
        return _spool["root"]


def _spool_path(path: UPath, info: ObjectInfo | None) -> Path | None:
    """Where a remote object's checked bytes are spooled: its path under the spool, with its ETag
    (None without a listing entry: nothing to check a spooled copy against)."""
    if info is None or is_local(path):
        return None
    tag = "".join(c for c in (info.etag or "") if c.isalnum()) or f"size{info.size}"
    return spool_root() / path.protocol / f"{path.path.lstrip('/')}.{tag}"


def _spooled(path: UPath, info: ObjectInfo | None) -> bytes | None:
    where = _spool_path(path, info)
    if where is None:
        return None
    try:
        data = where.read_bytes()
    except OSError:
        return None
    if len(data) != info.size:
        return None
    with _lock:
        COUNTS.spool_hits += 1
    return data


def _spool_bytes() -> int:
    """What the run's spool holds now, in bytes (every process's files; released logs' are gone)."""
    return sum(p.stat().st_size for p in spool_root().rglob("*") if p.is_file())


def _keep(path: UPath, info: ObjectInfo | None, data: bytes) -> None:
    """Write a fetched object to the spool (atomically: a reader sees all of it or none) while the
    spool holds less than SPOOL_BUDGET_BYTES: this process counts what it wrote since it last
    measured the spool, and measures again when that would pass the bound. A file not kept is
    counted (``COUNTS.not_kept``): the later job fetches it again."""
    where = _spool_path(path, info)
    if where is None:
        return
    with _lock:
        if _spool["written"] + len(data) > SPOOL_BUDGET_BYTES:
            _spool["written"] = _spool_bytes()
        if _spool["written"] + len(data) > SPOOL_BUDGET_BYTES:
            COUNTS.not_kept += 1
            return
        _spool["written"] += len(data)
        COUNTS.spooled += 1
    where.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=where.parent, prefix=".part-")
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, where)


@contextlib.contextmanager
def run_spool() -> Iterator[Path]:
    """The run's spool folder, named in ``$NCORE_CONVERT_SPOOL`` for the processes the run starts
    inside this context (enter it before the workers start); removed on the way out."""
    root = spool_root()
    os.environ[SPOOL_ENV] = str(root)
    try:
        yield root
    finally:
        remove_spool()
        os.environ.pop(SPOOL_ENV, None)


def not_kept_since(before: int) -> str | None:
    """The warning for the files this process could not keep since ``COUNTS.not_kept`` was
    ``before``, or None."""
    n = COUNTS.not_kept - before
    if n <= 0:
        return None
    return (
        f"{n} input file(s) not kept for the log's later jobs (the run's spool under {spool_root()} holds"
        f" {SPOOL_BUDGET_BYTES / 2**30:g} GiB at most): they are fetched again"
    )


def release(directory: UPath) -> None:
    """Remove what the spool holds under a log's source folder (the log has ended)."""
    if is_local(directory) or _spool["root"] is None and not os.environ.get(SPOOL_ENV):
        return
    shutil.rmtree(spool_root() / directory.protocol / directory.path.strip("/"), ignore_errors=True)


def remove_spool() -> None:
    """Remove this process's spool folder (the run, or a Ray task, has ended)."""
    with _lock:
        root, _spool["root"] = _spool["root"], None
        _spool["written"] = 0
    if root is not None:
        shutil.rmtree(root, ignore_errors=True)


def exists(path: UPath, listing: dict[str, ObjectInfo] | None) -> bool:
    """Whether a file exists: by its folder's ``listing`` for a remote file listed with it (no
    request), else by asking the store or the OS."""
    if listing and not is_local(path):
        return key(path) in listing
    return path.exists()


_local_pool: concurrent.futures.ThreadPoolExecutor | None = None


def _local_threads() -> concurrent.futures.ThreadPoolExecutor:
    global _local_pool
    with _lock:
        if _local_pool is None:
            _local_pool = concurrent.futures.ThreadPoolExecutor(LOCAL_THREADS, thread_name_prefix="read-ahead")
        return _local_pool


def _start(path: UPath, info: ObjectInfo | None) -> concurrent.futures.Future:
    """A file's fetch under way: the spooled copy, a GET on fsspec's loop, or a read in a thread
    (local files, and stores without an async interface)."""
    if not is_local(path):
        if (data := _spooled(path, info)) is not None:
            done: concurrent.futures.Future = concurrent.futures.Future()
            done.set_result(data)
            return done
        if getattr(path.fs, "async_impl", False):
            return asyncio.run_coroutine_threadsafe(get_remote(path, info), path.fs.loop)
    return _local_threads().submit(lambda: checked(path, read_bytes(path), info))


def fetch(path: UPath, listing: dict[str, ObjectInfo] | None = None, keep: bool = False) -> bytes:
    """One file's bytes (one GET remotely, checked against its ``listing`` entry if it has one;
    ``keep``: spooled for the log's later jobs); SourceError naming it."""
    info = (listing or {}).get(key(path))
    data = _start(path, info).result()
    if keep:
        _keep(path, info, data)
    return data


def read_ahead(
    paths: Iterable[UPath],
    listing: dict[str, ObjectInfo] | None = None,
    keep: bool = False,
) -> Iterator[tuple[UPath, bytes | SourceError]]:
    """Each file's bytes, in the order given, fetched ahead within the process's share of the
    read-ahead (:func:`budget_bytes`) and ``MAX_AHEAD`` files; ``keep``: spooled for the log's later jobs. A file
    that cannot be read yields its SourceError in its turn (the caller raises it, or skips the file
    and says so). Leaving the loop early cancels what is still in flight."""
    listing = listing or {}
    budget = budget_bytes()
    todo = iter(paths)
    ahead: collections.deque = collections.deque()
    held = 0

    def size_of(path: UPath) -> int:
        info = listing.get(key(path))
        return info.size if info is not None else UNKNOWN_SIZE

    def fill() -> None:
        nonlocal held
        while len(ahead) < MAX_AHEAD and (not ahead or held < budget):
            path = next(todo, None)
            if path is None:
                return
            size = size_of(path)
            ahead.append((path, size, _start(path, listing.get(key(path)))))
            held += size

    try:
        fill()
        while ahead:
            path, size, future = ahead.popleft()
            try:
                result: bytes | SourceError = future.result()
                if keep:
                    _keep(path, listing.get(key(path)), result)
            except SourceError as err:
                result = err
            held -= size
            fill()
            yield path, result
    finally:
        for _, _, future in ahead:
            future.cancel()
