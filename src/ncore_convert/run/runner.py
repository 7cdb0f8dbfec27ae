"""Runs per-log conversion tasks: atomic output directories, progress, per-log error isolation,
resumable runs and a run report.

Each log is written into ``<output>/.<log_id>.partial``, flushed to disk, and renamed to
``<output>/<log_id>`` only once complete, so an interrupted run (or a power loss) never leaves a
sequence that looks finished. ``<output>/conversion-report.json`` is rewritten atomically after
every log; a rerun skips the logs it records as converted by the same converter version with the
same options.
"""

from __future__ import annotations

import errno
import json
import re
import shutil
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Literal, Protocol

from tqdm import tqdm
from upath import UPath

from ncore_convert.contract import SAFE_NAME
from ncore_convert.errors import SourceError, UsageError, ValidationFailed
from ncore_convert.run.pool import Progress
from ncore_convert.storage import flush_to_disk, is_local, publish, remove_tree


class Summary(Protocol):
    warnings: list[str]
    validation: dict | None  #: ``validate.report.summarise`` of the log's output, when validated

    def line(self) -> str: ...


#: task(sequence_dir, log_id, progress=Progress, pool=JobPool | None) -> Summary: converts one log
#: into sequence_dir. A module-level function or a partial of one: it is shipped to worker processes
#: and Ray nodes.
LogTask = Callable[..., Summary]

#: convert(sequence_dir, log_id, progress) -> Summary: a task bound to where it runs (see executors).
ConvertFn = Callable[[UPath, str, Progress], Summary]


REPORT_NAME = "conversion-report.json"
#: Write errors that mean the output storage is full (or a file may not grow): no space, quota, size limit.
OUTPUT_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def report_name(shard: tuple[int, int] | None) -> str:
    """The run report's file name; each shard of an array job keeps its own report."""
    return REPORT_NAME if shard is None else f"conversion-report-shard-{shard[0]}-of-{shard[1]}.json"


def shard_logs(log_ids: list[str], shard: tuple[int, int] | None) -> list[str]:
    """Shard I of N: every N-th log of the sorted list, starting at I (all logs without a shard)."""
    if shard is None:
        return log_ids
    index, count = shard
    return [log for i, log in enumerate(sorted(log_ids)) if i % count == index]


Mode = Literal["resume", "overwrite", "retry-failed"]


@dataclass
class LogResult:
    log_id: str
    ok: bool
    summary: Summary | None = None
    error: str | None = None
    error_file: str | None = None  #: the input file at fault, when known
    skipped: bool = False
    seconds: float = 0.0
    validation: dict | None = None  #: of a log that failed validation (a converted log's is in its summary)
    traceback: str | None = None  #: of a failure, also from a worker process (printed with --verbose)
    usage_error: bool = False  #: failed because an option cannot apply to this log (the command exits 2)
    failure_warnings: list[str] | None = None  #: the warnings a failed log gave before it failed

    @property
    def warnings(self) -> list[str]:
        return list(self.summary.warnings) if self.summary is not None else list(self.failure_warnings or [])


def _origin(err: BaseException) -> str:
    """file:line where an exception was raised, also when it was raised in a worker process
    (concurrent.futures attaches the worker's formatted traceback as the cause)."""
    remote = re.findall(r'File "([^"]+)", line (\d+)', str(err.__cause__)) if err.__cause__ else []
    if remote:
        return ":".join(remote[-1])
    where = traceback.extract_tb(err.__traceback__)[-1]
    return f"{where.filename}:{where.lineno}"


