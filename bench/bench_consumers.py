"""Benchmark what the consumer options cost: the f-theta fit per camera, dynamic_flag per sweep, and
the ego-mask estimation per log.

Not a test. Prints, medians over --repeat runs, measured side by side in one run:

- the f-theta fit of each camera type (AV2 portrait front 1550x2048, AV2 ring 2048x1550, TbV half
  resolution 1024x775, OPV2V 800x600 at 100° HFOV): seconds, and its worst / median error over
  every pixel centre;
- on a synthetic 13 s AV2 log with jittering parked cars and slow traffic, and on the real AV2
  sample: the track decision per log (this rule with its static poses, and the speed rule before
  issue 26, restated here), and per sweep reading the sweep and making both units' ray bundles
  beside dynamic_flag of both units with either rule's dynamic tracks, and their ratios;
- a whole-log conversion (in this process, no validation) with the default pinhole and with
  ``--camera-model ftheta``, and their ratio;
- the same log with and without ``--lidar-rgb`` (per-point colours from the cameras), and the
  colouring's own time;
- ego-mask estimation on a 15 s log: alone, and the whole command with ``--ego-masks none`` and
  ``estimate``, and the share of the conversion it costs.

    python bench/bench_consumers.py [--work /tmp/ncore-bench] [--repeat 5] [--only ego-masks]
"""

from __future__ import annotations

import shutil
import statistics
import time
from pathlib import Path

import numpy as np
from bench_argoverse2 import bench_parser, cached, work_dir
from upath import UPath

CAMERAS = {  # name: (fx, fy, width, height), principal point at the image centre
    "AV2 ring_front_center 1550x2048": (1773.3, 1772.9, 1550, 2048),
    "AV2 ring camera 2048x1550": (1686.0, 1686.5, 2048, 1550),
    "TbV half resolution 1024x775": (843.0, 843.2, 1024, 775),
    "OPV2V 800x600, 100 deg HFOV": (335.64, 335.64, 800, 600),
}


def bench_fit(repeat: int) -> None:
    from ncore_convert.transforms.camera.models import Pinhole, fit_ftheta

    print(f"f-theta fit per camera (medians of {repeat})", flush=True)
    for name, (fx, fy, width, height) in CAMERAS.items():
        pinhole = Pinhole((fx, fy), (width / 2, height / 2), (width, height))
        seconds = []
        for _ in range(repeat):
            started = time.perf_counter()
            fit = fit_ftheta(pinhole)
            seconds.append(time.perf_counter() - started)
        print(
            f"  {name}: {statistics.median(seconds):.3f} s; worst {fit.max_error_px:.4f} px,"
            f" median {fit.median_error_px:.4f} px",
            flush=True,
        )


def synth_av2(work: Path) -> tuple[Path, str]:
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / "consumers-av2-2s"
    log_id = cached(
        root, "2 s AV2 log", lambda r: write_log(UPath(r / "val"), SynthConfig(seconds=2.0, seed=21)).log_id
    )
    return root, log_id


