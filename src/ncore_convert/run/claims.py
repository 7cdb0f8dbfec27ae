"""Claims: which run converts which log, so that several runs can share one output folder.

Before a run writes a log it claims it: ``<output>/.<log_id>.claim``, a small JSON record of the
run (run id, host, process id and its start time). The claim is created atomically:

- on a local or shared file system, by hard-linking a complete temporary file to the claim's name
  (``link`` fails when the name exists, also on NFS);
- on object storage, by a conditional write (``If-None-Match: *``), which S3 honours.

A claim whose owner is gone is taken over: on the same host when its process no longer exists (or
is another process with the same id), elsewhere when its heartbeat is stale (the owner refreshes
each claim it holds every ``HEARTBEAT_S``; stale after ``STALE_S``). Taking over is itself atomic:
a rename that only one run can make (file system), or a write conditional on the stale claim's
ETag (object storage). A run that finds its own claim taken over does not publish that log.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import shutil
import socket
import tempfile
import threading
import time
import uuid
from dataclasses import asdict, dataclass

from upath import UPath

from ncore_convert.paths import is_local
from ncore_convert.storage import precondition_failed

#: How often a run refreshes the claims it holds (seconds; NCORE_CONVERT_HEARTBEAT_S overrides).
HEARTBEAT_S = float(os.environ.get("NCORE_CONVERT_HEARTBEAT_S", "15"))
#: A claim not refreshed for this long belongs to a run that is gone (judged from another host).
STALE_S = 6 * HEARTBEAT_S


@dataclass(frozen=True)
class Holder:
    """The run that holds a claim."""

    run_id: str
    host: str
    pid: int
    pid_started: str | None  #: the process's start time (``/proc/<pid>/stat``), against pid reuse

    def describe(self) -> str:
        return f"run {self.run_id} on {self.host}, pid {self.pid}"


def claim_path(output_root: UPath, log_id: str) -> UPath:
    return output_root / f".{log_id}.claim"


#: A log's unfinished folder written by a run (``runner.convert_one``): ``.<log_id>.<run_id>.partial``.
_PARTIAL = re.compile(r"^\.(?P<log>.+)\.(?P<run>[0-9a-f]{12})\.partial$")


def _process_started(pid: int) -> str | None:
    """A process's start time in clock ticks since boot (Linux), None where it cannot be read."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _process_exists(holder: Holder) -> bool:
    try:
        os.kill(holder.pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        pass
    started = _process_started(holder.pid)
    return holder.pid_started is None or started is None or started == holder.pid_started


def _alive(holder: Holder, age_s: float) -> bool:
    """Whether a claim's (or a temporary file's) writer still runs: on this host, its process;
    elsewhere, judged by the age of what it wrote."""
    if holder.host == socket.gethostname():
        return _process_exists(holder)
    return age_s < STALE_S


#: The prefix of a log's local staging folder (output on object storage), in the system's temp folder.
STAGING_PREFIX = "ncore-convert-staging."
_WRITER = re.compile(r"\.w-(?P<host>[^/]+)-(?P<pid>\d+)-(?P<started>\d+|x)-[0-9a-f]{8}\.")


def writer_tag() -> str:
    """A name part for a temporary file or folder: ``.w-<host>-<pid>-<start time>-<random>.``, from
    which a later run judges whether its writer is gone (:func:`writer_gone`)."""
    pid = os.getpid()
    return f".w-{socket.gethostname()}-{pid}-{_process_started(pid) or 'x'}-{uuid.uuid4().hex[:8]}."


def writer_gone(path: str) -> bool:
    """Whether the process that named ``path`` with :func:`writer_tag` is gone (False for other names)."""
    found = _WRITER.search(os.path.basename(path))
    if found is None:
        return False
    try:
        age_s = max(0.0, time.time() - os.lstat(path).st_mtime)
    except FileNotFoundError:
        return False
    started = None if found["started"] == "x" else found["started"]
    return not _alive(Holder("", found["host"], int(found["pid"]), started), age_s)


class Claims:
    """The claims of one run on one output folder; a heartbeat thread refreshes those it holds.

    Use as a context manager: leaving it stops the heartbeat and releases every claim still held.
    """

    def __init__(self, output_root: UPath, run_id: str | None = None) -> None:
        self.root = output_root
        pid = os.getpid()
        self.me = Holder(run_id or uuid.uuid4().hex[:12], socket.gethostname(), pid, _process_started(pid))
        self._held: dict[str, str | None] = {}  #: log id -> the claim's ETag (object storage) or None
        self._lost: set[str] = set()
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._heartbeat = threading.Thread(target=self._beat, daemon=True, name="claims-heartbeat")
        self._heartbeat.start()

    def __enter__(self) -> Claims:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Stop the heartbeat and release every claim held; a claim taken after this (a thread
        that was starting a log as the run stopped) is given up at once (:meth:`_took`)."""
        with self._lock:
            self._closed.set()
            held = list(self._held)
        for log_id in held:
            self.release(log_id)

    # --- the run's side ---
    def acquire(self, log_id: str) -> Holder | None:
        """Claim a log: None when this run now holds it, else the live run that does."""
        path = claim_path(self.root, log_id)
        holder = None
        for _ in range(5):  # a claim may vanish or change between the steps: look again
            token = self._create(path)
            if token is not False:
                return self._took(log_id, token)
            found = self._read(path)
            if found is None:
                continue
            holder, age_s, token = found
            if holder.run_id == self.me.run_id:  # our own (a retried task of this run)
                return self._took(log_id, token)
            if _alive(holder, age_s):
                return holder
            token = self._take_over(path, holder, token)
            if token is not False:
                return self._took(log_id, token)
        return holder or self.me

    def holds(self, log_id: str) -> bool:
        """Whether this run still holds the log (its claim was not taken over by another run)."""
        with self._lock:
            return log_id in self._held and log_id not in self._lost

    def release(self, log_id: str) -> None:
        """Give a log's claim up (only if it is still this run's)."""
        with self._lock:
            if log_id not in self._held:
                return
            token = self._held.pop(log_id)
            lost = log_id in self._lost
            self._lost.discard(log_id)
        if lost:
            return
        path = claim_path(self.root, log_id)
        with contextlib.suppress(FileNotFoundError, OSError):
            found = self._read(path)
            if found is not None and found[0] == self.me and (is_local(path) or found[2] == token):
                path.unlink()

    def _took(self, log_id: str, token: str | None) -> Holder | None:
        """Record a claim this run now holds (None); once the claims are closed, remove it again and
        answer as if held (``self.me``): the run is ending and starts no log."""
        with self._lock:
            if not self._closed.is_set():
                self._held[log_id] = token
                self._lost.discard(log_id)
                return None
        with contextlib.suppress(OSError):
            claim_path(self.root, log_id).unlink()
        return self.me

    def _beat(self) -> None:
        while not self._closed.wait(HEARTBEAT_S):
            with self._lock:
                held = dict(self._held)
            for log_id, token in held.items():
                self._refresh(log_id, token)

    def _refresh(self, log_id: str, token: str | None) -> None:
        path = claim_path(self.root, log_id)
        try:
            if is_local(path):
                found = self._read(path)
                if found is None or found[0] != self.me:
                    raise FileNotFoundError(path)
                os.utime(path.path)
                return
            new = self._write(path, token)
        except (OSError, ValueError):
            with self._lock:
                if log_id in self._held:
                    self._lost.add(log_id)
            return
        with self._lock:
            if log_id in self._held:
                self._held[log_id] = new

    # --- storage ---
    def _text(self) -> bytes:
        return json.dumps({**asdict(self.me), "claimed": time.time()}).encode()

    def _read(self, path: UPath) -> tuple[Holder, float, str | None] | None:
        """(holder, seconds since its last heartbeat, ETag) of a claim; None if there is none. An
        unreadable claim counts as a holder that is gone once it is stale."""
        try:
            path.fs.invalidate_cache(path.path)  # another process may have changed it
            info = path.fs.info(path.path)
            data = path.read_bytes()
        except FileNotFoundError:
            return None
        modified = info.get("mtime") or info.get("LastModified") or info.get("created") or 0
        modified_s = modified.timestamp() if hasattr(modified, "timestamp") else float(modified)
        age_s = max(0.0, time.time() - modified_s)
        try:
            fields = json.loads(data)
            holder = Holder(str(fields["run_id"]), str(fields["host"]), int(fields["pid"]), fields.get("pid_started"))
        except (ValueError, KeyError, TypeError):
            holder = Holder("unreadable", "", -1, None)  # never alive by process; stale by age
            age_s = age_s if age_s >= STALE_S else 0.0
        return holder, age_s, info.get("ETag")

    def _create(self, path: UPath) -> str | None | bool:
        """Create the claim if it does not exist: its ETag (None on a file system), or False."""
        if is_local(path):
            tmp = f"{path.path}{writer_tag()}tmp"
            try:
                with open(tmp, "wb") as f:
                    f.write(self._text())
                    f.flush()
                    os.fsync(f.fileno())
                return self._link(tmp, path)
            finally:  # also when the write failed (a full disk)
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(tmp)
        try:
            return self._write(path, None, create=True)
        except OSError as err:
            if precondition_failed(err):
                return False
            raise

    def _link(self, tmp: str, path: UPath) -> None | bool:
        """Hard-link a complete temporary claim to the claim's name: None, or False if it exists."""
        try:
            os.link(tmp, path.path)
            return None
        except FileExistsError:
            return False
        except OSError as err:
            if err.errno in (errno.ENOSPC, errno.EDQUOT):
                raise
            return self._create_exclusive(path)  # a file system without hard links (some FUSE and SMB mounts)

    def _create_exclusive(self, path: UPath) -> None | bool:
        """``O_CREAT | O_EXCL``: atomic on local file systems and NFSv3+; a reader may see the claim
        empty for a moment, which counts as held until it is stale (see :meth:`_read`)."""
        try:
            fd = os.open(path.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "wb") as f:
            f.write(self._text())
        return None

    def _write(self, path: UPath, token: str | None, create: bool = False) -> str | None:
        """Write this run's claim to an object: created only if absent, or replaced only if its ETag
        is still ``token``; returns the new ETag."""
        kwargs = {"mode": "create"} if create else ({"IfMatch": token} if token else {})
        out = path.fs.pipe_file(path.path, self._text(), **kwargs)
        return (out or {}).get("ETag") if isinstance(out, dict) else None

    def _take_over(self, path: UPath, stale: Holder, token: str | None) -> str | None | bool:
        """Replace a gone run's claim with this run's, atomically: False if another run was faster."""
        if not is_local(path):
            try:
                return self._write(path, token) if token else False
            except OSError as err:
                if precondition_failed(err) or isinstance(err, FileNotFoundError):
                    return False
                raise
        return self._create(path) if self._remove_stale(path, stale) else False

    def _remove_stale(self, path: UPath, stale: Holder) -> bool:
        """Remove a gone run's claim on a file system, atomically: False if it changed meanwhile."""
        aside = f"{path.path}{writer_tag()}stale"
        try:
            os.rename(path.path, aside)  # only one run moves a given file
        except FileNotFoundError:
            return False
        moved = self._read(UPath(aside))
        if moved is None or moved[0] != stale:  # we moved a newer claim: put it back, leave the log
            with contextlib.suppress(OSError):
                os.link(aside, path.path)
            os.unlink(aside)
            return False
        os.unlink(aside)
        return True

    # --- what dead runs left ---
    def remove_dead_leftovers(self) -> list[str]:
        """Remove what runs that are gone left in a local output folder (their claims, temporary
        files, and the ``.partial`` folders no live run with their run id holds the log of) and in
        this host's temp folder (staging folders); returns the names removed."""
        removed = []
        if is_local(self.root) and self.root.is_dir():
            entries = list(os.scandir(self.root.path))
            for entry in entries:  # claims first: a .partial is kept only for a live claim
                if entry.name.startswith(".") and entry.name.endswith(".claim") and self._claim_gone(entry.path):
                    removed.append(entry.name)
            live = self._live_claims()
            for entry in entries:
                if entry.name.startswith(".") and writer_gone(entry.path):
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(entry.path)
                        removed.append(entry.name)
                elif (partial := _PARTIAL.match(entry.name)) and (partial["log"], partial["run"]) not in live:
                    shutil.rmtree(entry.path, ignore_errors=True)
                    removed.append(entry.name)
        for entry in os.scandir(tempfile.gettempdir()):
            if entry.name.startswith(STAGING_PREFIX) and writer_gone(entry.path):
                shutil.rmtree(entry.path, ignore_errors=True)
                removed.append(entry.path)
        return removed

    def _claim_gone(self, path: str) -> bool:
        found = self._read(UPath(path))
        if found is None or found[0].run_id == self.me.run_id or _alive(found[0], found[1]):
            return False
        return self._remove_stale(UPath(path), found[0])

    def _live_claims(self) -> set[tuple[str, str]]:
        """(log id, run id) of every claim in the output folder (the gone ones are removed first)."""
        live = set()
        for entry in os.scandir(self.root.path):
            if entry.name.startswith(".") and entry.name.endswith(".claim"):
                found = self._read(UPath(entry.path))
                if found is not None:
                    live.add((entry.name[1 : -len(".claim")], found[0].run_id))
        return live
