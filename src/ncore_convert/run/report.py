"""``<output>/conversion-report.json``: per log status, seconds, bytes, warnings and errors, shared by
every run on the output folder.

A run merges its entries into the report as it finds it, never writes back what it read at its
start, so runs that share an output folder (see :mod:`~ncore_convert.run.claims`) keep each other's
entries. On a file system the merge holds an advisory lock (``flock`` on the output folder, or on
``.<report>.lock`` where a folder cannot be locked) and replaces the file atomically (a temporary
file of its own, renamed); on object storage it is a write conditional on the ETag it read,
retried when another run wrote in between.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import time
from datetime import UTC, datetime

from upath import UPath

from ncore_convert.paths import is_local
from ncore_convert.run.claims import writer_tag
from ncore_convert.storage import flush_to_disk, precondition_failed

REPORT_NAME = "conversion-report.json"
#: Conditional writes of the report on object storage tried before giving up.
MERGE_ATTEMPTS = 20


def report_name(shard: tuple[int, int] | None) -> str:
    """The run report's file name; each shard of an array job keeps its own report."""
    return REPORT_NAME if shard is None else f"conversion-report-shard-{shard[0]}-of-{shard[1]}.json"


def now_iso() -> str:
    return datetime.now(UTC).isoformat(timespec="seconds")


class RunReport:
    """The report of an output folder: entries of logs not touched by this run are kept, so the
    report describes the whole folder. Every :meth:`record` merges into the stored report."""

    def __init__(self, output_root: UPath, fingerprint: dict, name: str = REPORT_NAME) -> None:
        self.path = output_root / name
        self.fingerprint = json.loads(json.dumps(fingerprint))  # as it reads back (tuples become lists)
        self.logs: dict[str, dict] = self._read()[0]

    def previous(self, log_id: str) -> dict | None:
        return self.logs.get(log_id)

    def is_done(self, log_id: str, output_root: UPath) -> bool:
        """Converted (or skipped) with this fingerprint and still there."""
        entry = self.logs.get(log_id) or {}
        return (
            entry.get("status") in ("ok", "skipped")
            and entry.get("fingerprint") == self.fingerprint
            and (output_root / log_id).is_dir()
        )

    def ensure(self) -> None:
        """Write the report if there is none yet, so that a run that records nothing (stopped
        before its first log) still leaves the report its last line names."""
        if not self.path.exists():
            self._merge({})

    def refresh(self) -> None:
        """Read the stored report again (other runs may have recorded logs since)."""
        self.logs = self._read()[0]

    def record(self, result, input_bytes: int, output_bytes: int) -> None:
        """Merge the entry of one log's result (a ``runner.LogResult``) into the stored report."""
        entry = {
            "status": "skipped" if result.skipped else ("ok" if result.ok else "failed"),
            "seconds": round(result.seconds, 3),
            "input_bytes": input_bytes,
            "output_bytes": output_bytes,
            "warnings": result.warnings,
            "error": None if result.ok else {"file": result.error_file, "reason": result.error},
            "validation": result.summary.validation if result.summary is not None else result.validation,
            "reads": getattr(result.summary, "reads", None) or None,  # input requests and bytes (converted logs)
            "fingerprint": self.fingerprint,
            "finished": now_iso(),
        }
        if result.skipped:  # keep what the converting run measured
            previous = self.logs.get(result.log_id) or {}
            entry.update({k: previous.get(k) for k in ("seconds", "warnings", "validation")})
        self._merge({result.log_id: entry})

    # --- storage ---
    def _read(self) -> tuple[dict[str, dict], str | None]:
        """The stored entries and, on object storage, the ETag they were read at (an unreadable
        report reads as empty: nothing is skipped, everything is redone)."""
        for _ in range(MERGE_ATTEMPTS):
            try:
                etag = self._etag()
                text = self.path.read_text()
                if etag != self._etag():  # changed while read: read again
                    continue
            except FileNotFoundError:
                return {}, None
            except OSError as err:  # s3fs's FileExpired (EBUSY): another run replaced it while read
                if err.errno != errno.EBUSY:
                    raise
                continue
            try:
                logs = json.loads(text).get("logs", {})
            except (json.JSONDecodeError, AttributeError):
                logs = {}
            return (logs if isinstance(logs, dict) else {}), etag
        return {}, None

    def _etag(self) -> str | None:
        if is_local(self.path):
            return None
        self.path.fs.invalidate_cache(self.path.path)
        return self.path.fs.info(self.path.path).get("ETag")

    def _text(self, logs: dict[str, dict]) -> str:
        return json.dumps({"converter": self.fingerprint, "logs": logs}, indent=2)

    def _merge(self, updates: dict[str, dict]) -> None:
        if is_local(self.path):
            with self._locked():
                logs = {**self._read()[0], **updates}
                tmp = self.path.parent / f".{self.path.name}{writer_tag()}tmp"
                try:
                    tmp.write_text(self._text(logs))
                    flush_to_disk(tmp)
                    tmp.rename(self.path)
                finally:  # also when the write failed (a full disk)
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(tmp.path)
            self.logs = logs
            return
        for attempt in range(MERGE_ATTEMPTS):
            logs, etag = self._read()
            logs = {**logs, **updates}
            condition = {"IfMatch": etag} if etag else {"mode": "create"}
            try:
                self.path.fs.pipe_file(self.path.path, self._text(logs).encode(), **condition)
            except OSError as err:
                if not precondition_failed(err):
                    raise
                time.sleep(0.05 * (attempt + 1))  # another run wrote in between: merge again
                continue
            self.logs = logs
            return
        raise OSError(f"{self.path}: could not merge the report ({MERGE_ATTEMPTS} conditional writes refused)")

    @contextlib.contextmanager
    def _locked(self):
        """An exclusive ``flock`` on the output folder itself (no lock file is left), or on
        ``.<report>.lock`` where a folder cannot be locked (some network file systems)."""
        fd = os.open(self.path.parent.path, os.O_RDONLY | os.O_DIRECTORY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            os.close(fd)
            fd = os.open(os.path.join(self.path.parent.path, f".{self.path.name}.lock"), os.O_RDWR | os.O_CREAT, 0o644)
            fcntl.flock(fd, fcntl.LOCK_EX)
        try:
            yield
        finally:
            os.close(fd)
