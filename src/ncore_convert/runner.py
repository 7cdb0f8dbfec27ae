"""Runs per-log conversion tasks: atomic output directories, progress, per-log error isolation.

Each log is written into ``<output>/.<log_id>.partial``, flushed to disk, and renamed to
``<output>/<log_id>`` only once complete, so an interrupted run (or a power loss) never leaves a
sequence that looks finished.
"""

from __future__ import annotations

import re
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

from tqdm import tqdm
from upath import UPath

from ncore_convert.sources.argoverse2 import SourceError
from ncore_convert.storage import flush_to_disk, remove_tree


class Summary(Protocol):
    warnings: list[str]

    def line(self) -> str: ...


#: convert(sequence_dir, log_id, on_frame, on_total) -> Summary
ConvertFn = Callable[[UPath, str, Callable[[int], None], Callable[[int], None]], Summary]


@dataclass
class LogResult:
    log_id: str
    ok: bool
    summary: Summary | None = None
    error: str | None = None


def _origin(err: BaseException) -> str:
    """file:line where an exception was raised, also when it was raised in a worker process
    (concurrent.futures attaches the worker's formatted traceback as the cause)."""
    remote = re.findall(r'File "([^"]+)", line (\d+)', str(err.__cause__)) if err.__cause__ else []
    if remote:
        return ":".join(remote[-1])
    where = traceback.extract_tb(err.__traceback__)[-1]
    return f"{where.filename}:{where.lineno}"


def convert_one(output_root: UPath, log_id: str, convert: ConvertFn, show_progress: bool = True) -> LogResult:
    """Convert one log atomically. Errors are caught and returned as a one-line message."""
    partial = output_root / f".{log_id}.partial"
    final = output_root / log_id
    remove_tree(partial)
    bar = tqdm(desc=log_id[:36], unit="frame", disable=not show_progress, leave=False, dynamic_ncols=True)

    def on_total(n: int) -> None:
        bar.reset(total=n)

    try:
        summary = convert(partial, log_id, bar.update, on_total)
    except SourceError as err:
        remove_tree(partial)
        return LogResult(log_id, False, error=str(err))
    except Exception as err:  # noqa: BLE001 - one log's failure must not stop the others
        remove_tree(partial)
        return LogResult(log_id, False, error=f"{type(err).__name__}: {err} (at {_origin(err)})".replace("\n", " "))
    finally:
        bar.close()
    flush_to_disk(partial)  # durable before it is renamed into place
    remove_tree(final)
    partial.rename(final)
    flush_to_disk(output_root)
    return LogResult(log_id, True, summary=summary)


def run_logs(
    output_root: UPath,
    log_ids: Iterable[str],
    convert: ConvertFn,
    echo: Callable[[str], None],
    show_progress: bool = True,
) -> list[LogResult]:
    """Convert logs one after another; print a one-line summary (or error) per log."""
    output_root.mkdir(parents=True, exist_ok=True)
    results = []
    for log_id in log_ids:
        result = convert_one(output_root, log_id, convert, show_progress)
        if result.ok:
            echo(f"ok    {result.summary.line()}")
            for warning in result.summary.warnings:
                echo(f"      warning: {warning}")
        else:
            echo(f"FAIL  {log_id}: {result.error}")
        results.append(result)
    return results