def convert_one(
    output_root: UPath, log_id: str, convert: ConvertFn, show_progress: bool = True, bar_position: int = 0
) -> LogResult:
    """Convert one log atomically; errors are caught and returned as a one-line message.

    The log is written to ``<output_root>/.<log_id>.partial`` (on a local output) or to a local
    staging folder (on an object store), and moved into ``<output_root>/<log_id>`` only once
    complete (see :func:`~ncore_convert.storage.publish`).
    """
    started = time.perf_counter()
    if not SAFE_NAME.match(log_id):  # sources check the names they list; this guards every other caller
        return LogResult(log_id, False, error=f"{log_id!r} is not a safe output folder name; nothing written")
    final = output_root / log_id
    staging = None if is_local(output_root) else tempfile.mkdtemp(prefix=f"ncore-convert-{log_id[:40]}-")
    work = output_root / f".{log_id}.partial" if staging is None else UPath(staging) / log_id
    remove_tree(work)
    bar = tqdm(
        desc=log_id[:36],
        unit="frame",
        disable=not show_progress,
        leave=False,
        dynamic_ncols=True,
        position=bar_position,
    )
    try:
        summary = convert(work, log_id, Progress(bar.update, lambda n: bar.reset(total=n)))
        publish(work, final)
        result = LogResult(log_id, True, summary=summary)
    except Exception as err:  # noqa: BLE001 - one log's failure must not stop the others
        result = _failure(log_id, err, final)
    finally:
        bar.close()
        remove_tree(work)
        if staging is not None:
            shutil.rmtree(staging, ignore_errors=True)
    result.seconds = time.perf_counter() - started
    return result


def _failure(log_id: str, err: Exception, output: UPath) -> LogResult:
    """A failed log's result, in one line: the file and the cause (bad input), the failed checks
    (validation), the output that could not be written (a full disk), or the error and where it was
    raised. In every case nothing was published."""
    if isinstance(err, SourceError):
        result = LogResult(log_id, False, error=str(err), error_file=err.path)
    elif isinstance(err, UsageError):
        result = LogResult(log_id, False, error=f"usage: {err}", usage_error=True)
    elif isinstance(err, ValidationFailed):
        result = LogResult(log_id, False, error=str(err), validation=err.validation)
    elif isinstance(err, OSError) and err.errno in OUTPUT_FULL:
        cause = f"{err.strerror or errno.errorcode[err.errno]} [{errno.errorcode[err.errno]}]"
        result = LogResult(log_id, False, error=f"{output}: output not written ({cause}); nothing published")
    else:
        result = LogResult(log_id, False, error=f"{type(err).__name__}: {err} (at {_origin(err)})")
    result.error = " ".join(result.error.split("\n")).strip()
    result.failure_warnings = list(getattr(err, "log_warnings", []))  # errors.warnings_kept
    result.traceback = "".join(traceback.format_exception(err))
    return result


def tree_bytes(path: UPath) -> int:
    """Total size of the files under ``path`` (0 if it does not exist)."""
    if not path.exists():
        return 0
    if path.is_file():
        return path.stat().st_size
    return int(path.fs.du(path.path, total=True))


class RunReport:
    """``<output>/conversion-report.json``: per log status, seconds, bytes, warnings and errors.

    Entries of logs not touched by this run are kept, so the report describes the whole output
    folder. It is rewritten atomically (temporary file + rename) after every log.
    """

    def __init__(self, output_root: UPath, fingerprint: dict, name: str = REPORT_NAME) -> None:
        self.path = output_root / name
        self.fingerprint = json.loads(json.dumps(fingerprint))  # as it reads back (tuples become lists)
        self.logs: dict[str, dict] = {}
        if self.path.exists():
            try:
                self.logs = json.loads(self.path.read_text()).get("logs", {})
            except (json.JSONDecodeError, AttributeError):
                self.logs = {}  # unreadable: nothing is skipped, everything is redone

    def previous(self, log_id: str) -> dict | None:
        return self.logs.get(log_id)

    def is_done(self, log_id: str, output_root: UPath) -> bool:
        entry = self.logs.get(log_id) or {}
        return (
            entry.get("status") in ("ok", "skipped")
            and entry.get("fingerprint") == self.fingerprint
            and (output_root / log_id).is_dir()
        )

    def record(self, result: LogResult, input_bytes: int, output_bytes: int) -> None:
        entry = {
            "status": "skipped" if result.skipped else ("ok" if result.ok else "failed"),
            "seconds": round(result.seconds, 3),
            "input_bytes": input_bytes,
            "output_bytes": output_bytes,
            "warnings": result.warnings,
            "error": None if result.ok else {"file": result.error_file, "reason": result.error},
            "validation": result.summary.validation if result.summary is not None else result.validation,
            "fingerprint": self.fingerprint,
            "finished": datetime.now(UTC).isoformat(timespec="seconds"),
        }
        if result.skipped:  # keep what the converting run measured
            entry.update({k: self.logs[result.log_id].get(k) for k in ("seconds", "warnings", "validation")})
        self.logs[result.log_id] = entry
        self._write()

    def _write(self) -> None:
        text = json.dumps({"converter": self.fingerprint, "logs": self.logs}, indent=2)
        if not is_local(self.path):  # an object is replaced atomically when it is written
            self.path.write_text(text)
            return
        tmp = self.path.parent / f".{self.path.name}.tmp"
        tmp.write_text(text)
        flush_to_disk(tmp)
        tmp.rename(self.path)


