"""Validation of an output folder: every sequence meta and ``scenario.json`` below it, and the
wrapper that validates each log the converter writes before it is published."""

from __future__ import annotations

import json
import time

from upath import UPath

from ncore_convert.contract import MANIFEST
from ncore_convert.errors import ValidationFailed
from ncore_convert.sources.reader import Reader, reading, with_reader
from ncore_convert.validate.coregister import check_coregistration
from ncore_convert.validate.report import Report, summarise
from ncore_convert.validate.sequence import RunJobs, validate_sequence


def validate_tree(
    path: UPath,
    source_root: UPath | None = None,
    relative_to: UPath | None = None,
    run_jobs: RunJobs | None = None,
    reader: Reader | None = None,
) -> list[Report]:
    """Validate a sequence meta, or every sequence and cooperative scenario (``scenario.json``:
    co-registration of its agents) below a folder (a ``scenario.json`` stands for its folder).
    Reports name their file relative to ``relative_to`` when given. With ``run_jobs`` (the
    converter's idle worker pool), each sequence's lidar frames are checked in the workers while
    the other checks run here. The source is read through ``reader`` (one made for the call if None)."""
    path = UPath(path)
    if path.name == MANIFEST:  # a cooperative scenario's manifest: the scenario's folder
        path = path.parent
    with reading(reader) as r:
        reports = [validate_sequence(meta, source_root, run_jobs, r) for meta in find_sequences(path)]
    if path.is_dir():
        reports += [check_coregistration(m) for m in sorted(path.rglob(MANIFEST), key=str) if _visible(m, path)]
    if relative_to is not None:
        for report in reports:
            report.sequence = str(UPath(report.sequence).relative_to(UPath(relative_to)))
    return reports


def find_sequences(path: UPath) -> list[UPath]:
    """A sequence meta file itself, or every sequence meta (``<sequence_id>.json``) below an output folder
    (unfinished ``.<log>.partial`` folders are skipped)."""
    path = UPath(path)
    if path.is_file():
        return [path]
    return sorted((p for p in path.rglob("*.json") if _visible(p, path) and _is_sequence_meta(p)), key=str)


def _visible(path: UPath, root: UPath) -> bool:
    return not any(part.startswith(".") for part in path.relative_to(root).parts)


def _is_sequence_meta(path: UPath) -> bool:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and "sequence_id" in data and "component_stores" in data


def convert_and_validate(
    task, sequence_dir: UPath, log_id: str, *, source_root: UPath | None = None, reader: Reader | None = None, **kwargs
):
    """A log task followed by :func:`validate_tree` of its output (with the source counts when
    ``source_root`` is given), both reading through the log's ``reader`` (one made for the call if
    None). Raises ValidationFailed, so the log is not published, on any failure."""
    return with_reader(_convert_and_validate, task, sequence_dir, log_id, source_root, reader=reader, **kwargs)


def _convert_and_validate(
    task, sequence_dir: UPath, log_id: str, source_root: UPath | None, *, reader: Reader, **kwargs
):
    summary = task(sequence_dir, log_id, reader=reader, **kwargs)
    started = time.perf_counter()
    run_jobs = kwargs["pool"].run if kwargs.get("pool") is not None else None  # the log's workers, idle now
    reports = validate_tree(sequence_dir, source_root, relative_to=sequence_dir, run_jobs=run_jobs, reader=reader)
    record = summarise(reports)
    record["seconds"] = round(time.perf_counter() - started, 3)
    if not record["ok"]:
        raise ValidationFailed(
            f"validation: {len(record['failed'])} of {record['checks']} checks failed, first: {record['failed'][0]}",
            record,
            summary.warnings,
        )
    summary.validation = record
    return summary
