"""Benchmark TbV conversion: memory per worker for a 15 s and a 120 s synthetic TbV log.

Not a test. Each log is converted by a fresh process (as by the command) with one worker (the log
is one job, the dataset-run mode) and with two (its stores shared between the workers). It prints
the peak resident set (VmHWM) of the largest worker and of the main process, the wall time and
the lidar path per sweep (read, firing-time reconstruction, decompensation, model elements,
write), medians over --repeat runs, and the 120 s / 15 s ratio of the worker peaks.

    python bench/bench_tbv.py [--work /tmp/ncore-bench] [--repeat 3]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import time
from pathlib import Path

from bench_runner import memory
from upath import UPath


def synth_tbv(work: Path, seconds: float) -> Path:
    """(Once, cached) a synthetic TbV log of ``seconds`` (7 ring cameras at 20 fps); returns its root."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / f"tbv-{seconds:g}s"
    if not (root / "DONE").exists():
        shutil.rmtree(root, ignore_errors=True)
        started = time.perf_counter()
        write_log(UPath(root), SynthConfig(seconds=seconds, seed=17, tbv=True))
        print(f"  synthesised {seconds:g} s TbV log in {time.perf_counter() - started:.0f} s", flush=True)
        (root / "DONE").write_text("")
    return root


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="/tmp/ncore-bench")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
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
