"""The tool commands (``validate``, ``preview``, ``export-opencood``, ``evaluate-lidar-model``,
``synth``): they need no ``--root-dir/--output-dir``; :mod:`ncore_convert.cli` adds them to its group."""

from __future__ import annotations

import sys
from collections.abc import Callable

import click
from upath import UPath

from ncore_convert.cli_options import off_flag, open_input, options
from ncore_convert.contract import MANIFEST
from ncore_convert.sources.argoverse2 import SPLITS as AV2_SPLITS
from ncore_convert.sources.opencood import SPLITS as OPENCOOD_SPLITS


def out_option(help: str) -> Callable:
    """The folder a tool command writes into (``--out``, required)."""
    return click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help=help)


@click.command("validate")
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
@click.pass_obj
def validate_command(obj, path, source_root, json_file, details):
    """Check converted sequences and cooperative scenarios (PATH: a <sequence_id>.json, a scenario.json
    (its folder), or an output folder to search).

    Prints a table (one row per sequence or scenario.json), each failed check, and exits 1 if any
    check failed.
    """
    import json

    from ncore_convert.validate.tree import validate_tree

    source = open_input(source_root, "--source", obj.anonymous) if source_root is not None else None
    reports = validate_tree(UPath(path), source)
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


@click.command("preview")
@click.argument("path", type=click.Path(exists=True, dir_okay=False))
@out_option("Folder for the PNGs.")
@click.option(
    "--frame",
    type=click.IntRange(min=0),
    default=None,
    show_default="the middle frame",
    help="Frame index: of the first lidar (a sequence), or of the frames all agents share (scenario.json).",
)
def preview_command(path, out_dir, frame):
    """PNGs of a converted sequence or cooperative scenario (PATH: <sequence_id>.json or scenario.json).

    A sequence: lidar points projected into every camera (coloured by range, motion-aware), each
    camera's depth label of that frame if it has one, and a bird's-eye view with cuboids and the
    ego trajectory. A scenario.json: every agent in one
    bird's-eye view of world_global, with each noisy poses instance beside the ground truth.
    """
    from ncore_convert.preview import preview_scenario, preview_sequence

    try:
        if UPath(path).name == MANIFEST:
            written = [preview_scenario(UPath(path), UPath(out_dir), frame)]
        else:
            result = preview_sequence(UPath(path), UPath(out_dir), frame)
            written = [result.bev] + [p.png for p in result.cameras] + result.depth_labels + result.mask_labels
    except ValueError as err:
        raise click.UsageError(str(err)) from None
    for png in written:
        click.echo(f"wrote {png}")


@click.command("export-opencood")
@click.argument("scenario", type=click.Path(exists=True, dir_okay=False))
@out_option("Folder to write <scenario>/ into (OpenCOOD's layout).")
@click.option(
    "--poses",
    default=None,
    show_default="the ground truth",
    help="A stored noise setting whose lidar_pose the YAMLs get (then switch OpenCOOD's own"
    " wild_setting off, or the noise is applied twice).",
)
@click.pass_obj
def export_opencood_command(obj, scenario, out_dir, poses):
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
    for line in counts.left_out:
        click.echo(f"left out: {line}")


@click.command("evaluate-lidar-model")
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


@click.group()
def synth():
    """Write synthetic source logs with known ground truth (test data and demo source)."""


def object_options() -> Callable:
    """The objects of a synthetic world (``synth.shapes``), for every ``synth`` command."""
    return options(
        click.option(
            "--shapes/--boxes",
            default=False,
            help="Shape vehicles (body, cabin, wheels, mirrors), pedestrians and cyclists inside their"
            " annotated boxes, and add cyclists (AV2, TbV); or keep every object its own box.",
        ),
        click.option(
            "--close-range/--no-close-range",
            default=False,
            help="Add a car just ahead of the ego (OPV2V/V2XSet: 0.3-1.0 m from the first CAV's front"
            " camera) and one 1-2 m alongside it.",
        ),
    )


#: ``synth argoverse2|tbv``'s pictures per camera: as many as the ego-mask estimator samples, so a
#: default log (2 s at 20 fps: 40 images per camera) gets its masks and converts without a warning.
SYNTH_PICTURES = 32


