"""Runs per-log conversion tasks: atomic output directories, progress, per-log error isolation,
resumable runs, runs that share an output folder, interruption, and a run report.

Each log is written into ``<output>/.<log_id>.<run_id>.partial``, flushed to disk, and renamed to
``<output>/<log_id>`` only once complete, so an interrupted run (or a power loss) never leaves a
sequence that looks finished. Before it writes a log, a run claims it (``run/claims.py``), so that
several runs on one output folder split the logs between them. ``<output>/conversion-report.json``
(``run/report.py``) is merged after every log; a rerun skips the logs it records as converted by the
same converter version with the same options. SIGINT or SIGTERM stops a run within seconds: it
starts no new log, abandons the logs in flight (nothing is published after the signal), records the
logs it did publish, and raises :class:`RunInterrupted`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from functools import partial
from typing import Literal, Protocol

from tqdm import tqdm
from upath import UPath

from ncore_convert.contract import SAFE_NAME
from ncore_convert.errors import SourceError, UsageError, ValidationFailed
from ncore_convert.paths import is_local
from ncore_convert.run import stop
from ncore_convert.run.claims import STAGING_PREFIX, Claims, writer_tag
from ncore_convert.run.pool import Progress
from ncore_convert.run.report import REPORT_NAME, RunReport
from ncore_convert.run.stop import deferred
from ncore_convert.storage import flush_to_disk, publish, remove_tree


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


#: Write errors that mean the output storage is full (or a file may not grow): no space, quota, size limit.
OUTPUT_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


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
    elsewhere: str | None = None  #: left to another run on the output folder, and why (not recorded)
    abandoned: bool = False  #: stopped unfinished by an interruption (not recorded; its .partial stays)
    failure_warnings: list[str] | None = None  #: the warnings a failed log gave before it failed
    kept_entry: bool = False  #: --retry-failed: converted by an earlier run (skipped; its entry stays)
    not_attempted: bool = False  #: --retry-failed: no earlier run attempted it (not converted, not recorded)

    @property
    def recorded(self) -> bool:
        """Whether the run's report records this result."""
        return self.elsewhere is None and not self.abandoned and not self.kept_entry and not self.not_attempted

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


class Abandoned(Exception):
    """A log stopped unfinished: the run was interrupted, or another run took its claim over."""


@dataclass
class RunControl:
    """What the logs of a run share on this machine: the stop signal, the claims, and the lock under
    which a log is published (an interruption takes it, so nothing is published after the signal).

    ``gate(log_id)``: called just before a log starts; None to convert it, else why this run leaves
    it to another (held by a live run, or converted by one meanwhile).
    """

    claims: Claims | None = None
    gate: Callable[[str], str | None] = lambda log_id: None
    stop: threading.Event = field(default_factory=threading.Event)
    publish_lock: threading.Lock = field(default_factory=threading.Lock)
    published: dict[str, LogResult] = field(default_factory=dict)  #: every log published, by id
    received: list[str] = field(default_factory=list)  #: the signals that stopped the run

    @contextlib.contextmanager
    def publishing(self, log_id: str):
        """Hold the publish lock; Abandoned if the run was stopped or lost the log's claim."""
        with self.publish_lock:
            if self.stop.is_set():
                raise Abandoned("the run was interrupted")
            if self.claims is not None and not self.claims.holds(log_id):
                raise Abandoned("another run took its claim over")
            yield


