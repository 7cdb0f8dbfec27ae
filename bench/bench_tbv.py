"""Benchmark TbV conversion: memory per worker for a 15 s and a 120 s synthetic TbV log.

Not a test. Each log is converted by a fresh process (as by the command) with one worker (the log
is one job, the dataset-run mode) and with two (its stores shared between the workers). It prints
the peak resident set (VmHWM) of the largest worker and of the main process, the wall time and
the lidar path per sweep (read, firing-time reconstruction, decompensation, model elements,
write), medians over --repeat runs, and the 120 s / 15 s ratio of the worker peaks.

    python bench/bench_tbv.py [--work /tmp/ncore-bench] [--repeat 3]
"""

from __future__ import annotations

import shutil
import statistics
from pathlib import Path

from bench_argoverse2 import bench_parser, cached, work_dir
from bench_runner import memory
from upath import UPath


def synth_tbv(work: Path, seconds: float) -> Path:
    """(Once, cached) a synthetic TbV log of ``seconds`` (7 ring cameras at 20 fps); returns its root."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / f"tbv-{seconds:g}s"
    cached(
        root,
        f"{seconds:g} s TbV log",
        lambda r: write_log(UPath(r), SynthConfig(seconds=seconds, seed=17, tbv=True)).log_id,
    )
    return root


def main() -> None:
    args = bench_parser(__doc__, repeat=3).parse_args()
    work = work_dir(args)
    print(f"TbV memory: peak RSS (VmHWM) per process, one log per run, medians of {args.repeat}", flush=True)
    figures = {}
    for seconds in (15.0, 120.0):
        root = synth_tbv(work, seconds)
        for workers in (1, 2):
            samples = [memory(root, work / "tbv-out", workers, tbv=True) for _ in range(args.repeat)]
            m = {k: statistics.median(sample[k] for sample in samples) for k in samples[0]}
            figures[seconds, workers] = m
            print(
                f"  {seconds:>5g} s log, {workers} worker(s): largest worker {m['worker_mb']:.0f} MB, main process"
                f" {m['main_mb']:.0f} MB, {m['s']:.1f} s, lidar {m['lidar_ms_per_sweep']:.1f} ms/sweep",
                flush=True,
            )
    for workers in (1, 2):
        ratio = figures[120.0, workers]["worker_mb"] / figures[15.0, workers]["worker_mb"]
        print(f"  largest worker, 120 s / 15 s log, {workers} worker(s): {ratio:.3f}x")
    shutil.rmtree(work / "tbv-out", ignore_errors=True)


if __name__ == "__main__":
    main()
