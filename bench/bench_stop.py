"""Stopped runs leave nothing behind (issue 65's acceptance; docs/scale-out.md): SIGTERM to the
process and SIGINT to its process group at each moment of a grid, into a 6-log run, with
``--workers 2`` and the default worker count, stdout piped. Per trial: the exit code, seconds from
the signal to the exit, processes of the run alive 3 s after the exit, paths under the output
folder changed after the exit, and whether anything but the stop's lines was printed.

    python bench/bench_stop.py [--moments 0.3,0.6,0.9,1.2,1.5,2.0] [--pid1] [--work DIR]
    python bench/bench_stop.py --window [--repeat 25]

``--pid1`` runs the command as PID 1 of a new PID namespace (``unshare --pid --fork``, root only).
``--window`` measures the window before the stop handlers: from the command's start (its spawn) to
the moment its SIGTERM is caught (``SigCgt`` in ``/proc/<pid>/status``; Python catches SIGINT from
its own start-up, SIGTERM only once ``stop.install`` ran), median of ``--repeat`` runs of
``ncore-convert --version``, beside the interpreter whose first statement installs a handler.
"""

from __future__ import annotations

import argparse
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from stop_trials import trial  # noqa: E402

from ncore_convert.synth.argoverse2 import SynthConfig, write_log  # noqa: E402

BIN = Path(sys.executable).parent / "ncore-convert"
STOP_LINES = re.compile(r"^(ok    |skip  |stop  |left  |      |SIG(INT|TERM): |\d+ converted, \d+ skipped, \d+ failed)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--moments", default="0.3,0.6,0.9,1.2,1.5,2.0")
    parser.add_argument("--pid1", action="store_true")
    parser.add_argument("--work", type=Path, default=None)
    parser.add_argument("--window", action="store_true")
    parser.add_argument("--repeat", type=int, default=25)
    args = parser.parse_args()
    if args.window:
        handlers = statistics.median(_until_sigterm_caught([str(BIN), "--version"]) for _ in range(args.repeat))
        first = "import signal, time; signal.signal(signal.SIGTERM, print); time.sleep(0.3)"
        bare = statistics.median(_until_sigterm_caught([sys.executable, "-c", first]) for _ in range(args.repeat))
        print(f"window before the stop handlers: median {handlers:.1f} ms from the spawn ({args.repeat} runs);")
        print(f"the interpreter alone, a handler as its first statement: median {bare:.1f} ms")
        return
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-stop-"))
    root = work / "source"
    if not (root / "val").exists():
        for seed in range(61, 67):
            write_log(root / "val", SynthConfig(seconds=0.5, seed=seed, camera_fps=10, pictures=2, camera_scale=4))
    moments = [float(m) for m in args.moments.split(",")]
    prefix = ["unshare", "--pid", "--fork", "--mount-proc"] if args.pid1 else []
    clean, exits = 0, []
    cases = [
        (sig, group, workers)
        for sig, group in ((signal.SIGTERM, False), (signal.SIGINT, True))
        for workers in (("--workers", "2"), ())
    ]
    for signum, group, workers in cases:
        for moment in moments:
            out = work / "out"
            shutil.rmtree(out, ignore_errors=True)
            command = [*prefix, str(BIN), "--no-progress", *workers, "--root-dir", str(root), "--output-dir", str(out)]
            result = trial(command + ["argoverse2-v4", "--split", "val"], out, moment, signum, group, args.pid1)
            quiet = all(STOP_LINES.match(line) for line in result.output.strip().splitlines())
            ok = result.clean and quiet
            clean += ok
            exits.append(result.exit_s)
            print(
                f"{signal.Signals(signum).name:7s} {'group' if group else 'pid':5s}"
                f" {' '.join(workers) or 'default':11s}"
                f" at {moment:.1f} s: exit {result.returncode} after {result.exit_s:.2f} s,"
                f" alive 3 s later {len(result.survivors)}, changed after exit {len(result.changed)},"
                f" only stop lines {quiet}" + ("" if ok else f"\n{result.output[-1500:]}\n{result.survivors}"),
                flush=True,
            )
    print(
        f"\n{clean} of {len(exits)} trials clean; signal to exit: median {statistics.median(exits):.2f} s,"
        f" max {max(exits):.2f} s"
    )


def _sigterm_caught(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as f:
            caught = next(line for line in f if line.startswith("SigCgt:"))
    except (OSError, StopIteration):
        return False
    return bool(int(caught.split()[1], 16) >> (signal.SIGTERM - 1) & 1)


def _until_sigterm_caught(command: list[str]) -> float:
    """Milliseconds from the spawn of ``command`` until its process catches SIGTERM (polled)."""
    started = time.perf_counter()
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while proc.poll() is None and not _sigterm_caught(proc.pid):
        pass
    seen = time.perf_counter()
    proc.wait()
    return (seen - started) * 1e3


if __name__ == "__main__":
    main()
