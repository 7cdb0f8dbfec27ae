"""Benchmark the runner: dataset throughput with 1 and 2 workers, and memory per worker vs log length.

Not a test. Figures are medians over --repeat runs (this machine is noisy):
- throughput: the same --logs synthetic logs (--seconds each, 9 cameras at 20 fps) converted with
  1 and with 2 workers, interleaved, as logs per minute; both through warm worker processes (the
  runner alone: every log of a dataset run after the first) and as the whole ``ncore-convert``
  command from process start; the speedup is the median of the per-run ratios;
- memory: a 15 s and a 60 s log, each converted by a fresh command-like run; the peak resident
  set (VmHWM) of the largest worker process and of the main process. With one worker, the log is
  one job (the dataset-run mode); with two, its stores are shared between the workers. Each log
  is measured as synthesised (with annotations) and without its annotations.feather (as TbV
  and the AV2 test split): NCore stores all cuboid observations of a log in one JSON attribute,
  so that part of the memory grows with the number of annotations.

    python bench/bench_runner.py [--work /tmp/ncore-bench] [--logs 6] [--seconds 2] [--repeat 3]
                                 [--skip-throughput]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

from bench_argoverse2 import bench_parser, cached, process_tree, work_dir
from upath import UPath


def synth_logs(work: Path, count: int, seconds: float) -> Path:
    """(Once, cached) ``count`` synthetic logs of ``seconds`` each under ``<root>/val``; returns root."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    def write(root: Path) -> str:
        for seed in range(count):
            write_log(UPath(root / "val"), SynthConfig(seconds=seconds, seed=100 + seed))
        return ""

    root = work / f"runner-{count}x{seconds:g}s"
    cached(root, f"{count} logs of {seconds:g} s", write)
    return root


def long_log_root(work: Path, seconds: float, annotations: bool) -> Path:
    """(Once, cached) one synthetic log of ``seconds``, shared with bench_argoverse2; returns its root.
    Without annotations: a hard-linked copy without annotations.feather."""
    from bench_argoverse2 import synth

    root = synth(work, seconds).parent.parent
    if annotations:
        return root
    bare = work / f"{root.name}-no-annotations"
    if not bare.exists():
        shutil.copytree(root, bare, copy_function=os.link)
        for path in bare.glob("val/*/annotations.feather"):
            path.unlink()
    return bare


def run_dataset(executor, root: Path, out: Path, tbv: bool = False) -> tuple[float, list]:
    """Convert every log under root/val (TbV: under root) with the runner; returns the seconds to
    synced files and the per-log results."""
    from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
    from ncore_convert.run.runner import run_logs
    from ncore_convert.sources import argoverse2
    from ncore_convert.sources import tbv as tbv_source

    shutil.rmtree(out, ignore_errors=True)
    options = Argoverse2Options(split=None if tbv else "val")
    log_ids = tbv_source.list_log_ids(UPath(root)) if tbv else argoverse2.list_log_ids(UPath(root), "val")
    t = time.perf_counter()
    task = partial(convert_log, UPath(root), options=options)
    results = run_logs(
        UPath(out), log_ids, task, executor, echo=lambda line: None, show_progress=False, mode="overwrite"
    )
    subprocess.run(["sync"], check=True)
    elapsed = time.perf_counter() - t
    failed = [r.error for r in results if not r.ok]
    if failed:
        raise SystemExit(f"conversion failed: {failed[0]}")
    return elapsed, results


def run_command(root: Path, out: Path, workers: int) -> float:
    """The whole command, from process start to synced files."""
    shutil.rmtree(out, ignore_errors=True)
    cli = Path(sys.executable).parent / "ncore-convert"
    t = time.perf_counter()
    subprocess.run(
        [
            str(cli),
            "--root-dir",
            str(root),
            "--output-dir",
            str(out),
            "--workers",
            str(workers),
            "--no-progress",
            "--no-validate",
            "argoverse2-v4",
            "--split",
            "val",
        ],
        check=True,
        capture_output=True,
    )
    subprocess.run(["sync"], check=True)
    return time.perf_counter() - t


def _ready(progress) -> int:
    return os.getpid()


