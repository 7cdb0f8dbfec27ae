"""Benchmark validation. Not a test.

1. What validation adds to a conversion: ``ncore-convert argoverse2-v4`` of a synthetic 5 s AV2 log
   (50 sweeps, 9 cameras at 10 fps) with ``--no-validate`` and with validation (the default,
   including the source comparison), interleaved in one run, and the ratio.
2. ``validate_tree`` alone, with and without ``--source``, on that output and on the real sample.
3. A cooperative scenario (60 frames, 3 CAVs + RSU): validation of every agent plus co-registration.

Figures are medians over --repeat runs.

    python bench/bench_validate.py [--work /tmp/ncore-bench] [--repeat 3]
"""

from __future__ import annotations

import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench_argoverse2 import bench_parser, cached, work_dir
from upath import UPath

from ncore_convert.validate.tree import validate_tree

CLI = Path(sys.executable).parent / "ncore-convert"


def convert(root: Path, out: Path, command: list[str], validate: bool) -> float:
    shutil.rmtree(out, ignore_errors=True)
    started = time.perf_counter()
    flag = "--validate" if validate else "--no-validate"
    subprocess.run(
        [
            str(CLI),
            "--no-progress",
            "--workers",
            "1",
            flag,
            "--root-dir",
            str(root),
            "--output-dir",
            str(out),
            *command,
        ],
        check=True,
        capture_output=True,
    )
    return time.perf_counter() - started


def median_seconds(repeat: int, run) -> float:
    times = []
    for _ in range(repeat):
        started = time.perf_counter()
        reports = run()
        times.append(time.perf_counter() - started)
        assert all(r.ok for r in reports), [(r.sequence, [c for c in r.checks if not c.ok]) for r in reports]
    return statistics.median(times)


def side_by_side(label: str, root: Path, work: Path, command: list[str], repeat: int) -> Path:
    times: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(repeat):
        for validate in (False, True):
            times[validate].append(convert(root, work / f"validate-out-{validate}", command, validate))
    plain, checked = statistics.median(times[False]), statistics.median(times[True])
    print(
        f"  {label}, whole command: {plain:.2f} s with --no-validate, {checked:.2f} s validated,"
        f" ratio {checked / plain:.2f}",
        flush=True,
    )
    return work / "validate-out-True"


def main() -> None:
    args = bench_parser(__doc__, repeat=3).parse_args()
    work = work_dir(args)
    print(f"validation; medians of {args.repeat}", flush=True)
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    av2_root = work / "validate-av2-5s"
    cached(
        av2_root,
        "the AV2 log",
        lambda r: write_log(UPath(r / "val"), SynthConfig(seconds=5.0, seed=3, camera_fps=10)).log_id,
    )
    out = side_by_side(
        "AV2 5 s log (50 sweeps, 450 images)", av2_root, work, ["argoverse2-v4", "--split", "val"], args.repeat
    )
    alone = median_seconds(args.repeat, lambda: validate_tree(UPath(out)))
    with_source = median_seconds(args.repeat, lambda: validate_tree(UPath(out), UPath(av2_root)))
    print(f"  validate_tree on it: {alone:.2f} s, with --source {with_source:.2f} s", flush=True)

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from conftest import find_av2_sample

    sample = find_av2_sample()
    real_out = work / "validate-real"
    convert(sample, real_out, ["argoverse2-v4", "--split", "val"], validate=False)
    alone = median_seconds(args.repeat, lambda: validate_tree(UPath(real_out)))
    with_source = median_seconds(args.repeat, lambda: validate_tree(UPath(real_out), UPath(sample)))
    print(
        f"  validate_tree on the real sample (2 sweeps, 11,364 cuboids): {alone:.2f} s, with --source"
        f" {with_source:.2f} s",
        flush=True,
    )

    from ncore_convert.synth.opencood import SynthConfig as OpenCoodConfig
    from ncore_convert.synth.opencood import write_dataset

    v2x_root = work / "validate-v2xset-60"
    config = OpenCoodConfig(dataset="v2xset", frames=60, cavs=3, infrastructure=1, lidar_columns=720)
    cached(v2x_root, "the V2XSet scenario", lambda r: write_dataset(UPath(r), config)[0].scenario)
    side_by_side("V2XSet 60 frames x 4 agents", v2x_root, work, ["v2xset-v4", "--split", "test"], args.repeat)


if __name__ == "__main__":
    main()
