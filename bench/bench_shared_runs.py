"""Benchmark runs that share an output folder, and stopping a run (issue 50).

Not a test. Figures are medians over --repeat runs, measured side by side in one run:
- bookkeeping per log: claiming and releasing a log (``run.claims``) and merging its report entry
  (``run.report``: flock, re-read, atomic replace) on a local folder, against the plain atomic
  rewrite of the report that came before (no lock, no re-read), for a report of --entries logs;
- sharing: the same --logs synthetic logs converted by one command with 2 workers, and by 2
  commands with 1 worker each started together on one output (claims split the logs), interleaved;
- stopping: SIGINT to a 2-worker run right after its first log is published; seconds from the
  signal to the exit.

    python bench/bench_shared_runs.py [--work /tmp/ncore-bench] [--repeat 3] [--logs 4] [--entries 1000]
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_argoverse2 import bench_parser, cached, work_dir
from upath import UPath

CLI = Path(sys.executable).parent / "ncore-convert"


def bookkeeping(entries: int, repeat: int) -> None:
    """Per-log cost of a claim (acquire + release) and of a merged report record, in ms."""
    from ncore_convert.run.claims import Claims
    from ncore_convert.run.report import RunReport
    from ncore_convert.run.runner import LogResult
    from ncore_convert.storage import flush_to_disk

    def plain_rewrite(report: RunReport, result: LogResult) -> None:  # before issue 50
        report.logs[result.log_id] = {"status": "ok", "warnings": [], "error": None}
        tmp = report.path.parent / f".{report.path.name}.tmp"
        tmp.write_text(json.dumps({"converter": report.fingerprint, "logs": report.logs}, indent=2))
        flush_to_disk(tmp)
        tmp.rename(report.path)

    samples = {"claim": [], "merged record": [], "plain rewrite": []}
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as folder:
            root = UPath(folder)
            report = RunReport(root, {"name": "bench"})
            report._merge({f"old-{i}": {"status": "ok", "warnings": [], "error": None} for i in range(entries)})
            with Claims(root) as claims:
                n = 50
                t = time.perf_counter()
                for i in range(n):
                    claims.acquire(f"log-{i}")
                    claims.release(f"log-{i}")
                samples["claim"].append((time.perf_counter() - t) / n * 1e3)
            for name in ("merged record", "plain rewrite"):
                t = time.perf_counter()
                for i in range(n):
                    result = LogResult(f"{name}-{i}", True)
                    report.record(result, 0, 0) if name == "merged record" else plain_rewrite(report, result)
                samples[name].append((time.perf_counter() - t) / n * 1e3)
    med = {k: statistics.median(v) for k, v in samples.items()}
    print(f"bookkeeping per log, report of {entries} logs, medians of {repeat}:")
    print(f"  claim + release            {med['claim']:7.2f} ms")
    print(f"  merged report record       {med['merged record']:7.2f} ms")
    print(f"  plain atomic rewrite       {med['plain rewrite']:7.2f} ms")
    print(f"  merged / plain             {med['merged record'] / med['plain rewrite']:7.2f}x")


def synth(work: Path, count: int) -> tuple[Path, list[str]]:
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / f"shared-{count}x1s"

    def write(folder: Path) -> str:
        configs = [SynthConfig(seconds=1.0, seed=200 + s, camera_fps=10) for s in range(count)]
        return " ".join(write_log(UPath(folder / "val"), c).log_id for c in configs)

    return root, cached(root, f"{count} logs of 1 s", write).split()


def command(root: Path, out: Path, workers: int) -> list[str]:
    """The conversion command (without validation: the runner is measured, not the checks)."""
    group = ["--no-progress", "--no-validate", "--root-dir", str(root), "--output-dir", str(out)]
    return [str(CLI), *group, "--workers", str(workers), "argoverse2-v4", "--split", "val"]


def sharing(root: Path, work: Path, repeat: int) -> None:
    one, two = [], []
    for _ in range(repeat):
        out = work / "shared-out"
        shutil.rmtree(out, ignore_errors=True)
        t = time.perf_counter()
        subprocess.run(command(root, out, 2), check=True, capture_output=True)
        one.append(time.perf_counter() - t)
        shutil.rmtree(out, ignore_errors=True)
        t = time.perf_counter()
        procs = [subprocess.Popen(command(root, out, 1), stdout=subprocess.DEVNULL) for _ in range(2)]
        assert all(p.wait() == 0 for p in procs)
        two.append(time.perf_counter() - t)
    ratios = [b / a for a, b in zip(one, two, strict=True)]
    print(f"sharing, medians of {repeat} interleaved runs:")
    print(f"  1 command, 2 workers       {statistics.median(one):7.2f} s")
    print(f"  2 commands, 1 worker each  {statistics.median(two):7.2f} s")
    print(f"  2 commands / 1 command     {statistics.median(ratios):7.2f}x")


def stopping(root: Path, work: Path, repeat: int) -> None:
    seconds, published = [], []
    for _ in range(repeat):
        out = work / "stop-out"
        shutil.rmtree(out, ignore_errors=True)
        proc = subprocess.Popen(command(root, out, 2), stdout=subprocess.DEVNULL)
        while not [p for p in out.glob("*") if p.is_dir() and not p.name.startswith(".")] if out.exists() else True:
            time.sleep(0.005)
        os.kill(proc.pid, signal.SIGINT)
        t = time.perf_counter()
        assert proc.wait() == 130
        seconds.append(time.perf_counter() - t)
        published.append(len(json.loads((out / "conversion-report.json").read_text())["logs"]))
    print(f"stopping (SIGINT after the first publish), medians of {repeat}:")
    print(f"  signal to exit             {statistics.median(seconds):7.3f} s (max {max(seconds):.3f} s)")
    print(f"  logs published and recorded {statistics.median(published):6.0f}")


def main() -> None:
    parser = bench_parser(__doc__, repeat=3)
    parser.add_argument("--logs", type=int, default=4)
    parser.add_argument("--entries", type=int, default=1000)
    args = parser.parse_args()
    work = work_dir(args)
    bookkeeping(args.entries, args.repeat)
    root, _ = synth(work, args.logs)
    sharing(root, work, args.repeat)
    stopping(root, work, args.repeat)


if __name__ == "__main__":
    main()
