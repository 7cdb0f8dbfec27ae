"""Command line: ``ncore-convert [GROUP OPTIONS] COMMAND [OPTIONS]``.

Group options (input/output roots, sensor selection) come before the dataset command, as in the
NCore converters; given after it, they are moved there (``cli_usage.hoist_group_options``). Every
dataset command builds its options (declared in :mod:`ncore_convert.cli_options`) and runs through
one path (:func:`_convert`) with the dataset's record (``converters.common.Dataset``),
found by the command in ``DATASET_PACKAGES``. The tool commands (:mod:`ncore_convert.cli_tools`:
``validate``, ``preview``, ``export-opencood``, ``evaluate-lidar-model``, ``synth``) need no
``--root-dir/--output-dir``.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from functools import partial
from typing import get_args

import click
from upath import UPath

from ncore_convert import __version__
from ncore_convert.cli_options import (
    NOISE_FLAGS,
    TBV_NO_LABEL,
    av2_family_options,
    noise_settings,
    off_flag,
    open_input,
    opencood_options,
)
from ncore_convert.cli_tools import (
    evaluate_lidar_model_command,
    export_opencood_command,
    preview_command,
    synth,
    validate_command,
)
from ncore_convert.cli_usage import ConverterGroup, DatasetCommand, make_output, pick_ids, unit_is_wrong, wrong_root
from ncore_convert.errors import SourceError
from ncore_convert.paths import is_local
from ncore_convert.run import stop
from ncore_convert.run.executors import ExecutorKind
from ncore_convert.run.pool import JobPool, default_workers
from ncore_convert.run.report import report_name
from ncore_convert.run.stop import STOPPED_EXIT
from ncore_convert.sources.argoverse2 import SPLITS as AV2_SPLITS
from ncore_convert.sources.reader import DEFAULT_RUN_BUDGET_MB, SPOOL_PREFIX, ReadSettings

#: The package each dataset command's converter lives in: its workers import it while the main
#: process starts up.
DATASET_PACKAGES = {
    "argoverse2-v4": "ncore_convert.converters.argoverse2",
    "tbv-v4": "ncore_convert.converters.argoverse2",
    "opv2v-v4": "ncore_convert.converters.opencood",
    "v2xset-v4": "ncore_convert.converters.opencood",
}


@dataclass(frozen=True)
class GroupOptions:
    root_dir: str | None
    output_dir: str | None
    camera_ids: tuple[str, ...] | None
    lidar_ids: tuple[str, ...] | None
    progress: bool
    workers: int
    mode: str
    shard: tuple[int, int] | None
    executor: ExecutorKind
    ray_address: str | None
    validate: bool
    verbose: bool
    anonymous: bool = False
    read_ahead_mb: int = DEFAULT_RUN_BUDGET_MB

    def require_paths(self) -> tuple[UPath, UPath]:
        if not self.root_dir:
            raise click.UsageError("--root-dir is required for conversion commands (give it before the command)")
        if not self.output_dir:
            raise click.UsageError("--output-dir is required for conversion commands (give it before the command)")
        root = open_input(self.root_dir, "--root-dir", self.anonymous)
        return root, UPath(self.output_dir)

    def make_executor(self, preload: list[str]):
        """The executor of this run (a context manager); local workers start here, in the background."""
        from ncore_convert.run.executors import LocalExecutor, RayExecutor

        if self.executor == "local":
            return LocalExecutor(JobPool(self.workers, preload=preload))  # its fork server imports meanwhile
        try:
            return RayExecutor(self.ray_address)
        except (ImportError, ConnectionError) as err:
            where = self.ray_address or "auto (RAY_ADDRESS or a cluster started on this machine)"
            raise click.UsageError(f"--executor ray, --ray-address {where}: {err}".replace("\n", " ")) from None


def _selection(ids: tuple[str, ...], disabled: bool) -> tuple[str, ...] | None:
    if disabled:
        return ()
    return ids or None


@click.group(cls=ConverterGroup, context_settings={"help_option_names": ["-h", "--help"], "show_default": True})
@click.version_option(__version__, prog_name="ncore-convert")
@click.option(
    "--root-dir",
    type=str,
    default=None,
    show_default="none; required by conversion commands",
    help="Dataset root (local path or fsspec URL).",
)
@click.option(
    "--output-dir",
    type=str,
    default=None,
    show_default="none; required by conversion commands",
    help="Where sequences are written, one folder per log.",
)
@click.option(
    "--camera-id", "camera_ids", multiple=True, show_default="all", help="Convert only this camera (repeatable)."
)
@off_flag("--no-cameras", help="Convert no cameras.")
@click.option(
    "--lidar-id", "lidar_ids", multiple=True, show_default="all", help="Convert only this lidar (repeatable)."
)
@off_flag("--no-lidars", help="Convert no lidars.")
@click.option(
    "--progress/--no-progress",
    default=None,
    show_default="on when stderr is a terminal",
    help="Show progress bars (on stderr). Off, only the per-log summary lines are printed: no cursor escapes"
    " in CI or batch logs.",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    default=None,
    show_default="the number of CPUs",
    help="Local worker processes: a log per worker when there are enough logs, else a log's stores (per sensor)"
    " spread over them. Not used with --executor ray.",
)
@off_flag("--overwrite", help="Reconvert logs that a previous run already converted with the same version and options.")
@off_flag("--retry-failed", help="Convert only the logs that the last run (conversion-report.json) reported as failed.")
@click.option(
    "--shard",
    type=str,
    default=None,
    show_default="none: every log",
    help="I/N: convert only every N-th log of the sorted list, starting at I (array jobs without Ray).",
)
@click.option(
    "--executor",
    type=click.Choice(get_args(ExecutorKind)),
    default="local",
    help="Where logs run: this machine's worker processes, or the tasks of an existing Ray cluster.",
)
@click.option(
    "--ray-address",
    type=str,
    default=None,
    show_default="RAY_ADDRESS, else a cluster started on this machine",
    help="host:port of the Ray head node (with --executor ray).",
)
@click.option(
    "--validate/--no-validate",
    default=True,
    help="Validate each converted log (the checks of 'ncore-convert validate --source', against --root-dir)"
    " before publishing it; a log that fails is not published and counts as failed.",
)
@off_flag("--verbose", "-v", help="Print the traceback of each failed log under its one-line error.")
@off_flag(
    "--anonymous",
    help="Read the input (--root-dir, validate --source) without credentials, as a public bucket allows"
    " (s3fs anon=True). The output is always written with your credentials.",
)
@click.option(
    "--read-ahead-mb",
    type=click.IntRange(min=1),
    default=DEFAULT_RUN_BUDGET_MB,
    help="Input bytes the run's processes on this machine hold fetched ahead, in total (each process an"
    " equal share; each Ray task all of it).",
)
@click.pass_context
def cli(
    ctx,
    root_dir,
    output_dir,
    camera_ids,
    no_cameras,
    lidar_ids,
    no_lidars,
    progress,
    workers,
    overwrite,
    retry_failed,
    shard,
    executor,
    ray_address,
    validate,
    verbose,
    anonymous,
    read_ahead_mb,
):
    """Convert autonomous-driving datasets to NVIDIA NCore V4 sequences.

    The options below are group options: they come before the dataset command, e.g.
    'ncore-convert --root-dir /data/av2 --output-dir /out --workers 4 argoverse2-v4 --split val'
    (given after it, they are moved there).

    Every dataset command also takes the options that shape the output for its consumers
    (3DGUT, 3DGRT, instant-nurec, NuRec; docs/consumers.md):

    \b
      --preset ncore|3dgut|3dgrt|nurec|instant-nurec  (sets the ones below)
      --camera-model ideal-pinhole|opencv-pinhole|ftheta
      --class-names ncore|source
      --cuboid-label-source auto|external|gt-synthetic|autolabel
      --seek-sec S --duration-sec D
      --world-global-mode none|identity|localized
      --lidar-rgb/--no-lidar-rgb
    """
    ctx.obj = GroupOptions(
        root_dir=root_dir,
        output_dir=output_dir,
        camera_ids=_selection(camera_ids, no_cameras),
        lidar_ids=_selection(lidar_ids, no_lidars),
        progress=sys.stderr.isatty() if progress is None else progress,
        workers=workers or default_workers(),
        mode="overwrite" if overwrite else ("retry-failed" if retry_failed else "resume"),
        shard=_parse_shard(shard),
        executor=executor,
        ray_address=ray_address,
        validate=validate,
        verbose=verbose,
        anonymous=anonymous,
        read_ahead_mb=read_ahead_mb,
    )
    if overwrite and retry_failed:
        raise click.UsageError("--overwrite and --retry-failed exclude each other")
    if ray_address and executor != "ray":
        raise click.UsageError("--ray-address needs --executor ray")


def _parse_shard(text: str | None) -> tuple[int, int] | None:
    if text is None:
        return None
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        raise click.UsageError(f"--shard {text}: expected I/N, e.g. 0/4") from None
    if not 0 <= index < count:
        raise click.UsageError(f"--shard {text}: need 0 <= I < N")
    return index, count


def _dataset(command: str):
    """The dataset record of a command (``converters.common.Dataset``), imported on demand: after the
    executor has started, so that its workers import the converter while this process does."""
    return importlib.import_module(DATASET_PACKAGES[command]).DATASETS[command]


def _convert(obj: GroupOptions, command: str, requested: tuple[str, ...], **option_values) -> None:
    """Run a dataset command: the requested logs or scenarios (all if none), each converted, validated
    (unless --no-validate) and published by the runner on the chosen executor. ``option_values``
    build the dataset's options (with the group's sensor selection)."""
    root, out = obj.require_paths()
    report_file = report_name(obj.shard)

    def last_lines(results: list, signal_name: str) -> list[str]:
        stopped = f"{signal_name}: run stopped; the report lists every log it published (exit {STOPPED_EXIT})"
        return [_counts(results) + f"; output and {report_file} in {out}", stopped]

    stop.set_farewell(partial(last_lines, []))  # a stop before the run loop: no log started
    with _run_reading(obj, root) as reading, obj.make_executor(preload=[DATASET_PACKAGES[command]]) as executor:
        from ncore_convert.run.runner import RunInterrupted, run_logs, shard_logs
        from ncore_convert.sources.reader import with_reader
        from ncore_convert.validate.tree import convert_and_validate

        dataset = _dataset(command)
        options = dataset.options(camera_ids=obj.camera_ids, lidar_ids=obj.lidar_ids, **option_values)
        try:
            dataset.check_sensors(options)
            available = dataset.list_ids(root, options)
        except (ValueError, SourceError) as err:
            hint = wrong_root(command, root) if isinstance(err, SourceError) else None
            raise click.UsageError(f"{err}; {hint}" if hint else str(err)) from None
        todo = pick_ids(requested, available, dataset.ids_dir(root, options), dataset.noun)
        first = dataset.input_dir(root, options, todo[0]) if todo else None
        if first is not None and unit_is_wrong(command, first):
            hint = wrong_root(command, root) or f"{first} is not a {dataset.noun}"
            raise click.UsageError(f"{hint} ({command} reads {dataset.ids_dir(root, options)}/<{dataset.noun}>)")
        make_output(out)
        task = partial(dataset.convert, root, options=options)
        if obj.validate:
            task = partial(convert_and_validate, task, source_root=root)
        task = partial(with_reader, task, reading=reading)  # each log's reader, closed with the log
        fingerprint = {"name": "ncore-convert", "version": __version__, "command": command}
        fingerprint["options"] = asdict(options)
        try:
            results = run_logs(
                out,
                shard_logs(todo, obj.shard),
                task,
                executor,
                echo=click.echo,
                show_progress=obj.progress,
                fingerprint=fingerprint,
                mode=obj.mode,
                input_dir=partial(dataset.input_dir, root, options),
                report_file=report_file,
                verbose=obj.verbose,
            )
        except OSError as err:  # the output storage itself fails (full, read-only): not even the report is kept
            raise click.ClickException(f"{out}: {err.strerror or err}; run stopped") from None
        except RunInterrupted as interrupted:
            # at once: every process of the run is killed, a log being planned in a thread is abandoned
            stop.end(last_lines(interrupted.results, interrupted.signal_name))
    click.echo(_counts(results) + f"; output and {report_file} in {out}")
    failed = sum(not r.ok for r in results)
    sys.exit(2 if any(r.usage_error for r in results) else 1 if failed else 0)


@contextlib.contextmanager
def _run_reading(obj: GroupOptions, root: UPath) -> Iterator[ReadSettings]:
    """The readers' settings for a run: each process's share of ``--read-ahead-mb``, and for a remote
    input converted on this machine the run's spool folder, where every process of a log finds the
    files its other jobs fetched. The folder is removed when the run ends, also when it is stopped
    (``stop.at_end``); each log's reader removes its own part of it when the log ends."""
    processes = 1 if obj.executor == "ray" else obj.workers + 1
    budget = max(1, obj.read_ahead_mb * 2**20 // processes)
    if is_local(root) or obj.executor == "ray":  # nothing spooled, or each Ray task keeps its own
        yield ReadSettings(budget)
        return
    spool_root = tempfile.mkdtemp(prefix=SPOOL_PREFIX)
    remove = partial(_remove_spool, spool_root)
    forget = stop.at_end(remove)
    try:
        yield ReadSettings(budget, spool_root)
    finally:
        remove()
        forget()


def _remove_spool(root: str) -> None:
    """Remove the run's spool even while threads of a stopping run still keep files: renamed first
    (a reader then finds no spool to keep into: it makes no parent folder), then removed, again if a
    file landed in it meanwhile."""
    gone = f"{root}.removed"
    try:
        os.rename(root, gone)
    except OSError:
        gone = root
    for _ in range(3):
        shutil.rmtree(gone, ignore_errors=True)
        if not os.path.exists(gone):
            return


def _counts(results: list) -> str:
    """The run's last line: converted, skipped, failed, and the logs never attempted (--retry-failed),
    left to other runs or abandoned."""
    left = sum(r.elsewhere is not None for r in results)
    abandoned = sum(r.abandoned for r in results)
    failed = sum(not r.ok and not r.abandoned for r in results)
    skipped = sum(r.skipped for r in results)
    not_attempted = sum(r.not_attempted for r in results)
    converted = len(results) - failed - skipped - left - abandoned - not_attempted
    return (
        f"{converted} converted, {skipped} skipped, {failed} failed"
        + (f", {not_attempted} never attempted" if not_attempted else "")
        + (f", {left} left to other runs on this output" if left else "")
        + (f", {abandoned} abandoned" if abandoned else "")
    )


def _convert_opencood(obj: GroupOptions, dataset: str, split: str, scenarios: tuple[str, ...], **options):
    """Run the OPV2V or V2XSet conversion of the selected scenarios."""
    flags = {param: options.pop(param) for _, param, _, _, _, _ in NOISE_FLAGS}
    noise = noise_settings(options.pop("noise_configs"), flags)

    _convert(obj, f"{dataset}-v4", scenarios, dataset=dataset, split=split, noise=noise, **options)


@cli.command("argoverse2-v4", cls=DatasetCommand)
@click.option("--split", type=click.Choice(AV2_SPLITS), required=True, help="Dataset split folder.")
@av2_family_options("of the split")
@click.pass_obj
def argoverse2_v4(obj: GroupOptions, split, log_ids, **options):
    """Argoverse 2 Sensor (<root>/<split>/<log_id>) to NCore V4."""
    _convert(obj, "argoverse2-v4", log_ids, split=split, **options)


@cli.command("tbv-v4", cls=DatasetCommand)
@av2_family_options("under the root", tbv=True)
@click.pass_obj
def tbv_v4(obj: GroupOptions, log_ids, **options):
    """Argoverse 2 TbV (<root>/<log_id>) to NCore V4; per-point times reconstructed (no offset_ns)."""
    if "dynamic" in options["camera_labels"] and options["dynamic_source"] == "annotations":
        raise click.BadParameter(
            f"dynamic: {TBV_NO_LABEL} (dynamic: from the lidar's movers, without --dynamic-source annotations)",
            param_hint="--camera-labels",
        )
    _convert(obj, "tbv-v4", log_ids, split=None, **options)


@cli.command("opv2v-v4", cls=DatasetCommand)
@opencood_options("opv2v")
@click.pass_obj
def opv2v_v4(obj: GroupOptions, split, scenarios, **options):
    """OPV2V (<root>/<split>/<scenario>/<agent_id>) to NCore V4: a sequence per agent, shared world_global."""
    _convert_opencood(obj, "opv2v", split, scenarios, **options)


@cli.command("v2xset-v4", cls=DatasetCommand)
@opencood_options("v2xset")
@click.pass_obj
def v2xset_v4(obj: GroupOptions, split, scenarios, **options):
    """V2XSet (OPV2V layout plus infrastructure agents with negative ids) to NCore V4."""
    _convert_opencood(obj, "v2xset", split, scenarios, **options)


for _command in (validate_command, preview_command, export_opencood_command, evaluate_lidar_model_command, synth):
    cli.add_command(_command)


def main() -> None:
    cli(auto_envvar_prefix="NCORE_CONVERT")