def convert_one(
    output_root: UPath,
    log_id: str,
    convert: ConvertFn,
    show_progress: bool = True,
    bar_position: int = 0,
    control: RunControl | None = None,
) -> LogResult:
    """Convert one log atomically; errors are caught and returned as a one-line message.

    The log is written to ``<output_root>/.<log_id>.<run_id>.partial`` (on a local output; the run's
    own folder, so that a run whose claim was taken over never writes where the new holder does;
    ``.<log_id>.partial`` without ``control``) or to a local staging folder (on an object store),
    and moved into ``<output_root>/<log_id>`` only once complete (see
    :func:`~ncore_convert.storage.publish`), under ``control``'s publish lock. A log the run
    abandons keeps its ``.partial`` folder; the next run to convert the log removes every one.
    """
    started = time.perf_counter()
    if not SAFE_NAME.match(log_id):  # sources check the names they list; this guards every other caller
        return LogResult(log_id, False, error=f"{log_id!r} is not a safe output folder name; nothing written")
    final = output_root / log_id
    staging = None if is_local(output_root) else tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{writer_tag()}")
    # a stop ends the process before this log's cleanup: the staged copy goes with it (the rerun redoes the log)
    forget_staging = stop.at_end(partial(shutil.rmtree, staging, ignore_errors=True)) if staging else None
    run_tag = f".{control.claims.me.run_id}" if control is not None and control.claims is not None else ""
    work = output_root / f".{log_id}{run_tag}.partial" if staging is None else UPath(staging) / log_id
    if staging is None:  # this run holds the log: unfinished folders of earlier runs go
        for old in _partials(output_root, log_id):
            remove_tree(old)
    remove_tree(work)
    bar = tqdm(
        desc=log_id[:36],
        unit="frame",
        disable=not show_progress,
        leave=False,
        dynamic_ncols=True,
        position=bar_position,
    )
    keep_work = False
    try:
        summary = convert(work, log_id, Progress(bar.update, lambda n: bar.reset(total=n)))
        if staging is None:
            flush_to_disk(work)  # the slow part of publishing, before the lock: under it, a rename
        with control.publishing(log_id) if control is not None else contextlib.nullcontext():
            publish(work, final, flushed=staging is None)
            result = LogResult(log_id, True, summary=summary)
            if control is not None:
                control.published[log_id] = result
    except (Abandoned, KeyboardInterrupt) as err:
        result, keep_work = LogResult(log_id, False, error=f"abandoned: {err}", abandoned=True), True
    except Exception as err:  # noqa: BLE001 - one log's failure must not stop the others
        keep_work = control is not None and control.stop.is_set()  # failed because the run stops
        result = _failure(log_id, err, final)
        result.abandoned = keep_work
    finally:
        bar.close()
        if not keep_work:
            remove_tree(work)
            if staging is not None:
                shutil.rmtree(staging, ignore_errors=True)
                forget_staging()
    result.seconds = time.perf_counter() - started
    return result


def _partials(output_root: UPath, log_id: str) -> list[UPath]:
    """The unfinished folders of a log in a local output: ``.<log_id>.partial`` and
    ``.<log_id>.<run_id>.partial`` (run ids: 12 hex digits), never another log's."""
    pattern = re.compile(rf"^\.{re.escape(log_id)}(\.[0-9a-f]{{12}})?\.partial$")
    if not output_root.is_dir():
        return []
    return [output_root / e.name for e in os.scandir(output_root.path) if e.is_dir() and pattern.match(e.name)]


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


def _input_bytes(result: LogResult, input_dir: Callable[[str], UPath] | None) -> int:
    """A log's input bytes: from the listings its conversion made (a remote input: no request
    more), else (local input) from its folder on disk; 0 when unknown."""
    listed = (getattr(result.summary, "reads", None) or {}).get("listed_bytes", 0)
    if listed or input_dir is None:
        return int(listed or 0)
    folder = input_dir(result.log_id)
    return tree_bytes(folder) if is_local(folder) else 0


def tree_bytes(path: UPath) -> int:
    """Total size of the files under ``path`` (0 if it does not exist)."""
    if not path.exists():
        return 0
    if path.is_file():
        return path.stat().st_size
    return int(path.fs.du(path.path, total=True))


class Executor(Protocol):
    """Where per-log tasks run (see :mod:`ncore_convert.run.executors`)."""

    def results(
        self, task: LogTask, output_root: UPath, log_ids: list[str], show_progress: bool, control: RunControl
    ) -> Iterator[LogResult]:
        """Convert the logs (each with :func:`convert_one`, after ``control.gate``); yield their
        results as they finish; return soon after ``control.stop`` is set."""
        ...

    def abandon(self) -> None:
        """Stop the work in flight at once (kill the worker processes, cancel the tasks)."""
        ...


