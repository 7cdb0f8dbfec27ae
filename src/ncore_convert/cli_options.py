"""The dataset commands' options, each declared once (docs/cli.md): the store layout, the consumer
options (the preset resolves in ``converters.common.ConsumerOptions``, so library callers get it
too), the Argoverse 2 family's, the OpenCOOD family's and the noise flags. Choices come from the
``Literal`` types the code uses.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import get_args

import click
from upath import UPath

from ncore_convert.contract import (
    CAMERA_LABEL_KINDS,
    EGO_BOX_M,
    PRESET_DEFAULTS,
    AsyncMode,
    CameraModel,
    ClassNames,
    CuboidLabelSource,
    GpsDof,
    GpsProcess,
    Layout,
    LidarModelSource,
    NoiseModel,
    Preset,
    Profile,
    StoreType,
    WorldGlobalMode,
)
from ncore_convert.errors import SourceError
from ncore_convert.sources import access
from ncore_convert.sources.opencood import SPLITS as OPENCOOD_SPLITS
from ncore_convert.sources.reader import Reader


def options(*decorators: Callable) -> Callable:
    """One decorator that applies ``decorators`` as if stacked in this order (the first on top)."""

    def decorate(f):
        for decorator in reversed(decorators):
            f = decorator(f)
        return f

    return decorate


def off_flag(*decls: str, help: str):
    """A boolean flag that is off unless given (documented as such in --help)."""
    return click.option(*decls, is_flag=True, default=False, show_default="off", help=help)


def choice(flag: str, literal, default: str | None, help: str, **settings) -> Callable:
    """An option choosing one of the values of the ``Literal`` type ``literal``."""
    return click.option(flag, type=click.Choice(get_args(literal)), default=default, help=help, **settings)


def preset_option(flag: str, help: str, literal=None) -> Callable:
    """An option a preset may set (``PRESET_DEFAULTS``): None unless given, so that the preset decides
    (``ConsumerOptions``); a ``literal`` choice, or an on/off flag without one."""
    value = PRESET_DEFAULTS[flag.split("/")[0].removeprefix("--").replace("-", "_")]
    shown = f"{('on' if value else 'off') if isinstance(value, bool) else value}, or the preset's"
    if literal is None:
        return click.option(flag, default=None, show_default=shown, help=help)
    return choice(flag, literal, None, help, show_default=shown)


store_options = options(
    choice("--store-type", StoreType, "itar", "Zarr store container."),
    choice(
        "--profile",
        Profile,
        "separate-sensors",
        "Component group layout: one store, one store per sensor, or also separate poses/intrinsics/masks/cuboids.",
    ),
    click.option("--sequence-meta/--no-sequence-meta", default=True, help="Write <sequence_id>.json (sequence meta)."),
)

#: Options every dataset command shares that shape the output for its consumers (docs/consumers.md).
consumer_options = options(
    choice(
        "--preset",
        Preset,
        "ncore",
        "Set the options below as this consumer needs them (explicit flags still win): 3dgut, 3dgrt"
        " and nurec: an OpenCV pinhole and world_global at the identity; instant-nurec: f-theta cameras"
        " and AUTOLABEL cuboids; ncore: the defaults, as NCore's own converter writes. The run report"
        " and the converter metadata record the preset and what it resolved to.",
    ),
    preset_option(
        "--camera-model",
        "How cameras are stored: NCore's ideal pinhole; an OpenCV pinhole with zero distortion"
        " (the same rays; 3DGUT reads it); or an f-theta model fitted to the pinhole over the whole"
        " image (instant-nurec), its worst error in the camera's metadata.",
        CameraModel,
    ),
    choice(
        "--class-names",
        ClassNames,
        "ncore",
        "Cuboid class names: NCore's lowercase names (e.g. REGULAR_VEHICLE -> car), the source"
        " name of every track kept in the cuboids' metadata; or the dataset's own names.",
    ),
    preset_option(
        "--cuboid-label-source",
        "LabelSource of the cuboids: 'auto' is the dataset's honest one (AV2 EXTERNAL, OPV2V"
        " GT_SYNTHETIC); 'autolabel' is a compatibility setting for instant-nurec, not a provenance"
        " claim.",
        CuboidLabelSource,
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
    preset_option(
        "--lidar-rgb/--no-lidar-rgb",
        "Colour every lidar point from the camera frame nearest its time (occlusion-tested, never"
        " from ego pixels): per-point generic data 'rgb', uint8 [N,3], which 3DGRUT seeds its colours"
        " from. AV2, TbV, OPV2V, V2XSet.",
    ),
    preset_option(
        "--world-global-mode",
        "What world -> world_global holds: the dataset's global frame ('localized'), the identity"
        " (scene at the origin for 3DGRUT), or no world_global node ('none'); the global pose is kept"
        " in the sequence metadata either way.",
        WorldGlobalMode,
    ),
)

lidar_model_source_option = choice(
    "--lidar-model-source",
    LidarModelSource,
    "empirical",
    "'empirical': each lidar's structured model (AV2/TbV: a VLP-32C row-offset model derived per unit"
    " and log; OPV2V/V2XSet: CARLA's from data_protocol.yaml, checked against the data) and each ray's"
    " model element; 'none': raw per-point-time ray bundles only.",
)


def _ego_masks_option(ctx, param, value: str) -> str:
    if value in ("estimate", "none"):
        return value
    with Reader() as reader:  # one listing of the folder (never a HEAD)
        if reader.is_folder(UPath(value)):
            return value
    raise click.BadParameter(f"{value!r} is neither 'estimate', 'none' nor a folder of <camera_id>.png masks")


#: The camera labels TbV can have: no cuboids, so no instances; its ``dynamic`` masks come from
#: what the lidar saw move. Why the others are not offered:
TBV_LABEL_KINDS = ("depth", "dynamic")
TBV_NO_LABEL = "made from the annotated boxes, and TbV has no cuboids"


def camera_labels_option(kinds: tuple[str, ...] = CAMERA_LABEL_KINDS, why_not: str = "") -> Callable:
    """``--camera-labels``, offering ``kinds`` (TbV: :data:`TBV_LABEL_KINDS`); ``why_not``: why the
    other kinds cannot be made here."""

    def parse(ctx, param, value: str | None) -> tuple[str, ...]:
        chosen = tuple(dict.fromkeys(k.strip() for k in (value or "").split(",") if k.strip()))
        for kind in chosen:
            if kind not in CAMERA_LABEL_KINDS:
                raise click.BadParameter(f"unknown camera label {kind!r} (available: {', '.join(kinds)})")
            if kind not in kinds:
                raise click.BadParameter(f"{kind}: {why_not} (available: {', '.join(kinds)})")
        return chosen

    meaning = {
        "depth": "'depth' -> depth.z@<camera>, the z-depth (m) of the nearest lidar point the camera sees in"
        " each pixel, 0 where none (needs the lidars)",
        "dynamic": "'dynamic' -> mask.dynamic@<camera>, 1 where a moving object shows"
        + (" (from the objects the lidar saw move: TbV has no cuboids)" if "instance" not in kinds else ""),
        "instance": "'instance' -> segmentation.instance@<camera>, the per-sequence instance index of the"
        " object each pixel shows, 0 where none (from the cuboids; each object is its box cut to where the"
        " lidar points show it)",
    }
    return click.option(
        "--camera-labels",
        type=str,
        default=None,
        callback=parse,
        metavar=",".join(kinds),
        show_default="none",
        help="Image-aligned labels per camera frame, in NCore's camera-labels component (comma-separated): "
        + "; ".join(meaning[k] for k in kinds)
        + ".",
    )


def av2_family_options(log_scope: str, tbv: bool = False) -> Callable:
    """Options shared by the Argoverse 2 Sensor and TbV commands (``tbv``: the TbV command's, whose
    logs have no cuboids)."""
    return options(
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
            default=EGO_BOX_M,
            show_default=True,
            metavar="LENGTH WIDTH HEIGHT",
            help="The nominal ego vehicle for the ego-mask prior (metres, around the rear-axle origin):"
            " where the body can be in each camera, and which cameras must see it.",
        ),
        lidar_model_source_option,
        camera_labels_option(TBV_LABEL_KINDS, TBV_NO_LABEL) if tbv else camera_labels_option(),
        click.option(
            "--dynamic-source",
            type=click.Choice(["annotations", "lidar", "both"]),
            default=None,
            show_default="annotations; lidar for a TbV log without annotations",
            help="Where the lidar's dynamic_flag comes from: the annotated movers' boxes; what the lidar itself"
            " saw move (free space: other sweeps saw through the point's place, docs/motion.md); or both (the"
            " lidar adds movers the annotations miss, never in a standing track's box).",
        ),
    )


#: Flags equivalent to a ``wild_setting`` block: (flag, parameter, wild_setting key, type, default, help).
#: Unset flags take OpenCOOD's defaults (shown), set in ``make_setting``.
# fmt: off
NOISE_FLAGS = [
    ("--noise-name", "noise_name", "name", str, "the model's name", "Name of the setting these flags make (its poses instance)."),  # noqa: E501
    ("--noise-model", "noise_model", "model", click.Choice(get_args(NoiseModel)), "opencood", "'opencood': OpenCOOD's draws exactly; 'realistic': independent per-agent streams."),  # noqa: E501
    ("--noise-seed", "noise_seed", "seed", int, "25, OpenCOOD's test seed", "seed."),
    ("--async/--no-async", "async_", "async", None, "off", "async: add communication delay."),
    ("--async-mode", "async_mode", "async_mode", click.Choice(get_args(AsyncMode)), "sim", "async_mode: 'sim' constant delay, 'real' U(0, overhead) + transmission + backbone."),  # noqa: E501
    ("--async-overhead", "async_overhead", "async_overhead", float, "0", "async_overhead, ms."),
    ("--backbone-delay", "backbone_delay", "backbone_delay", float, "0", "backbone_delay, ms (real mode)."),
    ("--data-size", "data_size", "data_size", float, "0", "data_size, Mb (real mode)."),
    ("--transmission-speed", "transmission_speed", "transmission_speed", float, "27", "transmission_speed, Mb/s (real mode)."),  # noqa: E501
    ("--loc-err/--no-loc-err", "loc_err", "loc_err", None, "off", "loc_err: add localisation (GPS) error."),
    ("--xyz-std", "xyz_std", "xyz_std", float, "0", "xyz_std: position error std, m."),
    ("--ryp-std", "ryp_std", "ryp_std", float, "0", "ryp_std: angular error std, deg."),
    ("--max-cav", "max_cav", "max_cav", int, "7", "OpenCOOD's train_params.max_cav (opencood model)."),
    ("--gps-process", "gps_process", "process", click.Choice(get_args(GpsProcess)), "white", "realistic: per-frame draws or Gauss-Markov drift."),  # noqa: E501
    ("--correlation-time-s", "correlation_time_s", "correlation_time_s", float, "10", "realistic: Gauss-Markov correlation time, s."),  # noqa: E501
    ("--bias-xyz-std", "bias_xyz_std", "bias_xyz_std", float, "0", "realistic: std of a constant position bias, m."),
    ("--bias-ryp-std", "bias_ryp_std", "bias_ryp_std", float, "0", "realistic: std of a constant angular bias, deg."),
    ("--gps-dof", "gps_dof", "dof", click.Choice(get_args(GpsDof)), "6dof", "realistic: perturb all 6 DoF or x, y and yaw."),  # noqa: E501
    ("--perturb-ego/--no-perturb-ego", "perturb_ego", "perturb_ego", None, "off", "realistic: perturb the OpenCOOD ego too."),  # noqa: E501
]
# fmt: on

#: ``--noise-config`` (repeatable) and the flags that make one further setting (``NOISE_FLAGS``).
noise_options = options(
    click.option(
        "--noise-config",
        "noise_configs",
        multiple=True,
        metavar="FILE",
        show_default="none",
        help="YAML with an OpenCOOD wild_setting block (repeatable): GPS error and delay, written as a"
        " further poses instance named by its 'name' key or the file name.",
    ),
    *(
        click.option(decl, param, type=kind, default=None, show_default=shown, help=help_text)
        for decl, param, _, kind, shown, help_text in NOISE_FLAGS
    ),
)


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


def opencood_options(dataset: str) -> Callable:
    """Options of the OPV2V and V2XSet commands."""
    return options(
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
        choice(
            "--layout",
            Layout,
            "agents",
            "'agents': one sequence per agent (rig = that agent) in <scenario>/<agent_id>/;"
            " 'scenario': one sequence with every agent (frames and sensors prefixed agent<id>_).",
        ),
        lidar_model_source_option,
        store_options,
        consumer_options,
        noise_options,
        camera_labels_option(),
    )


class AccessError(click.ClickException):
    """The input cannot be read (a credential problem, an unreachable store): one line, exit 2."""

    exit_code = 2


def open_input(url: str, option: str, anonymous: bool) -> UPath:
    """The input folder ``url`` given as ``option``, checked to exist: a usage error if it does
    not, an AccessError naming the fix for a credential problem."""
    try:
        root = access.input_root(url, anonymous)
        with Reader() as reader:  # one listing (never a HEAD)
            found = reader.is_folder(root)
    except ValueError as err:
        raise click.UsageError(str(err)) from None
    except Exception as err:  # noqa: BLE001 - the store's own errors (botocore's are not OSErrors)
        line = access.access_problem(err, f"{option} {url}", anonymous)
        cause = str(err).splitlines()[0] if str(err) else ""
        raise AccessError(line or f"{option} {url}: cannot be read ({type(err).__name__}: {cause})") from None
    if not found:
        raise click.UsageError(f"{option} {url}: folder not found")
    return root
