"""Benchmark: convert full-size synthetic AV2 logs and compare with copying their bytes.

Not a test. Prints, for a 5 s and a 15 s log (50 / 150 sweeps, 9 cameras at 20 fps, realistic JPEG
sizes): conversion wall time, lidar-path ms per sweep (read + decompensate + write, both units,
single thread), peak RSS, and the ratio of conversion time to `cp -r` of the same log, all measured
side by side in one run. Figures are medians over --repeat runs.

    python bench/bench_argoverse2.py [--work /tmp/ncore-bench] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from upath import UPath


def synth(work: Path, seconds: float) -> Path:
    """Generate (once, cached in `work`) a synthetic log of the given length; returns its log dir."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / f"src-{seconds:g}s"
    done = root / "DONE"
    if not done.exists():
        shutil.rmtree(root, ignore_errors=True)
        t = time.perf_counter()
        truth = write_log(UPath(root / "val"), SynthConfig(seconds=seconds, seed=7))
        print(f"  synthesised {seconds:g} s log in {time.perf_counter() - t:.0f} s", flush=True)
        done.write_text(truth.log_id)
    return root / "val" / done.read_text()


def child_convert(root: str, out: str, log_id: str) -> None:
    """Run one conversion in this process and print its figures as JSON (peak RSS is per process)."""
    from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log

    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    s = convert_log(UPath(root), UPath(out), log_id, Argoverse2Options(split="val"))
    wall = time.perf_counter() - t
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(
        json.dumps(
            {
                "wall_s": wall,
                "sweeps": s.sweeps,
                "images": s.images,
                "points": s.points,
                "lidar_s": s.lidar_seconds,
                "camera_s": s.camera_seconds,
                "peak_rss_mb": rss_mb,
            }
        )
    )


def du_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def measure(log_dir: Path, work: Path, repeat: int) -> dict:
    copies, runs = [], []
    for _ in range(repeat):
        dest = work / "copy"
        shutil.rmtree(dest, ignore_errors=True)
        t = time.perf_counter()
        subprocess.run(["cp", "-r", str(log_dir), str(dest)], check=True)
        subprocess.run(["sync"], check=True)
        copies.append(time.perf_counter() - t)
        shutil.rmtree(dest)
        out = subprocess.run(
            [sys.executable, __file__, "--child", str(log_dir.parent.parent), str(work / "out"), log_dir.name],
            check=True, capture_output=True, text=True,
        )  # fmt: skip
        run = json.loads(out.stdout.strip().splitlines()[-1])
        run["sync_s"] = _timed_sync()
        runs.append(run)
    med = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    med["cp_s"] = statistics.median(copies)
    med["bytes"] = du_bytes(log_dir)
    med["out_bytes"] = du_bytes(work / "out")
    return med


def _timed_sync() -> float:
    t = time.perf_counter()
    subprocess.run(["sync"], check=True)
    return time.perf_counter() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", default="/tmp/ncore-bench")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--child", nargs=3, metavar=("ROOT", "OUT", "LOG_ID"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child_convert(*args.child)
        return
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    results = {}
    for seconds in (5.0, 15.0):
        print(f"{seconds:g} s log:", flush=True)
        results[seconds] = r = measure(synth(work, seconds), work, args.repeat)
        conv = r["wall_s"] + r["sync_s"]
        print(
            f"  {r['sweeps']:.0f} sweeps, {r['images']:.0f} images, {r['bytes'] / 1e9:.2f} GB in, {r['out_bytes'] / 1e9:.2f} GB out\n"
            f"  convert wall        {r['wall_s']:.2f} s (+ sync {r['sync_s']:.2f} s)\n"
            f"  lidar path          {1e3 * r['lidar_s'] / r['sweeps']:.1f} ms/sweep (both units, one thread)\n"
            f"  camera path         {1e3 * r['camera_s'] / r['images']:.2f} ms/image\n"
            f"  cp -r (+ sync)      {r['cp_s']:.2f} s\n"
            f"  convert / copy      {conv / r['cp_s']:.2f}x\n"
            f"  peak RSS            {r['peak_rss_mb']:.0f} MB",
            flush=True,
        )
    a, b = results[5.0], results[15.0]
    print(f"peak RSS 15 s / 5 s log: {b['peak_rss_mb'] / a['peak_rss_mb']:.2f}x (medians of {args.repeat} runs)")


if __name__ == "__main__":
    main()