class Executor(Protocol):
    """Where per-log tasks run (see :mod:`ncore_convert.run.executors`)."""

    def results(
        self, task: LogTask, output_root: UPath, log_ids: list[str], show_progress: bool
    ) -> Iterator[LogResult]:
        """Convert the logs (each with :func:`convert_one`); yield their results as they finish."""
        ...


def run_logs(
    output_root: UPath,
    log_ids: Iterable[str],
    task: LogTask,
    executor: Executor,
    echo: Callable[[str], None],
    show_progress: bool = True,
    fingerprint: dict | None = None,
    mode: Mode = "resume",
    input_dir: Callable[[str], UPath] | None = None,
    report_file: str = REPORT_NAME,
    verbose: bool = False,
) -> list[LogResult]:
    """Convert logs on ``executor``; print a one-line summary (or error) per log; keep the report;
    show an overall bar (done, failed, skipped, ETA) above the executor's per-log bars.

    Args:
        fingerprint: converter name, version and options; a log converted with the same
            fingerprint is skipped in ``resume`` mode.
        mode: ``resume`` skips logs already converted with this fingerprint; ``overwrite`` redoes
            every log; ``retry-failed`` redoes only the logs the last run reported as failed.
        input_dir: a log's source folder (for the input bytes in the report).
        report_file: the report's name in ``output_root`` (one per shard, see :func:`report_name`).
        verbose: print the traceback of each failed log under its one-line error.
    """
    output_root.mkdir(parents=True, exist_ok=True)
    report = RunReport(output_root, fingerprint or {}, report_file)
    log_ids = list(log_ids)
    overall = tqdm(total=len(log_ids), desc="logs", unit="log", disable=not show_progress, dynamic_ncols=True)
    counts = {"ok": 0, "failed": 0, "skipped": 0}
    results: list[LogResult] = []

    def finish(result: LogResult, lines: list[str]) -> None:
        input_bytes = tree_bytes(input_dir(result.log_id)) if input_dir else 0
        output_bytes = tree_bytes(output_root / result.log_id) if result.ok else 0
        with tqdm.external_write_mode():  # messages above the bars
            for line in lines:
                echo(line)
        report.record(result, input_bytes, output_bytes)
        counts["skipped" if result.skipped else ("ok" if result.ok else "failed")] += 1
        overall.set_postfix(counts, refresh=False)
        overall.update(1)
        results.append(result)

    todo = []
    for log_id in log_ids:
        if mode == "retry-failed" and (report.previous(log_id) or {}).get("status") != "failed":
            with tqdm.external_write_mode():
                echo(f"skip  {log_id}: not a failure of the last run")
            overall.update(1)  # its report entry stays as it was
        elif mode == "resume" and report.is_done(log_id, output_root):
            finish(
                LogResult(log_id, True, skipped=True),
                [f"skip  {log_id}: already converted with the same converter version and options"],
            )
        else:
            todo.append(log_id)
    if todo:
        for result in executor.results(task, output_root, todo, show_progress):
            if result.ok:
                lines = [f"ok    {result.summary.line()}"] + [f"      warning: {w}" for w in result.warnings]
                if (validation := result.summary.validation) is not None:
                    lines.append(f"      validated: {validation['checks']} checks passed")
            else:
                lines = [f"FAIL  {result.log_id}: {result.error}"]
                if verbose and result.traceback:
                    lines.append(result.traceback.rstrip())
            finish(result, lines)
    overall.close()
    order = {log_id: i for i, log_id in enumerate(log_ids)}
    return sorted(results, key=lambda r: order[r.log_id])  # in the order asked for