class RunInterrupted(Exception):
    """SIGINT or SIGTERM stopped the run; ``results``: the logs it finished (published or failed)."""

    def __init__(self, signal_name: str, results: list[LogResult]) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name
        self.results = results


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

    Each log is claimed before it starts (:class:`~ncore_convert.run.claims.Claims`): a log another
    live run holds, or that one converted since this run started, is left to it (``elsewhere``).
    SIGINT/SIGTERM (:func:`~ncore_convert.run.stop.deferred`): the first one stops the run, which
    abandons its logs in flight, records what it published and raises :class:`RunInterrupted`.

    Args:
        fingerprint: converter name, version and options; a log converted with the same
            fingerprint is skipped in ``resume`` mode.
        mode: ``resume`` skips logs already converted with this fingerprint; ``overwrite`` redoes
            every log; ``retry-failed`` redoes only the logs the last run reported as failed.
        input_dir: a log's source folder (for the input bytes in the report).
        report_file: the report's name in ``output_root`` (one per shard, see ``run.report.report_name``).
        verbose: print the traceback of each failed log under its one-line error.
    """
    control = RunControl()
    with deferred(control.stop, control.received):  # from here on, a signal stops the run as below
        log_ids = list(log_ids)
        output_root.mkdir(parents=True, exist_ok=True)
        report = RunReport(output_root, fingerprint or {}, report_file)
        report.ensure()
        at_start = dict(report.logs)
        overall = tqdm(total=len(log_ids), desc="logs", unit="log", disable=not show_progress, dynamic_ncols=True)
        counts = {"ok": 0, "failed": 0, "skipped": 0}
        results: list[LogResult] = []

        def say(lines: list[str]) -> None:
            with tqdm.external_write_mode():  # messages above the bars
                for line in lines:
                    echo(line)

        def finish(result: LogResult, lines: list[str]) -> None:
            say(lines)
            if result.recorded:
                input_bytes = _input_bytes(result, input_dir)
                output_bytes = tree_bytes(output_root / result.log_id) if result.ok else 0
                report.record(result, input_bytes, output_bytes)
                counts["skipped" if result.skipped else ("ok" if result.ok else "failed")] += 1
            claims.release(result.log_id)  # after the report holds it: another run re-reads it
            overall.set_postfix(counts, refresh=False)
            overall.update(1)
            results.append(result)

        def gate(log_id: str) -> str | None:
            holder = claims.acquire(log_id)
            if holder is not None:
                return f"being converted by another run ({holder.describe()})"
            report.refresh()
            changed = report.previous(log_id) != at_start.get(log_id)  # another run recorded it since
            if report.is_done(log_id, output_root) and (mode == "resume" or changed):
                claims.release(log_id)
                return "converted by another run meanwhile"
            return None

        with Claims(output_root) as claims:
            control.claims, control.gate = claims, gate
            claims.remove_dead_leftovers()
            todo = []
            for log_id in log_ids:
                if control.stop.is_set():
                    break
                if (skip := _not_to_convert(report, output_root, log_id, mode)) is not None:
                    finish(*skip)
                else:
                    todo.append(log_id)
            for result in executor.results(task, output_root, todo, show_progress, control) if todo else ():
                if control.stop.is_set() and not result.ok:  # it failed because the run stops
                    result.abandoned = True
                finish(result, _lines(result, verbose))
                if control.stop.is_set():
                    break
            if control.stop.is_set():  # stop the work in flight, then record what was published before it
                say([f"{control.received[0]}: stopping; no new log starts, the logs in flight are abandoned"])
                with control.publish_lock:  # a publish under way ends first; none starts after
                    finished = {r.log_id for r in results}
                    published = [r for log_id, r in control.published.items() if log_id not in finished]
                executor.abandon()
                for result in published:
                    finish(result, _lines(result, verbose))
        overall.close()
    results = _in_order(results, log_ids)
    if control.received:
        raise RunInterrupted(control.received[0], results)
    return results


def _not_to_convert(
    report: RunReport, output_root: UPath, log_id: str, mode: Mode
) -> tuple[LogResult, list[str]] | None:
    """A log this run does not convert, with its line: converted already (resume), or, retrying
    the failures, converted by an earlier run or never attempted; None to convert it."""
    previous = (report.previous(log_id) or {}).get("status")
    if mode == "retry-failed" and previous in ("ok", "skipped"):
        return LogResult(log_id, True, skipped=True, kept_entry=True), [
            f"skip  {log_id}: converted by an earlier run, not a failure"
        ]
    if mode == "retry-failed" and previous != "failed":
        return LogResult(log_id, True, not_attempted=True), [
            f"skip  {log_id}: never attempted (run without --retry-failed to convert it)"
        ]
    if mode == "resume" and report.is_done(log_id, output_root):
        line = f"skip  {log_id}: already converted with the same converter version and options"
        return LogResult(log_id, True, skipped=True), [line]
    return None


def _lines(result: LogResult, verbose: bool) -> list[str]:
    """What the run prints of a finished log."""
    if result.elsewhere is not None:
        return [f"left  {result.log_id}: {result.elsewhere}"]
    if result.abandoned:
        return [f"stop  {result.log_id}: abandoned unfinished (its .partial folder is removed by the next run)"]
    if not result.ok:
        lines = [f"FAIL  {result.log_id}: {result.error}"]
        return lines + ([result.traceback.rstrip()] if verbose and result.traceback else [])
    lines = [f"ok    {result.summary.line()}"] + [f"      warning: {w}" for w in result.warnings]
    if (validation := result.summary.validation) is not None:
        lines.append(f"      validated: {validation['checks']} checks passed")
    return lines


def _in_order(results: list[LogResult], log_ids: list[str]) -> list[LogResult]:
    order = {log_id: i for i, log_id in enumerate(log_ids)}
    return sorted(results, key=lambda r: order[r.log_id])  # in the order asked for
