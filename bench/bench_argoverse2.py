"""Benchmark: convert full-size synthetic AV2 logs and compare with copying their bytes.

Not a test. For a 5 s and a 15 s log (50 / 150 sweeps, 9 cameras at 20 fps, realistic JPEG sizes)
it measures, side by side and interleaved (copy, convert, command, copy, convert, ...):
- ``cp -r`` of the log plus sync;
- one log's conversion through warm worker processes, to synced files (every log after the first
  of a dataset run), and its ratio to the copy (median of per-run ratios);
- the whole ``ncore-convert`` command for that one log, from process start (interpreter, imports,
  worker start-up) to synced files, and its ratio to the copy;
- lidar model derivation time per unit (slowest unit);
- lidar path ms per sweep (read, decompensate, assign model elements, write; both units, in one
  process), both inside the parallel run and alone on one core (``--no-cameras --workers 1``);
- peak RSS and CPU time of the log, summed over the process tree (sampled every 50 ms from /proc).
Figures are medians over --repeat runs; this machine is noisy.

    python bench/bench_argoverse2.py [--work /tmp/ncore-bench] [--repeat 5] [--workers N]
                                     [--lidar-model-source empirical|none]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from upath import UPath


def bench_parser(doc: str, repeat: int) -> argparse.ArgumentParser:
    """The options every benchmark has: --work (where synthetic inputs are cached) and --repeat."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="/tmp/ncore-bench")
    parser.add_argument("--repeat", type=int, default=repeat)
    return parser


def work_dir(args: argparse.Namespace) -> Path:
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    return work


def cached(root: Path, label: str, write: Callable[[Path], str | None]) -> str:
    """Synthesise into ``root`` once: ``root/DONE`` marks a finished synthesis and holds what
    ``write(root)`` returned (e.g. a log id); a partial one is redone."""
    done = root / "DONE"
    if not done.exists():
        shutil.rmtree(root, ignore_errors=True)
        started = time.perf_counter()
        text = write(root)
        print(f"  synthesised {label} in {time.perf_counter() - started:.0f} s", flush=True)
        done.write_text(text or "")
    return done.read_text()


