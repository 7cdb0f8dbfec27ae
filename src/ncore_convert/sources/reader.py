"""The input reader: every listing and every read of a dataset goes through one :class:`Reader`,
an object made for a log (or a job, a validation, a preview), handed to what reads, and closed at
the end. It holds its own counts, its spool and its thread pool; nothing of it lives in module
state or in the environment.

- **One listing per folder** (:meth:`Reader.list_folder`): sizes and ETags of a remote folder's
  files from one LIST (no HEAD per file); a file's existence is asked of its folder's listing.
- **One whole-object GET per file**, fetched ahead (:meth:`Reader.read_ahead`) while the caller works
  on the current one. Remote: coroutines on fsspec's own event loop, many in flight at once; on S3
  the GET carries the listing's ETag as ``If-Match``, so an object replaced since the listing is
  refused (412) instead of read; on every store the body's length must equal the listing's size.
  Local: a small thread pool (``LOCAL_THREADS``), so disk reads overlap the CPU work. What is held
  ahead is bounded in bytes (the reader's share of ``--read-ahead-mb``) and in files (``MAX_AHEAD``).
- **Once per log.** A remote file that a later job of the same log reads again (a sweep: the lidar
  job, the label jobs and validation read it; an image of the ego-mask sample: its camera's job
  copies it) is read with ``keep=True``: its checked bytes are also written to the log's spool
  folder on local disk, where every reader of the log on this machine (:meth:`Reader.shared`, in
  other processes too) finds it by the object's path and ETag. The spool folder belongs to the
  reader that named it and is removed when it closes; the run's spool (``ReadSettings.spool_root``)
  holds about ``SPOOL_BUDGET_BYTES`` at most, and a file past that is fetched again when needed,
  counted (``ReadCounts.not_kept``) and reported in the log's warnings (:meth:`Reader.not_kept_warning`).
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import hashlib
import os
import shutil
import tempfile
import threading
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.paths import is_local
from ncore_convert.sources.checks import check_safe_names
from ncore_convert.sources.store import (
    ObjectInfo,
    checked,
    entry_info,
    get_remote,
    get_remote_sync,
    key,
    list_remote,
    read_local,
)

DEFAULT_RUN_BUDGET_MB = 256  #: ``--read-ahead-mb``: bytes held ahead by a run's processes on one machine
DEFAULT_BUDGET_BYTES = DEFAULT_RUN_BUDGET_MB * 2**20  #: a reader's share when none is given
MAX_AHEAD = 64  #: files in flight or held ahead per reader
LOCAL_THREADS = 4  #: threads reading local files ahead
UNKNOWN_SIZE = 8 * 2**20  #: what a file not in any listing counts against the budget
SPOOL_BUDGET_BYTES = 4 * 2**30  #: bytes the run's spool holds at most (about: each reader measures it)
SPOOL_PREFIX = "ncore-convert-spool-"  #: the name of every spool folder a reader or a run makes


@dataclass(frozen=True)
class ReadSettings:
    """What a reader is made with: plain values, handed to worker processes and Ray tasks.

    Attributes:
        budget_bytes: bytes the reader may hold ahead (its process's share of ``--read-ahead-mb``).
        spool_root: the run's spool folder on this machine, whose size the spool bound measures
            (None: the reader's own folder under the temporary directory).
        spool_dir: a folder another reader named and owns (:meth:`Reader.shared`): this reader keeps
            its files there and leaves the folder to its owner (None: the reader names its own).
    """

    budget_bytes: int = DEFAULT_BUDGET_BYTES
    spool_root: str | None = None
    spool_dir: str | None = None


@dataclass
class ReadCounts:
    """A reader's requests and bytes (remote GETs and LISTs; local reads are not requests)."""

    gets: int = 0
    lists: int = 0
    bytes: int = 0
    listed_bytes: int = 0  #: the size of the distinct files its listings found (a log's input bytes)
    refetched: int = 0  #: objects this reader fetched a second time
    spooled: int = 0  #: files written to the spool
    spool_hits: int = 0  #: files read from the spool instead of fetched
    not_kept: int = 0  #: files a later job reads again, not spooled (the spool was full): fetched again

    def add(self, other: ReadCounts | dict | None) -> None:
        """Add another reader's counts (a worker's, as a dict or counts)."""
        values = asdict(other) if isinstance(other, ReadCounts) else (other or {})
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + int(values.get(f.name, 0)))

    def plus(self, reads: dict | None) -> dict[str, int]:
        """These counts added to ``reads`` (other readers' counts, as a dict), as a dict."""
        total = ReadCounts()
        total.add(self)
        total.add(reads)
        return asdict(total)


class Reader:
    """The input side of one log (or job, validation, preview): listings, reads, read-ahead, the
    spool, and their counts. Use it as a context manager, or call :meth:`close`."""

    def __init__(self, settings: ReadSettings | None = None) -> None:
        self.settings = settings or ReadSettings()
        self.counts = ReadCounts()
        self.listed: dict[str, ObjectInfo] = {}  #: every file of every remote listing this reader made
        self._listed_folders: set[str] = set()
        self._seen: set[str] = set()
        self._lock = threading.RLock()  # re-entrant: the spool bound measures the spool under it
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self._spool_written = 0
        if self.settings.spool_dir is not None:
            self.spool_dir, self._owns_spool = Path(self.settings.spool_dir), False
        else:
            parent = self.settings.spool_root or tempfile.gettempdir()
            self.spool_dir = Path(parent) / f"{SPOOL_PREFIX}{os.getpid()}-{uuid.uuid4().hex[:12]}"
            self._owns_spool = True  # made on the first file kept, removed by close()

    # --- lifetime ---
    def __enter__(self) -> Reader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reads in flight and remove the spool folder this reader named (with what it
        and the readers sharing it kept)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
        if self._owns_spool:
            shutil.rmtree(self.spool_dir, ignore_errors=True)

    def shared(self) -> ReadSettings:
        """Settings for a reader of the same log in another process or thread: the same budget, and
        this reader's spool folder (which stays this reader's to remove)."""
        return ReadSettings(self.settings.budget_bytes, self.settings.spool_root, str(self.spool_dir))

    def not_kept_warning(self) -> str | None:
        """The log warning for the files this reader could not keep for the log's later jobs, or None."""
        if self.counts.not_kept <= 0:
            return None
        return (
            f"{self.counts.not_kept} input file(s) not kept for the log's later jobs (the run's spool under"
            f" {self._bound_root()} holds {SPOOL_BUDGET_BYTES / 2**30:g} GiB at most): they are fetched again"
        )

    # --- listings ---
    def list_folder(self, directory: UPath) -> dict[str, ObjectInfo]:
        """The files directly in ``directory`` with their sizes and ETags, from one listing (remote; no
        request per file), keyed by :func:`store.key`; {} for a local folder (the OS checks local
        reads) and for a remote one that does not exist."""
        if is_local(directory):
            return {}
        return self._list(directory)[1]

    def file_names(self, directory: UPath, listing: dict[str, ObjectInfo] | None = None) -> list[str]:
        """The names of the files in a folder ([] without it): a local folder's entries, or a remote
        folder's one listing, whose sizes and ETags are added to ``listing``."""
        if is_local(directory):
            with contextlib.suppress(FileNotFoundError, NotADirectoryError):
                return [e.name for e in os.scandir(directory.path) if not e.is_dir()]
            return []
        found = self.list_folder(directory)
        if listing is not None:
            listing.update(found)
        return [name.rsplit("/", 1)[-1] for name in found]

    def folder_names(self, directory: UPath, what: str | None) -> list[str]:
        """The sorted names of the visible folders in ``directory`` (logs, scenarios, agents), each
        checked to be a safe name for a ``what`` (SourceError naming ``directory`` otherwise; None:
        the caller checks them); [] without it."""
        if is_local(directory):
            try:
                names = [e.name for e in os.scandir(directory.path) if e.is_dir()]
            except (FileNotFoundError, NotADirectoryError):
                names = []
        else:
            entries = self._list(directory)[0]
            names = [e["name"].rstrip("/").rsplit("/", 1)[-1] for e in entries if e.get("type") != "file"]
        names = sorted(n for n in names if not n.startswith("."))
        if what is not None:
            check_safe_names(directory, names, what)
        return names

    def is_folder(self, path: UPath) -> bool:
        """Whether ``path`` is a folder with something in it (remote: one listing; a store's folders
        exist only through what is in them)."""
        if is_local(path):
            return os.path.isdir(path.path)
        return bool(self._list(path)[0])

    def require_folder(self, path: UPath, noun: str) -> None:
        """SourceError unless ``path`` is a folder with something in it (``noun``: "log directory", ...)."""
        if is_local(path):
            if not os.path.isdir(path.path):
                raise SourceError(path, f"{noun} not found")
            if not any(os.scandir(path.path)):
                raise SourceError(path, f"empty {noun} (an interrupted download?)")
        elif not self._list(path)[0]:
            raise SourceError(path, f"{noun} not found")

    def exists(self, path: UPath, listing: dict[str, ObjectInfo] | None = None) -> bool:
        """Whether a file exists: by ``listing`` (a folder listing given with it) or this reader's own
        listings for a remote file, else by one listing of its folder; by the OS for a local one.
        Never a HEAD."""
        if is_local(path):
            return os.path.isfile(path.path)
        name = key(path)
        if listing or key(path.parent) in self._listed_folders:
            return name in (listing or {}) or name in self.listed
        return name in self.list_folder(path.parent)

    def _list(self, directory: UPath) -> tuple[list[dict], dict[str, ObjectInfo]]:
        """One LIST of a remote folder: its entries, and its files (sizes, ETags), which the reader
        remembers whatever the listing was for."""
        with self._lock:
            self.counts.lists += 1
        entries = list_remote(directory)
        found = {}
        for entry in entries:
            if entry.get("type") == "file":
                path = UPath(f"{directory.protocol}://{entry['name']}", **directory.storage_options)
                found[key(path)] = entry_info(entry)
        with self._lock:
            self.counts.listed_bytes += sum(info.size for name, info in found.items() if name not in self.listed)
            self.listed.update(found)
            self._listed_folders.add(key(directory))
        return entries, found

    # --- reads ---
    def read(
        self, path: UPath, listing: dict[str, ObjectInfo] | None = None, keep: bool = False, max_bytes: int = -1
    ) -> bytes:
        """One file's bytes (one GET remotely, checked against its listing entry if it has one;
        ``max_bytes``: its first bytes only, one ranged GET; ``keep``: spooled for the log's later
        jobs); SourceError naming it."""
        path = UPath(path)
        if max_bytes >= 0:
            if is_local(path):
                return read_local(path, max_bytes)
            info = self._info(path, listing)
            if (kept := self._spooled(path, info, max_bytes)) is not None:
                return kept  # a file the log keeps: its head without a request
            data = (  # a ranged GET, conditional on the listing's ETag
                asyncio.run_coroutine_threadsafe(get_remote(path, info, max_bytes), path.fs.loop).result()
                if getattr(path.fs, "async_impl", False)
                else get_remote_sync(path, info, max_bytes)
            )
            self._count_get(path, data)
            return data
        info = self._info(path, listing)
        future, fetched = self._start(path, info, in_pool=False)
        data = future.result()
        if fetched:
            self._count_get(path, data)
        if keep:
            self._keep(path, info, data)
        return data

    def read_ahead(
        self, paths: Iterable[UPath], listing: dict[str, ObjectInfo] | None = None, keep: bool = False
    ) -> Iterator[tuple[UPath, bytes | SourceError]]:
        """Each file's bytes, in the order given, fetched ahead within the reader's budget and
        ``MAX_AHEAD`` files; ``keep``: spooled for the log's later jobs. A file that cannot be read
        yields its SourceError in its turn (the caller raises it, or skips the file and says so).
        Leaving the loop early cancels what is still in flight."""
        budget = self.settings.budget_bytes
        todo = iter(paths)
        ahead: collections.deque = collections.deque()
        held = 0

        def fill() -> None:
            nonlocal held
            while len(ahead) < MAX_AHEAD and (not ahead or held < budget):
                path = next(todo, None)
                if path is None:
                    return
                info = self._info(path, listing)
                size = info.size if info is not None else UNKNOWN_SIZE
                ahead.append((path, info, size, *self._start(path, info, in_pool=True)))
                held += size

        try:
            fill()
            while ahead:
                path, info, size, future, fetched = ahead.popleft()
                try:
                    result: bytes | SourceError = future.result()
                    if fetched:  # counted here, where its bytes are taken (not in the loop's thread)
                        self._count_get(path, result)
                    if keep:
                        self._keep(path, info, result)
                except SourceError as err:
                    result = err
                held -= size
                fill()
                yield path, result
        finally:
            for *_, future, _ in ahead:
                future.cancel()

    def _info(self, path: UPath, listing: dict[str, ObjectInfo] | None) -> ObjectInfo | None:
        name = key(path)
        return (listing or {}).get(name) or self.listed.get(name)

    def _start(self, path: UPath, info: ObjectInfo | None, in_pool: bool) -> tuple[concurrent.futures.Future, bool]:
        """A file's read under way: the spooled copy, a GET on fsspec's loop, or a read in a thread
        (``in_pool``; local files, and stores without an async interface), else done here; and
        whether it is a request (a remote GET, counted when its bytes are taken)."""
        done: concurrent.futures.Future = concurrent.futures.Future()
        if not is_local(path):
            if (data := self._spooled(path, info)) is not None:
                done.set_result(data)
                return done, False
            if getattr(path.fs, "async_impl", False):
                return asyncio.run_coroutine_threadsafe(get_remote(path, info), path.fs.loop), True
            read = lambda: get_remote_sync(path, info)  # noqa: E731
        else:
            read = lambda: checked(path, read_local(path), info)  # noqa: E731
        if in_pool:
            return self._threads().submit(read), not is_local(path)
        try:
            done.set_result(read())
        except SourceError as err:
            done.set_exception(err)
        return done, not is_local(path)

    def _threads(self) -> concurrent.futures.ThreadPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = concurrent.futures.ThreadPoolExecutor(LOCAL_THREADS, thread_name_prefix="read-ahead")
            return self._pool

    def _count_get(self, path: UPath, data: bytes) -> None:
        with self._lock:
            self.counts.gets += 1
            self.counts.bytes += len(data)
            name = key(path)
            if name in self._seen:
                self.counts.refetched += 1
            self._seen.add(name)

    # --- the spool ---
    def _bound_root(self) -> Path:
        return Path(self.settings.spool_root) if self.settings.spool_root else self.spool_dir

    def _spool_path(self, path: UPath, info: ObjectInfo | None) -> Path | None:
        """Where a remote object's checked bytes are spooled: a file directly in the spool folder,
        named by a hash of its key, its name and its ETag (None without a listing entry: nothing to
        check a spooled copy against). Flat, so keeping a file never creates a folder but the
        reader's own, inside a run's spool that still exists."""
        if info is None or is_local(path):
            return None
        tag = "".join(c for c in (info.etag or "") if c.isalnum()) or f"size{info.size}"
        digest = hashlib.sha1(key(path).encode(), usedforsecurity=False).hexdigest()[:20]
        return self.spool_dir / f"{digest}-{path.name}.{tag}"

    def _spooled(self, path: UPath, info: ObjectInfo | None, max_bytes: int = -1) -> bytes | None:
        """The spooled copy of a remote object (its first ``max_bytes``, if given), or None."""
        where = self._spool_path(path, info)
        if where is None:
            return None
        try:
            with open(where, "rb") as f:
                if os.fstat(f.fileno()).st_size != info.size:
                    return None
                data = f.read(max_bytes)
        except OSError:
            return None
        with self._lock:
            self.counts.spool_hits += 1
        return data

    def _spool_bytes(self) -> int:
        """What the run's spool holds now, in bytes (every reader's files; closed logs' are gone)."""
        return sum(p.stat().st_size for p in self._bound_root().rglob("*") if p.is_file())

    def _keep(self, path: UPath, info: ObjectInfo | None, data: bytes) -> None:
        """Write a fetched object to the spool (atomically: a reader sees all of it or none) while the
        run's spool holds less than SPOOL_BUDGET_BYTES: this reader counts what it wrote since it
        last measured the spool, and measures again when that would pass the bound. A file not kept
        is counted (``not_kept``): the later job fetches it again."""
        where = self._spool_path(path, info)
        if where is None:
            return
        with self._lock:
            if self._spool_written + len(data) > SPOOL_BUDGET_BYTES:
                self._spool_written = self._spool_bytes()
            if self._spool_written + len(data) > SPOOL_BUDGET_BYTES:
                self.counts.not_kept += 1
                return
            self._spool_written += len(data)
            self.counts.spooled += 1
        try:  # never its parents: a run's spool removed (the run stops) is not made again
            where.parent.mkdir(exist_ok=True)
            fd, tmp = tempfile.mkstemp(dir=where.parent, prefix=".part-")
        except FileNotFoundError:
            return
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, where)


@contextlib.contextmanager
def reading(reader: Reader | None, settings: ReadSettings | None = None) -> Iterator[Reader]:
    """``reader`` itself (its owner closes it), or a reader made for the block and closed after it."""
    if reader is not None:
        yield reader
        return
    with Reader(settings) as made:
        yield made


def with_reader(
    task: Callable[..., Any],
    *args: Any,
    reader: Reader | None = None,
    reading: ReadSettings | None = None,
    **kwargs: Any,
) -> Any:
    """``task(*args, reader=..., **kwargs)`` (a log or scenario task, or its conversion) reading
    through ``reader`` (its owner closes it and counts it), or through a reader made for the call
    (``reading``: the run's settings), closed when the task ends (which removes what its spool kept),
    whose requests are added to the summary's (the workers'), its listings' bytes being the remote
    input's size (``listed_bytes``)."""
    if reader is not None:
        return task(*args, reader=reader, **kwargs)
    with Reader(reading) as made:
        summary = task(*args, reader=made, **kwargs)
        summary.reads = made.counts.plus(summary.reads)
    return summary