def synth_log_options(out_help: str, max_seconds: float | None) -> Callable:
    """The options of ``synth argoverse2`` and ``synth tbv`` (the log and its camera pictures)."""
    return options(
        out_option(out_help),
        click.option(
            "--seconds",
            type=click.FloatRange(min=0.1, max=max_seconds),
            default=2.0,
            help="Log duration (10 sweeps per second).",
        ),
        click.option("--seed", type=int, default=0, help="Random seed (scene, trajectory, log id)."),
        click.option(
            "--camera-fps", type=click.FloatRange(min=0.0), default=20.0, help="Images per second per camera (0: none)."
        ),
        click.option(
            "--parked-fraction",
            type=click.FloatRange(0.0, 1.0),
            default=0.0,
            help="The first part of the log (a fraction) in which the cameras' world stands still, as if parked"
            " (1: the whole log; tests the ego-mask fallback).",
        ),
        click.option(
            "--pictures",
            type=click.IntRange(min=1),
            default=SYNTH_PICTURES,
            help="Distinct pictures per camera that its images cycle through (the ego-mask estimator samples"
            " 32 images per camera and needs 24 distinct ones: fewer, and a log converts without ego masks,"
            " with a warning).",
        ),
        click.option(
            "--shadows/--no-shadows",
            default=False,
            help="Moving soft-edged shadows across the pictures, the body included.",
        ),
        click.option(
            "--light",
            type=click.Choice(["day", "night"]),
            default="day",
            help="Daylight, or a night scene: a dark world lit by moving lamps, which the paint mirrors.",
        ),
        click.option(
            "--ego-body",
            type=click.Choice(["realistic", "easy", "glossy"]),
            default="realistic",
            help="The ego body in the cameras that see it: glossy paint with reflections,"
            " lighting changes, markings, glare and camouflaged silhouette stretches; still paint under ±5 %"
            " light; or the realistic body with strong reflections (75-95 % of the scene's contrast).",
        ),
        click.option(
            "--world",
            type=click.Choice(["pattern", "render"]),
            default="pattern",
            help="The pictures: a few textured pictures per camera, cycled (cheap); or each picture ray-cast"
            " from the scene the lidar sees at its own time, flat-shaded (one world: lidar colours can be"
            " checked against it; ~0.3 s per picture).",
        ),
        click.option(
            "--camera-scale",
            type=click.IntRange(min=1),
            default=1,
            help="Divide every camera's size and focal length by this (the same field of view; pictures"
            " about 1/scale² as costly). 4 makes AV2's 2048 px cameras 512 px.",
        ),
        click.option(
            "--clear-paths/--overlapping-traffic",
            default=True,
            help="Nothing moves through a standing object (parked cars stand clear of passing traffic); or the"
            " old worlds, whose passing cars drive through parked cars (objects that fuse, on purpose).",
        ),
        object_options(),
    )


def _synth_log(out_dir: str, split: str | None = None, **config) -> None:
    """Write one synthetic AV2 log into ``<out_dir>/<split>``, or a TbV log (no split) into
    ``out_dir`` (``config``: ``synth.argoverse2.SynthConfig``'s fields)."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    truth = write_log(UPath(out_dir) / split if split else UPath(out_dir), SynthConfig(**config))
    cuboids = "" if config.get("tbv") else f", {truth.n_cuboids} cuboids"
    points = sum(len(s.offset_ns) for s in truth.sweeps)
    click.echo(f"wrote {truth.log_dir}: {len(truth.sweeps)} sweeps, {points} points, {truth.n_images} images{cuboids}")


@synth.command("argoverse2")
@synth_log_options("Dataset root: writes <out>/<split>/<log_id>/... (the --root-dir to convert).", max_seconds=None)
@click.option("--split", type=click.Choice(AV2_SPLITS), default="val", help="Split folder.")
@off_flag(
    "--swap-lidar-halves",
    help="Give up_lidar the laser_number half >= 32 (proves the unit decision comes from the data).",
)
def synth_argoverse2(**config):
    """A synthetic Argoverse 2 Sensor log: real schemas, two simulated VLP-32C units, cameras (with the
    ego body in five of them), cuboids."""
    _synth_log(**config)


@synth.command("tbv")
@synth_log_options("Dataset root: writes <out>/<log_id>/... (TbV has no split folders).", max_seconds=120.0)
def synth_tbv(**config):
    """A synthetic TbV log: flat layout, no offset_ns, 7 ring cameras (6 at half resolution; the ego body
    in three), no annotations."""
    _synth_log(tbv=True, **config)


def _synth_opencood(dataset: str):
    @synth.command(dataset, help=f"Synthetic {dataset.upper()} scenarios, written as OpenCDA writes them, with truth.")
    @out_option("Dataset root: writes <out>/<split>/<scenario>/<agent_id>/...")
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
    @click.option(
        "--render-step",
        type=click.IntRange(min=1),
        default=2,
        help="Ray-cast the 800x600 pictures at one ray per N x N pixels (8: 16 times cheaper, blockier).",
    )
    @click.option(
        "--legacy-format",
        "opencda_format",
        flag_value=False,
        default=True,
        help="Write the YAMLs as the generator did before issue 73 (exact doubles, flow style) instead of"
        " as OpenCDA does (CARLA's float32 values, block style); bench/fingerprints.py pins it.",
    )
    @object_options()
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
        render_step,
        opencda_format,
        shapes,
        close_range,
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
            render_step=render_step,
            shapes=shapes,
            close_range=close_range,
            opencda_format=opencda_format,
        )
        for truth in write_dataset(UPath(out_dir), config, scenarios):
            click.echo(f"wrote {truth.scenario_dir}: agents {', '.join(truth.agents)}, {len(truth.keys)} frames")

    return command


synth_opv2v = _synth_opencood("opv2v")
synth_v2xset = _synth_opencood("v2xset")