def synth_traffic(work: Path) -> tuple[Path, str]:
    """A 13 s lidar-only log with jittering parked cars and the slow traffic (issue 26)."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / "consumers-av2-13s-traffic"
    config = SynthConfig(seconds=13.0, seed=23, camera_fps=0)
    return root, cached(root, "13 s AV2 log with slow traffic", lambda r: write_log(UPath(r / "val"), config).log_id)


def speed_rule_ids(observations, classes: list[str]) -> set[str]:
    """The rule before issue 26, restated here only for the comparison: dynamic when the class always
    is, or when the speed of the box centres (median over 5 observations, 2 s baseline) exceeds
    1 km/h anywhere; never for always-static classes."""
    from ncore_convert.transforms.objects.classes import ALWAYS_DYNAMIC, ALWAYS_STATIC

    ids = np.asarray(observations.track_ids)
    out = set()
    for track in np.unique(ids):
        rows = np.flatnonzero(ids == track)
        rows = rows[np.argsort(observations.timestamps_us[rows])]
        t_s = (observations.timestamps_us[rows] - observations.timestamps_us[rows[0]]) * 1e-6
        padded = np.concatenate(
            [
                np.repeat(observations.centers_m[rows[:1]], 2, 0),
                observations.centers_m[rows],
                np.repeat(observations.centers_m[rows[-1:]], 2, 0),
            ]
        )
        smooth = np.median(np.lib.stride_tricks.sliding_window_view(padded, 5, axis=0), axis=-1)
        later = np.searchsorted(t_s, t_s + min(2.0, t_s[-1]) - 1e-9)
        ok = (later < len(t_s)) & (later > np.arange(len(t_s)))
        i, j = np.flatnonzero(ok), later[ok]
        speed = (np.linalg.norm(smooth[j] - smooth[i], axis=1) / (t_s[j] - t_s[i])).max(initial=0.0)
        cls = classes[rows[0]]
        if cls not in ALWAYS_STATIC and (cls in ALWAYS_DYNAMIC or (t_s[-1] >= 0.3 and speed > 1 / 3.6)):
            out.add(str(track))
    return out


def bench_dynamic_flag(root: Path, log_id: str, repeat: int) -> None:
    """Per log, the track decision (this rule with its static poses, and the speed rule before it);
    per sweep, reading and ray bundles beside dynamic_flag with either rule's dynamic tracks."""
    from ncore_convert.transforms.lidar.rays.frames import lidar_frame, point_data

    from ncore_convert.converters.argoverse2.lidar import sweep_frame, sweep_times_ns
    from ncore_convert.converters.argoverse2.plan import Argoverse2Options, plan_log
    from ncore_convert.sources import argoverse2 as av2
    from ncore_convert.transforms.geometry import transform_points
    from ncore_convert.transforms.objects import dynamic
    from ncore_convert.transforms.objects.classes import AV2_TO_NCORE

    plan = plan_log(UPath(root), log_id, Argoverse2Options(split="val", camera_ids=()))
    traj, annotations = plan.T_rig_world, plan.inputs.annotations
    T_box_world = traj.interpolate(traj.relative_seconds(annotations.timestamps_ns)) @ annotations.T_object_ego
    observations = dynamic.TrackObservations(
        annotations.track_uuids,
        annotations.timestamps_ns // 1000,
        T_box_world[:, :3, 3],
        T_box_world[:, :3, :3],
        annotations.dims_m,
    )
    classes = [AV2_TO_NCORE.get(c, c) for c in annotations.categories]
    decide_s: dict[str, list[float]] = {"after": [], "before": []}
    for _ in range(repeat):
        started = time.perf_counter()
        motion = dynamic.classify_tracks(observations, classes)
        dynamic.static_poses(observations, {t for t, m in motion.items() if not m.dynamic})
        middle = time.perf_counter()
        before_ids = speed_rule_ids(observations, classes)
        decide_s["after"].append(middle - started)
        decide_s["before"].append(time.perf_counter() - middle)
    tracks = {"after": {t for t, m in motion.items() if m.dynamic}, "before": before_ids}
    boxes = {rule: dynamic.DynamicBoxes.select(observations, ids) for rule, ids in tracks.items()}
    T_sensor_rig = {unit: plan.inputs.T_sensor_ego[unit] for unit in plan.lidar_ids}
    rays_s: list[float] = []
    flag_s: dict[str, list[float]] = {"after": [], "before": []}
    points = []
    sweeps = plan.sweep_timestamps_ns[:: max(1, len(plan.sweep_timestamps_ns) // 20)]  # at most ~20 sweeps
    for _ in range(repeat):
        for sweep_ns in sweeps:
            started = time.perf_counter()
            sweep = av2.read_sweep(plan.inputs.log_dir, int(sweep_ns), True)
            times_ns = sweep_times_ns(sweep, plan.lidar_calibration, traj, T_sensor_rig)
            frame, geometry = sweep_frame(sweep, times_ns, plan.lidar_calibration, traj, T_sensor_rig)
            units, _ = lidar_frame(frame, geometry, None, None)
            rays_s.append(time.perf_counter() - started)
            points.append(len(sweep.xyz_ego_m))
            world = {
                u: transform_points(frame.T_reference_fixed, sweep.xyz_ego_m[s.rows].astype(float))
                for u, s in units.items()
            }
            times_us = {unit: stored.rays.timestamp_us for unit, stored in units.items()}
            for rule in ("after", "before"):  # interleaved
                flag_s[rule].append(point_data(world, times_us, boxes[rule], None).flag_seconds)
    rays_ms = statistics.median(rays_s) * 1e3
    after_ms, before_ms = (statistics.median(flag_s[r]) * 1e3 for r in ("after", "before"))
    print(
        f"{len(set(annotations.track_uuids))} tracks over {np.ptp(annotations.timestamps_ns) * 1e-9:.1f} s;"
        f" dynamic: {len(tracks['after'])} (this rule), {len(tracks['before'])} (the speed rule before it)",
        flush=True,
    )
    print(
        f"  track decision per log: this rule + static poses {statistics.median(decide_s['after']) * 1e3:.1f} ms,"
        f" speed rule {statistics.median(decide_s['before']) * 1e3:.1f} ms",
        flush=True,
    )
    print(
        f"  per sweep ({int(np.median(points))} points, medians over {len(rays_s)} sweeps): read + ray bundles"
        f" (both units) {rays_ms:.1f} ms; dynamic_flag (both units) {after_ms:.1f} ms with this rule,"
        f" {before_ms:.1f} ms before it; ratios to the read {after_ms / rays_ms:.3f} / {before_ms / rays_ms:.3f},"
        f" after / before {after_ms / before_ms:.3f}",
        flush=True,
    )


def bench_conversion(root: Path, log_id: str, work: Path, repeat: int) -> None:
    from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log

    seconds: dict[str, list[float]] = {"ideal-pinhole": [], "ftheta": []}
    for _ in range(repeat):
        for model in seconds:  # interleaved: the machine's noise hits both alike
            out = work / "consumers-out"
            shutil.rmtree(out, ignore_errors=True)
            started = time.perf_counter()
            convert_log(UPath(root), UPath(out), log_id, Argoverse2Options(split="val", camera_model=model))
            seconds[model].append(time.perf_counter() - started)
    shutil.rmtree(work / "consumers-out", ignore_errors=True)
    pinhole, ftheta = (statistics.median(seconds[m]) for m in ("ideal-pinhole", "ftheta"))
    print(
        f"2 s AV2 log, 9 cameras, one process (medians of {repeat}): ideal-pinhole {pinhole:.2f} s,"
        f" ftheta {ftheta:.2f} s, ratio {ftheta / pinhole:.3f}",
        flush=True,
    )


def bench_lidar_rgb(root: Path, log_id: str, work: Path, repeat: int) -> None:
    """The 2 s log converted in this process (no validation) without ``--lidar-rgb``, and with it
    decoding images one at a time and ``DECODE_THREADS`` at a time, interleaved; the colouring's own
    time from the run's counters."""
    from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
    from ncore_convert.transforms.camera import colours as point_colours

    threads = point_colours.DECODE_THREADS
    seconds: dict[int, list[float]] = {0: [], 1: [], threads: []}  # 0: --no-lidar-rgb
    colour_s: dict[int, list[float]] = {1: [], threads: []}
    for _ in range(repeat):
        for decoders in seconds:
            point_colours.DECODE_THREADS = max(1, decoders)
            out = work / "consumers-out"
            shutil.rmtree(out, ignore_errors=True)
            started = time.perf_counter()
            options = Argoverse2Options(split="val", lidar_rgb=bool(decoders))
            summary = convert_log(UPath(root), UPath(out), log_id, options)
            seconds[decoders].append(time.perf_counter() - started)
            if decoders:
                colour_s[decoders].append(summary.colour_seconds)
    point_colours.DECODE_THREADS = threads
    shutil.rmtree(work / "consumers-out", ignore_errors=True)
    off = statistics.median(seconds[0])
    print(f"--lidar-rgb, 2 s AV2 log, 9 cameras at 20 fps, one process (medians of {repeat}): off {off:.2f} s", end="")
    for decoders in (1, threads):
        on = statistics.median(seconds[decoders])
        print(
            f"; on, {decoders} decoder thread(s): {on:.2f} s, ratio {on / off:.3f}, colouring itself"
            f" {statistics.median(colour_s[decoders]):.2f} s",
            end="",
        )
    print(flush=True)


def bench_ego_masks(work: Path, repeat: int) -> None:
    """Ego-mask estimation on a 15 s synthetic AV2 log (9 cameras at 20 fps): the estimation alone
    (on 2 warm worker processes, as the command runs it while it plans the log), and the whole
    command with ``--ego-masks none`` and ``estimate`` (2 workers, no validation), interleaved."""
    import subprocess
    import sys

    from ncore_convert.converters.argoverse2.masks import plan_ego_masks
    from ncore_convert.converters.argoverse2.plan import camera_pinhole
    from ncore_convert.run.pool import JobPool
    from ncore_convert.sources import argoverse2 as av2
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log
    from ncore_convert.transforms.camera.ego_mask import EgoBox

    root = work / "consumers-av2-15s-realistic-body-32-pictures"  # as many distinct pictures as are sampled
    log_id = cached(
        root,
        "15 s AV2 log",
        lambda r: write_log(UPath(r / "val"), SynthConfig(seconds=15.0, seed=22, pictures=32)).log_id,
    )
    log_dir = UPath(root / "val" / log_id)
    intrinsics, extrinsics = av2.read_intrinsics(log_dir), av2.read_sensor_extrinsics(log_dir)
    cameras = {
        cam: (av2.list_image_timestamps_ns(log_dir, cam), camera_pinhole(intrinsics[cam]), extrinsics[cam])
        for cam in av2.CAMERAS
    }
    alone = []
    with JobPool(2, preload=["ncore_convert.converters.argoverse2"]) as pool:  # as the command's 2 workers
        for _ in range(repeat):
            started = time.perf_counter()
            plan_ego_masks(log_dir, "estimate", cameras, [], EgoBox(), pool.run)
            alone.append(time.perf_counter() - started)
    command = [
        str(Path(sys.executable).parent / "ncore-convert"),
        "--no-progress",
        "--no-validate",
        "--workers",
        "2",
        "--root-dir",
        str(root),
        "--output-dir",
        str(work / "consumers-out"),
        "argoverse2-v4",
        "--split",
        "val",
    ]
    seconds: dict[str, list[float]] = {"none": [], "estimate": []}
    for _ in range(repeat):
        for mode in seconds:
            shutil.rmtree(work / "consumers-out", ignore_errors=True)
            started = time.perf_counter()
            subprocess.run([*command, "--ego-masks", mode], check=True, capture_output=True)
            seconds[mode].append(time.perf_counter() - started)
    shutil.rmtree(work / "consumers-out", ignore_errors=True)
    none, estimate = (statistics.median(seconds[m]) for m in ("none", "estimate"))
    print(
        f"ego masks, 15 s AV2 log, 9 cameras, 32 sampled images on each of the 5 that see the body (medians"
        f" of {repeat}): estimation alone (2 worker processes) {statistics.median(alone):.2f} s;",
        flush=True,
    )
    print(
        f"  whole command, 2 workers: --ego-masks none {none:.2f} s, estimate {estimate:.2f} s,"
        f" ratio {estimate / none:.3f}; estimation / conversion {statistics.median(alone) / none:.3f}",
        flush=True,
    )


def main() -> None:
    parser = bench_parser(__doc__, repeat=5)
    parser.add_argument("--only", choices=["ego-masks"], help="run only this part")
    args = parser.parse_args()
    work = work_dir(args)
    if args.only == "ego-masks":
        bench_ego_masks(work, max(1, args.repeat // 2 + 1))
        return
    bench_fit(args.repeat)
    root, log_id = synth_av2(work)
    print("dynamic_flag, synthetic 13 s log with jittering parked cars and slow traffic:", end=" ")
    bench_dynamic_flag(*synth_traffic(work), max(1, args.repeat // 2))
    from bench_input_checks import sample_log

    sample = sample_log()
    print("dynamic_flag, real AV2 sample (2 sweeps; annotations over 15.5 s):", end=" ")
    bench_dynamic_flag(Path(str(sample.parent.parent)), sample.name, args.repeat * 4)
    bench_conversion(root, log_id, work, max(1, args.repeat // 2))
    bench_lidar_rgb(root, log_id, work, max(1, args.repeat // 2))
    bench_ego_masks(work, max(1, args.repeat // 2 + 1))


if __name__ == "__main__":
    main()
