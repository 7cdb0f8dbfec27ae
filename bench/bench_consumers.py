"""Benchmark what the consumer options cost: the f-theta fit per camera, dynamic_flag per sweep, and
the ego-mask estimation per log.

Not a test. Prints, medians over --repeat runs, measured side by side in one run:

- the f-theta fit of each camera type (AV2 portrait front 1550x2048, AV2 ring 2048x1550, TbV half
  resolution 1024x775, OPV2V 800x600 at 100° HFOV): seconds, and its worst / median error over
  every pixel centre;
- per sweep of a synthetic 2 s AV2 log (about 96k points, every annotated track) and of the real
  AV2 sample: reading the sweep and making both units' ray bundles (decompensation, model
  elements), beside dynamic_flag of both units (the sweep to world, the grown-box tests), and their
  ratio;
- a whole-log conversion (in this process, no validation) with the default pinhole and with
  ``--camera-model ftheta``, and their ratio;
- ego-mask estimation on a 15 s log: alone, and the whole command with ``--ego-masks none`` and
  ``estimate``, and the share of the conversion it costs.

    python bench/bench_consumers.py [--work /tmp/ncore-bench] [--repeat 5]
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
    from ncore_convert.transforms.camera_models import Pinhole, fit_ftheta

    print(f"f-theta fit per camera (medians of {repeat})", flush=True)
    for name, (fx, fy, width, height) in CAMERAS.items():
        pinhole = Pinhole((fx, fy), (width / 2, height / 2), (width, height))
        seconds = []
        for _ in range(repeat):
            started = time.perf_counter()
            fit = fit_ftheta(pinhole)
            seconds.append(time.perf_counter() - started)
        print(f"  {name}: {statistics.median(seconds):.3f} s; worst {fit.max_error_px:.4f} px,"
              f" median {fit.median_error_px:.4f} px", flush=True)  # fmt: skip


def synth_av2(work: Path) -> tuple[Path, str]:
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / "consumers-av2-2s"
    log_id = cached(
        root, "2 s AV2 log", lambda r: write_log(UPath(r / "val"), SynthConfig(seconds=2.0, seed=21)).log_id
    )
    return root, log_id


def bench_dynamic_flag(root: Path, log_id: str, repeat: int) -> None:
    from ncore_convert.converters.argoverse2.convert import sweep_dynamic_flags
    from ncore_convert.converters.argoverse2.lidar import read_covered_sweep, sweep_ray_bundles
    from ncore_convert.converters.argoverse2.plan import Argoverse2Options, plan_log

    plan = plan_log(UPath(root), log_id, Argoverse2Options(split="val", camera_ids=()))
    traj, boxes = plan.T_rig_world, plan.dynamic_boxes
    T_sensor_rig = {unit: plan.inputs.T_sensor_ego[unit] for unit in plan.lidar_ids}
    rays_s, flag_s, points = [], [], []
    for _ in range(repeat):
        for sweep_ns in plan.sweep_timestamps_ns:
            started = time.perf_counter()
            sweep = read_covered_sweep(plan.inputs.log_dir, int(sweep_ns), traj, True)
            units = sweep_ray_bundles(sweep, plan.lidar_calibration, traj, T_sensor_rig)
            middle = time.perf_counter()
            flags = sweep_dynamic_flags(sweep, traj, boxes)
            _per_unit = [flags[unit_rays.sweep_rows] for unit_rays in units.values()]
            done = time.perf_counter()
            rays_s.append(middle - started)
            flag_s.append(done - middle)
            points.append(len(sweep.xyz_ego_m))
    rays_ms, flag_ms = statistics.median(rays_s) * 1e3, statistics.median(flag_s) * 1e3
    print(f"dynamic_flag per sweep ({int(np.median(points))} points, {len(boxes)} dynamic tracks,"
          f" medians over {len(rays_s)} sweeps)", flush=True)  # fmt: skip
    print(f"  read + ray bundles (both units): {rays_ms:.1f} ms; dynamic_flag (both units): {flag_ms:.1f} ms;"
          f" ratio {flag_ms / rays_ms:.3f}", flush=True)  # fmt: skip


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
    print(f"2 s AV2 log, 9 cameras, one process (medians of {repeat}): ideal-pinhole {pinhole:.2f} s,"
          f" ftheta {ftheta:.2f} s, ratio {ftheta / pinhole:.3f}", flush=True)  # fmt: skip


def bench_ego_masks(work: Path, repeat: int) -> None:
    """Ego-mask estimation on a 15 s synthetic AV2 log (9 cameras at 20 fps): the estimation alone,
    and the whole command with ``--ego-masks none`` and ``estimate`` (2 workers, no validation),
    interleaved."""
    import subprocess
    import sys

    from ncore_convert.converters.argoverse2.masks import plan_ego_masks
    from ncore_convert.sources import argoverse2 as av2
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log
    from ncore_convert.transforms.ego_mask import EgoBox

    root = work / "consumers-av2-15s-realistic-body"
    log_id = cached(
        root, "15 s AV2 log", lambda r: write_log(UPath(r / "val"), SynthConfig(seconds=15.0, seed=22)).log_id
    )
    log_dir = UPath(root / "val" / log_id)
    intrinsics, extrinsics = av2.read_intrinsics(log_dir), av2.read_sensor_extrinsics(log_dir)
    cameras = {
        cam: (av2.list_image_timestamps_ns(log_dir, cam), intrinsics[cam], extrinsics[cam]) for cam in av2.CAMERAS
    }
    alone = []
    for _ in range(repeat):
        started = time.perf_counter()
        plan_ego_masks(log_dir, "estimate", cameras, [], EgoBox())
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
    print(f"ego masks, 15 s AV2 log, 9 cameras x 16 sampled images (medians of {repeat}):"
          f" estimation alone {statistics.median(alone):.2f} s;", flush=True)  # fmt: skip
    print(
        f"  whole command, 2 workers: --ego-masks none {none:.2f} s, estimate {estimate:.2f} s,"
        f" ratio {estimate / none:.3f}; estimation / conversion {statistics.median(alone) / none:.3f}",
        flush=True,
    )


def main() -> None:
    args = bench_parser(__doc__, repeat=5).parse_args()
    work = work_dir(args)
    bench_fit(args.repeat)
    root, log_id = synth_av2(work)
    print("synthetic log:", end=" ")
    bench_dynamic_flag(root, log_id, max(1, args.repeat // 2))
    from bench_input_checks import sample_log

    sample = sample_log()
    print("real AV2 sample (2 sweeps; speeds from its annotations over the whole log):", end=" ")
    bench_dynamic_flag(Path(str(sample.parent.parent)), sample.name, args.repeat * 4)
    bench_conversion(root, log_id, work, max(1, args.repeat // 2))
    bench_ego_masks(work, max(1, args.repeat // 2 + 1))


if __name__ == "__main__":
    main()