def synth(work: Path, seconds: float) -> Path:
    """Generate (once, cached in `work`) a synthetic log of the given length; returns its log dir."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / f"src-{seconds:g}s"
    log_id = cached(
        root, f"{seconds:g} s log", lambda r: write_log(UPath(r / "val"), SynthConfig(seconds=seconds, seed=7)).log_id
    )
    return root / "val" / log_id


def process_tree(root_pid: int) -> dict[int, tuple[int, float]]:
    """(resident bytes, CPU seconds) of a process and all its descendants (Linux /proc)."""
    page, tick = os.sysconf("SC_PAGE_SIZE"), os.sysconf("SC_CLK_TCK")
    tree, todo = {}, [root_pid]
    while todo:
        pid = todo.pop()
        try:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            for task in os.listdir(f"/proc/{pid}/task"):
                with open(f"/proc/{pid}/task/{task}/children") as f:
                    todo += [int(child) for child in f.read().split()]
        except OSError:
            continue
        tree[pid] = (int(fields[21]) * page, (int(fields[11]) + int(fields[12])) / tick)
    return tree


def _ready(progress) -> int:
    return os.getpid()


def child_convert(root: str, out: str, log_id: str, workers: int, cameras: bool, model_source: str) -> None:
    """One log through a warm worker pool (as every log after the first in a dataset run);
    prints its figures as JSON. Time and CPU run from the start of the log to its synced files."""
    from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
    from ncore_convert.run.pool import JobPool

    shutil.rmtree(out, ignore_errors=True)
    peak, cpu = [0], {}
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.05):
            tree = process_tree(os.getpid())
            peak[0] = max(peak[0], sum(rss for rss, _ in tree.values()))
            cpu.update({pid: max(cpu.get(pid, 0.0), seconds) for pid, (_, seconds) in tree.items()})

    options = Argoverse2Options(split="val", camera_ids=None if cameras else (), lidar_model_source=model_source)
    with JobPool(workers, preload=["ncore_convert.converters.argoverse2"]) as pool:
        pool.run([(_ready, ())] * workers)
        cpu_before = sum(seconds for _, seconds in process_tree(os.getpid()).values())
        threading.Thread(target=sample, daemon=True).start()
        t = time.perf_counter()
        s = convert_log(UPath(root), UPath(out), log_id, options, pool=pool)
        subprocess.run(["sync"], check=True)
        wall = time.perf_counter() - t
        stop.set()
    figures = {"wall_s": wall, "sweeps": s.frames, "images": s.images, "points": s.points}
    figures.update(lidar_s=s.lidar_seconds, camera_s=s.camera_seconds, peak_rss_mb=peak[0] / 2**20)
    figures.update(cpu_s=sum(cpu.values()) - cpu_before, model_s=s.lidar_model_seconds)
    print(json.dumps(figures))


def convert(log_dir: Path, out: Path, workers: int, model_source: str, cameras: bool = True) -> dict:
    args = [sys.executable, __file__, "--child", str(log_dir.parent.parent), str(out), log_dir.name, str(workers)]
    args += ["--lidar-model-source", model_source]
    proc = subprocess.run(args + ([] if cameras else ["--no-cameras"]), check=True, capture_output=True, text=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def convert_cli(log_dir: Path, out: Path, workers: int, model_source: str) -> float:
    """The whole command for this one log, from process start (imports, pool start) to synced files."""
    cli = Path(sys.executable).parent / "ncore-convert"
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    subprocess.run(
        [
            str(cli),
            "--root-dir",
            str(log_dir.parent.parent),
            "--output-dir",
            str(out),
            "--workers",
            str(workers),
            "--no-progress",
            "--no-validate",
            "argoverse2-v4",
            "--split",
            "val",
            "--lidar-model-source",
            model_source,
        ],
        check=True,
        capture_output=True,
    )
    subprocess.run(["sync"], check=True)
    return time.perf_counter() - t


def copy(log_dir: Path, dest: Path) -> float:
    shutil.rmtree(dest, ignore_errors=True)
    subprocess.run(["sync"], check=True)
    t = time.perf_counter()
    subprocess.run(["cp", "-r", str(log_dir), str(dest)], check=True)
    subprocess.run(["sync"], check=True)
    elapsed = time.perf_counter() - t
    shutil.rmtree(dest)
    return elapsed


def du_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def measure(log_dir: Path, work: Path, repeat: int, workers: int, model_source: str) -> dict:
    runs, lidar_alone = [], []
    for _ in range(repeat):
        run = {"cp_s": copy(log_dir, work / "copy")}
        run.update(convert(log_dir, work / "out", workers, model_source))
        run["cli_s"] = convert_cli(log_dir, work / "out-cli", workers, model_source)
        run["ratio"] = run["wall_s"] / run["cp_s"]
        run["cli_ratio"] = run["cli_s"] / run["cp_s"]
        runs.append(run)
        alone = convert(log_dir, work / "out-lidar", 1, model_source, cameras=False)
        lidar_alone.append(1e3 * alone["lidar_s"] / alone["sweeps"])
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    med["lidar_alone_ms"] = statistics.median(lidar_alone)
    med["bytes"] = du_bytes(log_dir)
    med["out_bytes"] = du_bytes(work / "out")
    return med


def main() -> None:
    from ncore_convert.run.pool import default_workers

    parser = bench_parser(__doc__, repeat=5)
    parser.add_argument("--workers", type=int, default=default_workers())
    parser.add_argument("--lidar-model-source", choices=["empirical", "none"], default="empirical")
    parser.add_argument("--child", nargs=4, metavar=("ROOT", "OUT", "LOG_ID", "WORKERS"), help=argparse.SUPPRESS)
    parser.add_argument("--no-cameras", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        root, out, log_id, workers = args.child
        child_convert(root, out, log_id, int(workers), not args.no_cameras, args.lidar_model_source)
        return
    work = work_dir(args)
    print(
        f"{args.workers} worker process(es), lidar model {args.lidar_model_source},"
        f" medians of {args.repeat} interleaved runs",
        flush=True,
    )
    results = {}
    for seconds in (5.0, 15.0):
        print(f"{seconds:g} s log:", flush=True)
        workers = args.workers
        results[seconds] = r = measure(synth(work, seconds), work, args.repeat, workers, args.lidar_model_source)
        print(
            f"  {r['sweeps']:.0f} sweeps, {r['images']:.0f} images, {r['bytes'] / 1e9:.2f} GB in,"
            f" {r['out_bytes'] / 1e9:.2f} GB out\n"
            f"  cp -r + sync                                   {r['cp_s']:.2f} s\n"
            f"  convert one log (warm workers, + sync)         {r['wall_s']:.2f} s  = {r['ratio']:.2f}x copy\n"
            f"  whole command for this log (start to sync)     {r['cli_s']:.2f} s  = {r['cli_ratio']:.2f}x copy\n"
            f"  lidar model derivation (slowest unit)          {r['model_s']:.2f} s\n"
            f"  lidar path in the parallel run                 {1e3 * r['lidar_s'] / r['sweeps']:.1f} ms/sweep\n"
            f"  lidar path alone on one core                   {r['lidar_alone_ms']:.1f} ms/sweep\n"
            f"  camera path in the parallel run                {1e3 * r['camera_s'] / r['images']:.2f} ms/image\n"
            f"  CPU time, all processes                        {r['cpu_s']:.1f} s"
            f" ({r['cpu_s'] / (r['wall_s'] * workers):.0%} of {workers} cores)\n"
            f"  peak RSS, all processes                        {r['peak_rss_mb']:.0f} MB",
            flush=True,
        )
    a, b = results[5.0], results[15.0]
    print(f"peak RSS 15 s / 5 s log: {b['peak_rss_mb'] / a['peak_rss_mb']:.2f}x")


if __name__ == "__main__":
    main()