def _vm_hwm_bytes(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return 0


def child_memory(root: str, out: str, workers: int, tbv: bool) -> None:
    """Convert the one log under root/val (TbV: root) in a fresh process; print the peak RSS of the
    largest worker and of this process, the time and the lidar path per sweep as JSON."""
    from ncore_convert.run.executors import LocalExecutor
    from ncore_convert.run.pool import JobPool

    with LocalExecutor(JobPool(workers, preload=["ncore_convert.converters.argoverse2"])) as executor:
        executor.pool.run([(_ready, ())] * workers)
        wall, results = run_dataset(executor, Path(root), Path(out), tbv)
        workers_peak = max(_vm_hwm_bytes(pid) for pid in process_tree(os.getpid()) if pid != os.getpid())
    sweeps = sum(r.summary.frames for r in results)
    lidar_ms = 1e3 * sum(r.summary.lidar_seconds for r in results) / max(1, sweeps)
    figures = {"worker_mb": workers_peak / 2**20, "main_mb": _vm_hwm_bytes(os.getpid()) / 2**20, "s": wall}
    print(json.dumps({**figures, "lidar_ms_per_sweep": lidar_ms}))


def memory(root: Path, out: Path, workers: int, tbv: bool = False) -> dict:
    """One fresh-process conversion of the log under ``root`` (see :func:`child_memory`)."""
    args = [sys.executable, str(Path(__file__).resolve()), "--child-memory", str(root), str(out), str(workers)]
    args += ["--tbv"] if tbv else []
    proc = subprocess.run(args, check=True, capture_output=True, text=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def throughput(work: Path, logs: int, seconds: float, repeat: int) -> None:
    from ncore_convert.run.executors import LocalExecutor
    from ncore_convert.run.pool import JobPool

    root = synth_logs(work, logs, seconds)
    print(f"throughput: {logs} logs of {seconds:g} s, medians of {repeat} interleaved runs", flush=True)
    runs = []
    with (
        LocalExecutor(JobPool(1, preload=["ncore_convert.converters.argoverse2"])) as one,
        LocalExecutor(JobPool(2, preload=["ncore_convert.converters.argoverse2"])) as two,
    ):
        one.pool.run([(_ready, ())])
        two.pool.run([(_ready, ())] * 2)
        for _ in range(repeat):
            run = {
                "runner_1": run_dataset(one, root, work / "runner-out")[0],
                "runner_2": run_dataset(two, root, work / "runner-out")[0],
                "command_1": run_command(root, work / "runner-out", 1),
                "command_2": run_command(root, work / "runner-out", 2),
            }
            run["runner_speedup"] = run["runner_1"] / run["runner_2"]
            run["command_speedup"] = run["command_1"] / run["command_2"]
            runs.append(run)
            print("  " + ", ".join(f"{k} {v:.2f}" for k, v in run.items()), flush=True)
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    per_min = {k: 60 * logs / med[k] for k in ("runner_1", "runner_2", "command_1", "command_2")}
    print(
        f"  runner (warm workers)  1 worker {per_min['runner_1']:.1f} logs/min, 2 workers {per_min['runner_2']:.1f}"
        f" logs/min: speedup {med['runner_speedup']:.2f}x\n"
        f"  whole command          1 worker {per_min['command_1']:.1f} logs/min, 2 workers {per_min['command_2']:.1f}"
        f" logs/min: speedup {med['command_speedup']:.2f}x",
        flush=True,
    )


def main() -> None:
    parser = bench_parser(__doc__, repeat=3)
    parser.add_argument("--logs", type=int, default=6)
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--skip-throughput", action="store_true")
    parser.add_argument("--tbv", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--child-memory", nargs=3, metavar=("ROOT", "OUT", "WORKERS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child_memory:
        root, out, workers = args.child_memory
        child_memory(root, out, int(workers), args.tbv)
        return
    work = work_dir(args)
    if not args.skip_throughput:
        throughput(work, args.logs, args.seconds, args.repeat)
    print("memory: peak RSS (VmHWM) per process, one log per run", flush=True)
    figures = {}
    for annotated in (True, False):
        for seconds in (15.0, 60.0):
            log_root = long_log_root(work, seconds, annotated)
            for workers in (1, 2):
                samples = [memory(log_root, work / "memory-out", workers) for _ in range(args.repeat)]
                m = {k: statistics.median(sample[k] for sample in samples) for k in samples[0]}
                figures[annotated, seconds, workers] = m
                print(
                    f"  {seconds:>4g} s log, {'with' if annotated else 'without'} annotations, {workers} worker(s):"
                    f" largest worker {m['worker_mb']:.0f} MB, main process {m['main_mb']:.0f} MB ({m['s']:.1f} s)",
                    flush=True,
                )
    for annotated in (True, False):
        for workers in (1, 2):
            ratio = figures[annotated, 60.0, workers]["worker_mb"] / figures[annotated, 15.0, workers]["worker_mb"]
            label = "with" if annotated else "without"
            print(f"  largest worker, 60 s / 15 s log, {label} annotations, {workers} worker(s): {ratio:.3f}x")
    shutil.rmtree(work / "memory-out", ignore_errors=True)
    shutil.rmtree(work / "runner-out", ignore_errors=True)


if __name__ == "__main__":
    main()
