"""Benchmark: what a user's default command costs next to the floor (issue 28). Not a test.

On one synthetic 15 s AV2 log (``synth argoverse2 --seconds 15 --seed 2 --pictures 16``: 150 sweeps, 2,790 images),
whole commands from process start to synced files, interleaved in every round
(copy, --no-validate, default, validate alone, NCore's own converter, copy, ...):
- ``cp -r`` of the log plus ``sync`` (the floor);
- ``ncore-convert --no-validate argoverse2-v4`` with the default workers;
- the default command (validation on, against the source);
- validation alone: ``ncore-convert validate OUT --source ROOT`` on that output;
- NCore's own AV2 converter (``tools/data_converter/argoverse2`` of an NVIDIA/ncore checkout; it is not
  in the nvidia-ncore wheel), when ``--ncore-repo`` or ``$NCORE_REPO`` names one. Otherwise the row
  says it was skipped.
Prints medians over --repeat rounds and the two ratios issue 28 accepts on: default / --no-validate
(target <= 1.15) and --no-validate / copy (target <= 3.0).

    python bench/bench_speed.py [--work /tmp/ncore-bench] [--repeat 3] [--ncore-repo DIR]
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench_argoverse2 import bench_parser, cached, copy, du_bytes, work_dir
from upath import UPath

CLI = Path(sys.executable).parent / "ncore-convert"


def timed(command: list[str], out: Path | None, env: dict | None = None) -> float:
    """Wall seconds of ``command`` plus ``sync``; ``out`` is removed first (a fresh conversion)."""
    if out is not None:
        shutil.rmtree(out, ignore_errors=True)
    subprocess.run(["sync"], check=True)
    started = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, env=env)
    subprocess.run(["sync"], check=True)
    return time.perf_counter() - started


def speed_log(work: Path) -> tuple[Path, str]:
    """The 15 s synthetic AV2 log the speed benchmarks share (150 sweeps, 9 cameras at 20 fps),
    synthesised once into ``work/speed-av2-15s``: its root (``--root-dir``) and log id."""
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    root = work / "speed-av2-15s"
    config = SynthConfig(seconds=15.0, seed=2)
    return root, cached(root, "the 15 s AV2 log", lambda r: write_log(UPath(r / "val"), config).log_id)


def ours(root: Path, out: Path, validate: bool) -> list[str]:
    flag = "--validate" if validate else "--no-validate"
    return [
        str(CLI),
        "--no-progress",
        flag,
        "--root-dir",
        str(root),
        "--output-dir",
        str(out),
        "argoverse2-v4",
        "--split",
        "val",
    ]


def upstream(repo: Path, root: Path, out: Path) -> tuple[list[str], dict]:
    """NCore's own AV2 converter, run from a source checkout with this interpreter."""
    main = repo / "tools" / "data_converter" / "argoverse2" / "main.py"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(repo), os.environ.get("PYTHONPATH")]))}
    return [
        sys.executable,
        str(main),
        "--root-dir",
        str(root),
        "--output-dir",
        str(out),
        "argoverse2-v4",
        "--split",
        "val",
    ], env


def main() -> None:
    parser = bench_parser(__doc__, repeat=3)
    parser.add_argument("--ncore-repo", default=os.environ.get("NCORE_REPO"), help="an NVIDIA/ncore checkout")
    args = parser.parse_args()
    work = work_dir(args)

    root, log_id = speed_log(work)
    log_dir = root / "val" / log_id
    repo = Path(args.ncore_repo) if args.ncore_repo else None
    if repo is not None and not (repo / "tools" / "data_converter" / "argoverse2" / "main.py").is_file():
        sys.exit(f"{repo}: not an NVIDIA/ncore checkout (no tools/data_converter/argoverse2/main.py)")

    rows: dict[str, list[float]] = {}
    for round_ in range(args.repeat):
        times = {
            "cp -r + sync": copy(log_dir, work / "speed-copy"),
            "--no-validate": timed(ours(root, work / "speed-plain", False), work / "speed-plain"),
            "default (validated)": timed(ours(root, work / "speed-default", True), work / "speed-default"),
            "validate alone": timed([str(CLI), "validate", str(work / "speed-plain"), "--source", str(root)], None),
        }
        if repo is not None:
            command, env = upstream(repo, root, work / "speed-upstream")
            times["NCore's own AV2 converter"] = timed(command, work / "speed-upstream", env)
        for label, seconds in times.items():
            rows.setdefault(label, []).append(seconds)
        print(f"  round {round_ + 1}: " + ", ".join(f"{k} {v:.2f} s" for k, v in times.items()), flush=True)

    med = {label: statistics.median(seconds) for label, seconds in rows.items()}
    print(
        f"15 s AV2 log ({du_bytes(log_dir) / 1e9:.2f} GB in, {du_bytes(work / 'speed-plain') / 1e9:.2f} GB out),"
        f" whole commands, medians of {args.repeat}:"
    )
    copy_s, plain_s = med["cp -r + sync"], med["--no-validate"]
    for label, seconds in med.items():
        print(f"  {label:<28} {seconds:7.2f} s  = {seconds / copy_s:.2f}x copy, {seconds / plain_s:.2f}x --no-validate")
    if repo is None:
        print(
            "  NCore's own AV2 converter    skipped: not in the nvidia-ncore wheel; pass --ncore-repo DIR"
            " (or set NCORE_REPO) to an NVIDIA/ncore checkout"
        )
    print(
        f"issue 28: default / --no-validate = {med['default (validated)'] / plain_s:.2f} (target <= 1.15);"
        f" --no-validate / copy = {plain_s / copy_s:.2f} (target <= 3.0)"
    )


if __name__ == "__main__":
    main()
