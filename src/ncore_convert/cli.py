"""Command line: ``ncore-convert [GROUP OPTIONS] COMMAND [OPTIONS]``.

Group options (input/output roots, sensor selection) come before the dataset command, as in the
NCore converters. Every dataset command builds its options and runs through one path
(:func:`_convert`) with the dataset's record (``converters.common.Dataset``). Tool commands
(``validate``, ``preview``, ``evaluate-lidar-model``, ``synth``) need no ``--root-dir/--output-dir``.
Choices come from the ``Literal`` types the code uses.
"""

from __future__ import annotations

import sys
from dataclasses import asdict, dataclass
from functools import partial
from typing import get_args

import click
from click.core import ParameterSource
from upath import UPath

from ncore_convert import __version__
from ncore_convert.contract import (
    MANIFEST,
    PRESETS,
    CameraModel,
    ClassNames,
    CuboidLabelSource,
    Layout,
    LidarModelSource,
    Preset,
    Profile,
    StoreType,
    WorldGlobalMode,
)
from ncore_convert.errors import SourceError
from ncore_convert.run.executors import ExecutorKind
from ncore_convert.run.pool import JobPool, default_workers
from ncore_convert.sources.argoverse2 import SPLITS as AV2_SPLITS
from ncore_convert.sources.opencood import SPLITS as OPENCOOD_SPLITS
from ncore_convert.transforms.ego_mask import EgoBox
from ncore_convert.transforms.noise import ASYNC_MODES, DOFS, MODELS, PROCESSES

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

    def require_paths(self) -> tuple[UPath, UPath]:
        if not self.root_dir:
            raise click.UsageError("--root-dir is required for conversion commands (give it before the command)")
        if not self.output_dir:
            raise click.UsageError("--output-dir is required for conversion commands (give it before the command)")
        root = UPath(self.root_dir)
        if not root.is_dir():
            raise click.UsageError(f"--root-dir {self.root_dir}: directory not found")
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


def off_flag(*decls: str, help: str):
    """A boolean flag that is off unless given (documented as such in --help)."""
    return click.option(*decls, is_flag=True, default=False, show_default="off", help=help)


def _selection(ids: tuple[str, ...], disabled: bool) -> tuple[str, ...] | None:
    if disabled:
        return ()
    return ids or None


@click.group(context_settings={"help_option_names": ["-h", "--help"], "show_default": True})
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
):
    """Convert autonomous-driving datasets to NVIDIA NCore V4 sequences.

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


def store_options(f):
    """Store layout options shared by every dataset command."""
    for option in reversed(
        [
            click.option(
                "--store-type", type=click.Choice(get_args(StoreType)), default="itar", help="Zarr store container."
            ),
            click.option(
                "--profile",
                type=click.Choice(get_args(Profile)),
                default="separate-sensors",
                help="Component group layout: one store, one store per sensor, or also separate"
                " poses/intrinsics/masks/cuboids.",
            ),
            click.option(
                "--sequence-meta/--no-sequence-meta", default=True, help="Write <sequence_id>.json (sequence meta)."
            ),
        ]
    ):
        f = option(f)
    return f


def consumer_options(f):
    """Options every dataset command shares that shape the output for its consumers (docs/consumers.md)."""
    for option in reversed(
        [
            click.option(
                "--preset",
                type=click.Choice(get_args(Preset)),
                default="ncore",
                help="Set the options below as this consumer needs them (explicit flags still win): 3dgut, 3dgrt"
                " and nurec: an OpenCV pinhole and world_global at the identity; instant-nurec: f-theta cameras"
                " and AUTOLABEL cuboids; ncore: the defaults, as NCore's own converter writes. The run report"
                " and the converter metadata record the preset and what it resolved to.",
            ),
            click.option(
                "--camera-model",
                type=click.Choice(get_args(CameraModel)),
                default="ideal-pinhole",
                help="How cameras are stored: NCore's ideal pinhole; an OpenCV pinhole with zero distortion"
                " (the same rays; 3DGUT reads it); or an f-theta model fitted to the pinhole over the whole"
                " image (instant-nurec), its worst error in the camera's metadata.",
            ),
            click.option(
                "--class-names",
                type=click.Choice(get_args(ClassNames)),
                default="ncore",
                help="Cuboid class names: NCore's lowercase names (e.g. REGULAR_VEHICLE -> car), the source"
                " name of every track kept in the cuboids' metadata; or the dataset's own names.",
            ),
            click.option(
                "--cuboid-label-source",
                type=click.Choice(get_args(CuboidLabelSource)),
                default="auto",
                help="LabelSource of the cuboids: 'auto' is the dataset's honest one (AV2 EXTERNAL, OPV2V"
                " GT_SYNTHETIC); 'autolabel' is a compatibility setting for instant-nurec, not a provenance"
                " claim.",
            ),
            click.option(
                "--seek-sec",
                type=click.FloatRange(min=0.0),
                default=None,
                show_default="none: from the start",
                help="Skip this many seconds from the start of each log (its first sweep, image or frame).",
            ),
            click.option(
                "--duration-sec",
                type=click.FloatRange(min=0.0, min_open=True),
                default=None,
                show_default="none: to the end",
                help="Keep this many seconds from the seek point; lidar frames are kept whole or dropped.",
            ),
            click.option(
                "--lidar-rgb/--no-lidar-rgb",
                default=False,
                show_default="off",
                help="Colour every lidar point from the camera frame nearest its time (occlusion-tested, never"
                " from ego pixels): per-point generic data 'rgb', uint8 [N,3], which 3DGRUT seeds its colours"
                " from. AV2, TbV, OPV2V, V2XSet.",
            ),
            click.option(
                "--world-global-mode",
                type=click.Choice(get_args(WorldGlobalMode)),
                default="localized",
                help="What world -> world_global holds: the dataset's global frame ('localized'), the identity"
                " (scene at the origin for 3DGRUT), or no world_global node ('none'); the global pose is kept"
                " in the sequence metadata either way.",
            ),
        ]
    ):
        f = option(f)
    return f


def _ego_masks_option(ctx, param, value: str) -> str:
    if value in ("estimate", "none") or UPath(value).is_dir():
        return value
    raise click.BadParameter(f"{value!r} is neither 'estimate', 'none' nor a folder of <camera_id>.png masks")


def av2_family_options(log_scope: str):
    """Options shared by the Argoverse 2 Sensor and TbV commands."""

    def decorate(f):
        for option in reversed(
            [
                click.option(
                    "--log-id",
                    "log_ids",
                    multiple=True,
                    show_default=f"every log {log_scope}",
                    help="Convert only this log (repeatable).",
                ),
                store_options,
                consumer_options,
                click.option(
                    "--maps/--no-maps",
                    default=True,
                    help="Store the log's HD map (vector map, ground-height raster, Sim(2)) with the poses.",
                ),
                click.option(
                    "--ego-masks",
                    type=str,
                    default="estimate",
                    callback=_ego_masks_option,
                    metavar="estimate|none|DIR",
                    help="Camera masks named 'ego' (the ego vehicle's pixels): estimated from a sample of each"
                    " camera's own images; none; or DIR/<camera_id>.png (binary, the camera's size).",
                ),
                click.option(
                    "--ego-box-m",
                    type=float,
                    nargs=3,
                    default=EgoBox().dims_m,
                    show_default=True,
                    metavar="LENGTH WIDTH HEIGHT",
                    help="The nominal ego vehicle for the ego-mask prior (metres, around the rear-axle origin):"
                    " where the body can be in each camera, and which cameras must see it.",
                ),
                click.option(
                    "--lidar-model-source",
                    type=click.Choice(get_args(LidarModelSource)),
                    default="empirical",
                    help="'empirical': derive a VLP-32C row-offset model per unit and log and store each ray's"
                    " model element; 'none': raw per-point-time ray bundles only.",
                ),
            ]
        ):
            f = option(f)
        return f

    return decorate


def _pick(requested: tuple[str, ...], available: list[str], where: UPath, noun: str) -> list[str]:
    """The requested logs (or scenarios) in order, all available ones if none are requested."""
    if requested:
        unknown = [name for name in requested if name not in available]
        if unknown:
            raise click.UsageError(f"{noun}(s) not found under {where}: {', '.join(unknown)}")
        return list(dict.fromkeys(requested))
    if not available:
        raise click.UsageError(f"no {noun}s under {where}")
    return available


def _dataset(command: str):
    """The dataset record of a command (``converters.common.Dataset``), imported on demand: after the
    executor has started, so that its workers import the converter while this process does."""
    if DATASET_PACKAGES[command] == "ncore_convert.converters.argoverse2":
        from ncore_convert.converters.argoverse2 import DATASETS
    else:
        from ncore_convert.converters.opencood import DATASETS
    return DATASETS[command]


def _with_preset(option_values: dict) -> dict:
    """``option_values`` with the ``--preset``'s options in place of every one the user left at its
    default (a flag given on the command line, even at the default value, wins)."""
    ctx = click.get_current_context()
    chosen = {
        name: value
        for name, value in PRESETS[option_values["preset"]].items()
        if ctx.get_parameter_source(name) in (ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)
    }
    return {**option_values, **chosen}


def _convert(obj: GroupOptions, command: str, requested: tuple[str, ...], **option_values) -> None:
    """Run a dataset command: the requested logs or scenarios (all if none), each converted, validated
    (unless --no-validate) and published by the runner on the chosen executor. ``option_values``
    build the dataset's options (with the group's sensor selection)."""
    root, out = obj.require_paths()
    with obj.make_executor(preload=[DATASET_PACKAGES[command]]) as executor:
        from ncore_convert.run.runner import report_name, run_logs, shard_logs
        from ncore_convert.validate.tree import convert_and_validate

        dataset = _dataset(command)
        option_values = _with_preset(option_values)
        options = dataset.options(camera_ids=obj.camera_ids, lidar_ids=obj.lidar_ids, **option_values)
        try:
            dataset.check_sensors(options)
            available = dataset.list_ids(root, options)
        except (ValueError, SourceError) as err:
            raise click.UsageError(str(err)) from None
        todo = _pick(requested, available, dataset.ids_dir(root, options), dataset.noun)
        task = partial(dataset.convert, root, options=options)
        if obj.validate:
            task = partial(convert_and_validate, task, source_root=root)
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
                report_file=report_name(obj.shard),
                verbose=obj.verbose,
            )
        except OSError as err:  # the output storage itself fails (full, read-only): not even the report is kept
            raise click.ClickException(f"{out}: {err.strerror or err}; run stopped") from None
    failed = sum(not r.ok for r in results)
    skipped = sum(r.skipped for r in results)
    click.echo(
        f"{len(results) - failed - skipped} converted, {skipped} skipped, {failed} failed;"
        f" output and {report_name(obj.shard)} in {out}"
    )
    sys.exit(2 if any(r.usage_error for r in results) else 1 if failed else 0)


#: Flags equivalent to a ``wild_setting`` block: (flag, parameter, wild_setting key, type, default, help).
#: Unset flags take OpenCOOD's defaults (shown), set in ``make_setting``.
NOISE_FLAGS = [
    (
        "--noise-name",
        "noise_name",
        "name",
        str,
        "the model's name",
        "Name of the setting these flags make (its poses instance).",
    ),
    (
        "--noise-model",
        "noise_model",
        "model",
        click.Choice(MODELS),
        "opencood",
        "'opencood': OpenCOOD's draws exactly; 'realistic': independent per-agent streams.",
    ),
    ("--noise-seed", "noise_seed", "seed", int, "25, OpenCOOD's test seed", "seed."),
    ("--async/--no-async", "async_", "async", None, "off", "async: add communication delay."),
    (
        "--async-mode",
        "async_mode",
        "async_mode",
        click.Choice(ASYNC_MODES),
        "sim",
        "async_mode: 'sim' constant delay, 'real' U(0, overhead) + transmission + backbone.",
    ),
    ("--async-overhead", "async_overhead", "async_overhead", float, "0", "async_overhead, ms."),
    ("--backbone-delay", "backbone_delay", "backbone_delay", float, "0", "backbone_delay, ms (real mode)."),
    ("--data-size", "data_size", "data_size", float, "0", "data_size, Mb (real mode)."),
    (
        "--transmission-speed",
        "transmission_speed",
        "transmission_speed",
        float,
        "27",
        "transmission_speed, Mb/s (real mode).",
    ),
    ("--loc-err/--no-loc-err", "loc_err", "loc_err", None, "off", "loc_err: add localisation (GPS) error."),
    ("--xyz-std", "xyz_std", "xyz_std", float, "0", "xyz_std: position error std, m."),
    ("--ryp-std", "ryp_std", "ryp_std", float, "0", "ryp_std: angular error std, deg."),
    ("--max-cav", "max_cav", "max_cav", int, "7", "OpenCOOD's train_params.max_cav (opencood model)."),
    (
        "--gps-process",
        "gps_process",
        "process",
        click.Choice(PROCESSES),
        "white",
        "realistic: per-frame draws or Gauss-Markov drift.",
    ),
    (
        "--correlation-time-s",
        "correlation_time_s",
        "correlation_time_s",
        float,
        "10",
        "realistic: Gauss-Markov correlation time, s.",
    ),
    ("--bias-xyz-std", "bias_xyz_std", "bias_xyz_std", float, "0", "realistic: std of a constant position bias, m."),
    ("--bias-ryp-std", "bias_ryp_std", "bias_ryp_std", float, "0", "realistic: std of a constant angular bias, deg."),
    ("--gps-dof", "gps_dof", "dof", click.Choice(DOFS), "6dof", "realistic: perturb all 6 DoF or x, y and yaw."),
    (
        "--perturb-ego/--no-perturb-ego",
        "perturb_ego",
        "perturb_ego",
        None,
        "off",
        "realistic: perturb the OpenCOOD ego too.",
    ),
]


def noise_options(f):
    """``--noise-config`` (repeatable) and the flags that make one further setting (``NOISE_FLAGS``)."""
    for decl, param, _, kind, shown, help_text in reversed(NOISE_FLAGS):
        f = click.option(decl, param, type=kind, default=None, show_default=shown, help=help_text)(f)
    return click.option(
        "--noise-config",
        "noise_configs",
        multiple=True,
        metavar="FILE",
        show_default="none",
        help="YAML with an OpenCOOD wild_setting block (repeatable): GPS error and delay, written as a"
        " further poses instance named by its 'name' key or the file name.",
    )(f)


def noise_settings(noise_configs: tuple[str, ...], flags: dict) -> tuple:
    """The settings of the ``--noise-config`` files, then the one the flags make (if any flag is given)."""
    from ncore_convert.sources.noise_config import check_unique, make_setting, read_noise_config

    try:
        settings = [read_noise_config(UPath(path)) for path in noise_configs]
        given = {key: flags[param] for _, param, key, _, _, _ in NOISE_FLAGS if flags[param] is not None}
        if given:
            given.setdefault("name", given.get("model", "opencood"))
            try:
                settings.append(make_setting(given))
            except ValueError as err:
                raise ValueError(f"noise flags: {err}") from None
        check_unique(settings)
    except (SourceError, ValueError) as err:
        raise click.UsageError(str(err)) from None
    return tuple(settings)


def _convert_opencood(obj: GroupOptions, dataset: str, split: str, scenarios: tuple[str, ...], **options):
    """Run the OPV2V or V2XSet conversion of the selected scenarios."""
    flags = {param: options.pop(param) for _, param, _, _, _, _ in NOISE_FLAGS}
    noise = noise_settings(options.pop("noise_configs"), flags)

    _convert(obj, f"{dataset}-v4", scenarios, dataset=dataset, split=split, noise=noise, **options)


def opencood_options(dataset: str):
    """Options of the OPV2V and V2XSet commands."""

    def decorate(f):
        for option in reversed(
            [
                click.option(
                    "--split", type=click.Choice(OPENCOOD_SPLITS[dataset]), required=True, help="Dataset split folder."
                ),
                click.option(
                    "--scenario",
                    "scenarios",
                    multiple=True,
                    show_default="every scenario of the split",
                    help="Convert only this scenario (repeatable).",
                ),
                click.option(
                    "--layout",
                    type=click.Choice(get_args(Layout)),
                    default="agents",
                    help="'agents': one sequence per agent (rig = that agent) in <scenario>/<agent_id>/;"
                    " 'scenario': one sequence with every agent (frames and sensors prefixed agent<id>_).",
                ),
                click.option(
                    "--lidar-model-source",
                    type=click.Choice(get_args(LidarModelSource)),
                    default="empirical",
                    help="'empirical': the CARLA lidar's structured model from data_protocol.yaml, checked against"
                    " the data, and each ray's model element; 'none': raw rays only.",
                ),
                store_options,
                consumer_options,
                noise_options,
            ]
        ):
            f = option(f)
        return f

    return decorate


@cli.command("argoverse2-v4")
@click.option("--split", type=click.Choice(AV2_SPLITS), required=True, help="Dataset split folder.")
@av2_family_options("of the split")
@click.pass_obj
def argoverse2_v4(obj: GroupOptions, split, log_ids, **options):
    """Argoverse 2 Sensor (<root>/<split>/<log_id>) to NCore V4."""
    _convert(obj, "argoverse2-v4", log_ids, split=split, **options)


@cli.command("tbv-v4")
@av2_family_options("under the root")
@click.pass_obj
def tbv_v4(obj: GroupOptions, log_ids, **options):
    """Argoverse 2 TbV (<root>/<log_id>) to NCore V4; per-point times reconstructed (no offset_ns)."""
    _convert(obj, "tbv-v4", log_ids, split=None, **options)


@cli.command("opv2v-v4")
@opencood_options("opv2v")
@click.pass_obj
def opv2v_v4(obj: GroupOptions, split, scenarios, **options):
    """OPV2V (<root>/<split>/<scenario>/<agent_id>) to NCore V4: a sequence per agent, shared world_global."""
    _convert_opencood(obj, "opv2v", split, scenarios, **options)


@cli.command("v2xset-v4")
@opencood_options("v2xset")
@click.pass_obj
def v2xset_v4(obj: GroupOptions, split, scenarios, **options):
    """V2XSet (OPV2V layout plus infrastructure agents with negative ids) to NCore V4."""
    _convert_opencood(obj, "v2xset", split, scenarios, **options)


@cli.command("validate")
@click.argument("path", type=click.Path(exists=True))
@click.option(
    "--source",
    "source_root",
    type=str,
    default=None,
    show_default="none: no source comparison",
    help="The dataset root the sequences were converted from (the converter's --root-dir): also"
    " compare frames, points, images and cuboids with it.",
)
@click.option(
    "--json",
    "json_file",
    type=click.Path(dir_okay=False, writable=True),
    show_default="none",
    help="Also write every check of every sequence to this JSON file.",
)
@off_flag("--details", help="Print every check with its detail, not only the failed ones.")
def validate_command(path, source_root, json_file, details):
    """Check converted sequences and cooperative scenarios (PATH: a <sequence_id>.json, a scenario.json
    (its folder), or an output folder to search).

    Prints a table (one row per sequence or scenario.json), each failed check, and exits 1 if any
    check failed.
    """
    import json

    from ncore_convert.validate.tree import validate_tree

    if source_root is not None and not UPath(source_root).is_dir():
        raise click.UsageError(f"--source {source_root}: directory not found")
    reports = validate_tree(UPath(path), UPath(source_root) if source_root else None)
    if not reports:
        raise click.UsageError(f"no sequence meta (<sequence_id>.json) under {path}")
    width = max(len(r.sequence) for r in reports)
    click.echo(f"{'result':6}  {'checks':>6}  {'failed':>6}  {'file':{width}}")
    for report in reports:
        failed = sum(not c.ok for c in report.checks)
        click.echo(f"{'ok' if report.ok else 'FAIL':6}  {len(report.checks):6}  {failed:6}  {report.sequence}")
        for check in report.checks:
            if details or not check.ok:
                click.echo(f"{'':8}{'' if check.ok else 'FAIL '}{check.name}: {check.detail}")
    if json_file:
        UPath(json_file).write_text(json.dumps([r.to_dict() for r in reports], indent=2))
    failed = sum(not r.ok for r in reports)
    click.echo(f"{len(reports) - failed} passed, {failed} failed")
    sys.exit(1 if failed else 0)


@cli.command("preview")
@click.argument("path", type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Folder for the PNGs.")
@click.option(
    "--frame",
    type=click.IntRange(min=0),
    default=None,
    show_default="the middle frame",
    help="Frame index: of the first lidar (a sequence), or of the frames all agents share (scenario.json).",
)
def preview_command(path, out_dir, frame):
    """PNGs of a converted sequence or cooperative scenario (PATH: <sequence_id>.json or scenario.json).

    A sequence: lidar points projected into every camera (coloured by range, motion-aware) and a
    bird's-eye view with cuboids and the ego trajectory. A scenario.json: every agent in one
    bird's-eye view of world_global, with each noisy poses instance beside the ground truth.
    """
    from ncore_convert.preview import preview_scenario, preview_sequence

    try:
        if UPath(path).name == MANIFEST:
            written = [preview_scenario(UPath(path), UPath(out_dir), frame)]
        else:
            result = preview_sequence(UPath(path), UPath(out_dir), frame)
            written = [result.bev] + [p.png for p in result.cameras]
    except ValueError as err:
        raise click.UsageError(str(err)) from None
    for png in written:
        click.echo(f"wrote {png}")


@cli.command("export-opencood")
@click.argument("scenario", type=click.Path(exists=True, dir_okay=False))
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    required=True,
    help="Folder to write <scenario>/ into (OpenCOOD's layout).",
)
@click.option(
    "--poses",
    default=None,
    show_default="the ground truth",
    help="A stored noise setting whose lidar_pose the YAMLs get (then switch OpenCOOD's own"
    " wild_setting off, or the noise is applied twice).",
)
@click.pass_obj
def export_opencood_command(obj: GroupOptions, scenario, out_dir, poses):
    """Write a converted OPV2V / V2XSet scenario back in OpenCOOD's layout (SCENARIO: its scenario.json):
    <key>.yaml, <key>.pcd and <key>_camera<k>.png per agent, and data_protocol.yaml. A bar counts the
    agent-frames (with the group's --progress)."""
    from tqdm import tqdm

    from ncore_convert.validate.readback import read_manifest
    from ncore_convert.views.opencood_export import export_opencood

    if UPath(scenario).name != MANIFEST:
        raise click.UsageError(f"{scenario}: expected a {MANIFEST} (a converted OPV2V or V2XSet scenario)")
    total = sum(a.frames or 0 for a in read_manifest(UPath(scenario)).agents if a.written)  # the bar's length
    with tqdm(total=total, desc="agent-frames", unit="frame", disable=not obj.progress, dynamic_ncols=True) as bar:
        try:
            folder, counts = export_opencood(UPath(scenario), UPath(out_dir), poses, progress=bar.update)
        except ValueError as err:
            raise click.UsageError(str(err)) from None
    click.echo(f"wrote {counts.line(folder)}")


@cli.command("evaluate-lidar-model")
@click.argument("sequence", type=click.Path(exists=True, dir_okay=False))
@click.option("--lidar-id", "lidar_ids", multiple=True, show_default="every lidar", help="Evaluate only this lidar.")
@click.option(
    "--far-range-m", type=click.FloatRange(min=0.0), default=20.0, help="Rays beyond this count as far range."
)
@off_flag("--json", "as_json", help="Print the report as JSON.")
def evaluate_lidar_model_command(sequence, lidar_ids, far_range_m, as_json):
    """Compare each stored ray with the model ray of its model_element (SEQUENCE: <log_id>.json)."""
    import json

    from ncore_convert.evaluate import evaluate_lidar_model
    from ncore_convert.validate.readback import open_sequence

    loader = open_sequence(UPath(sequence)).loader
    unknown = sorted(set(lidar_ids) - set(loader.lidar_ids))
    if unknown:
        raise click.UsageError(f"lidar(s) {unknown} not in {sequence}; it has {loader.lidar_ids}")
    try:
        reports = [evaluate_lidar_model(loader, lidar, far_range_m) for lidar in (lidar_ids or loader.lidar_ids)]
    except ValueError as err:
        raise click.ClickException(f"{sequence}: {err}") from None
    if as_json:
        click.echo(json.dumps([r.to_dict() for r in reports], indent=2))
    else:
        for report in reports:
            click.echo("\n".join(report.lines()))


@cli.group()
def synth():
    """Write synthetic source logs with known ground truth (test data and demo source)."""


def synth_camera_options(f):
    """The camera-picture options of ``synth argoverse2`` and ``synth tbv``."""
    f = click.option(
        "--world",
        type=click.Choice(["pattern", "render"]),
        default="pattern",
        show_default=True,
        help="The pictures: a few textured pictures per camera, cycled (cheap); or each picture ray-cast"
        " from the scene the lidar sees at its own time, flat-shaded (one world: lidar colours can be"
        " checked against it; ~0.3 s per picture).",
    )(f)
    f = click.option(
        "--ego-body",
        type=click.Choice(["realistic", "easy", "glossy"]),
        default="realistic",
        show_default=True,
        help="The ego body in the cameras that see it: glossy paint with reflections,"
        " lighting changes, markings, glare and camouflaged silhouette stretches; still paint under ±5 %"
        " light; or the realistic body with strong reflections (75-95 % of the scene's contrast).",
    )(f)
    f = click.option(
        "--light",
        type=click.Choice(["day", "night"]),
        default="day",
        show_default=True,
        help="Daylight, or a night scene: a dark world lit by moving lamps, which the paint mirrors.",
    )(f)
    f = click.option(
        "--shadows/--no-shadows",
        default=False,
        show_default=True,
        help="Moving soft-edged shadows across the pictures, the body included.",
    )(f)
    f = click.option(
        "--pictures",
        type=click.IntRange(min=1),
        default=16,
        show_default=True,
        help="Distinct pictures per camera that its images cycle through (the ego-mask estimator samples"
        " 32 images per camera).",
    )(f)
    return click.option(
        "--parked-fraction",
        type=click.FloatRange(0.0, 1.0),
        default=0.0,
        help="The first part of the log (a fraction) in which the cameras' world stands still, as if parked"
        " (1: the whole log; tests the ego-mask fallback).",
    )(f)


@synth.command("argoverse2")
@click.option(
    "--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Split folder to write the log into."
)
@click.option("--seconds", type=click.FloatRange(min=0.1), default=2.0, help="Log duration (10 sweeps per second).")
@click.option("--seed", type=int, default=0, help="Random seed (scene, trajectory, log id).")
@off_flag(
    "--swap-lidar-halves",
    help="Give up_lidar the laser_number half >= 32 (proves the unit decision comes from the data).",
)
@click.option(
    "--camera-fps", type=click.FloatRange(min=0.0), default=20.0, help="Images per second per camera (0: none)."
)
@synth_camera_options
def synth_argoverse2(out_dir, seconds, seed, swap_lidar_halves, camera_fps, **camera_options):
    """A synthetic Argoverse 2 Sensor log: real schemas, two simulated VLP-32C units, cameras (with the
    ego body in five of them), cuboids."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    config = SynthConfig(
        seconds=seconds, seed=seed, swap_lidar_halves=swap_lidar_halves, camera_fps=camera_fps, **camera_options
    )
    truth = write_log(UPath(out_dir), config)
    click.echo(
        f"wrote {truth.log_dir}: {len(truth.sweeps)} sweeps,"
        f" {sum(len(s.offset_ns) for s in truth.sweeps)} points, {truth.n_images} images, {truth.n_cuboids} cuboids"
    )


@synth.command("tbv")
@click.option(
    "--out", "out_dir", type=click.Path(file_okay=False), required=True, help="TbV root to write the log into."
)
@click.option(
    "--seconds", type=click.FloatRange(min=0.1, max=120.0), default=2.0, help="Log duration (10 sweeps per second)."
)
@click.option("--seed", type=int, default=0, help="Random seed (scene, trajectory, log id).")
@click.option(
    "--camera-fps", type=click.FloatRange(min=0.0), default=20.0, help="Images per second per camera (0: none)."
)
@synth_camera_options
def synth_tbv(out_dir, seconds, seed, camera_fps, **camera_options):
    """A synthetic TbV log: flat layout, no offset_ns, 7 ring cameras (6 at half resolution; the ego body
    in three), no annotations."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    config = SynthConfig(seconds=seconds, seed=seed, camera_fps=camera_fps, tbv=True, **camera_options)
    truth = write_log(UPath(out_dir), config)
    click.echo(
        f"wrote {truth.log_dir}: {len(truth.sweeps)} sweeps,"
        f" {sum(len(s.offset_ns) for s in truth.sweeps)} points, {truth.n_images} images"
    )


def _synth_opencood(dataset: str):
    @synth.command(dataset, help=f"Synthetic {dataset.upper()} scenarios, written as OpenCDA writes them, with truth.")
    @click.option(
        "--out",
        "out_dir",
        type=click.Path(file_okay=False),
        required=True,
        help="Dataset root: writes <out>/<split>/<scenario>/<agent_id>/...",
    )
    @click.option("--split", type=click.Choice(OPENCOOD_SPLITS[dataset]), default="test", help="Split folder.")
    @click.option("--scenarios", type=click.IntRange(min=1), default=1, help="Number of scenarios.")
    @click.option(
        "--frames",
        type=click.IntRange(min=1),
        default=10,
        help="Frames per scenario (10 per second; 1: a one-tick scenario).",
    )
    @click.option("--cavs", type=click.IntRange(min=2), default=2, help="Connected vehicles per scenario.")
    @click.option(
        "--infrastructure",
        type=click.IntRange(min=0),
        default=1 if dataset == "v2xset" else 0,
        help="Infrastructure units per scenario.",
    )
    @click.option(
        "--lidar-columns",
        type=click.IntRange(min=16),
        default=720,
        help="Lidar azimuths per channel and tick (one tick is one revolution, as in OPV2V's 1016);"
        " data_protocol.yaml's points_per_second is written to match.",
    )
    @click.option(
        "--lidar-noise-stddev",
        type=click.FloatRange(min=0.0),
        default=0.0,
        help="CARLA's noise_stddev: range noise along each ray, m (OPV2V: 0.02).",
    )
    @click.option(
        "--lidar-dropoff-rate",
        type=click.FloatRange(0.0, 1.0),
        default=0.0,
        help="CARLA's dropoff_general_rate: share of points dropped at random (OPV2V: 0.1).",
    )
    @click.option("--seed", type=int, default=0, help="Random seed (scene, actor ids, scenario names).")
    def command(
        out_dir,
        split,
        scenarios,
        frames,
        cavs,
        infrastructure,
        lidar_columns,
        lidar_noise_stddev,
        lidar_dropoff_rate,
        seed,
    ):
        from ncore_convert.synth.opencood import SynthConfig, write_dataset

        config = SynthConfig(
            dataset=dataset,
            frames=frames,
            seed=seed,
            cavs=cavs,
            infrastructure=infrastructure,
            split=split,
            lidar_columns=lidar_columns,
            lidar_noise_stddev=lidar_noise_stddev,
            lidar_dropoff_rate=lidar_dropoff_rate,
        )
        for truth in write_dataset(UPath(out_dir), config, scenarios):
            click.echo(f"wrote {truth.scenario_dir}: agents {', '.join(truth.agents)}, {len(truth.keys)} frames")

    return command


synth_opv2v = _synth_opencood("opv2v")
synth_v2xset = _synth_opencood("v2xset")


def main() -> None:
    cli(auto_envvar_prefix="NCORE_CONVERT")
