"""Benchmark OPV2V conversion and PCD parsing. Not a test.

1. Conversion of a synthetic 150-frame OPV2V scenario with 4 CAVs (64 x 1024 lidar rays per frame,
   4 PNG cameras per agent), in a fresh ``ncore-convert opv2v-v4`` process with --workers 1 and 2
   (the agents' sequences are the jobs). Prints wall time, agent-frames/s and lidar points/s.
2. PCD parse rate, in points per second, of ``ncore_convert.sources.pcd.read_pcd`` against
   ``numpy.loadtxt`` on the same ASCII files, interleaved in the same run.
3. Per real OPV2V frame (the tests' ``opv2v-agent-sample``: 4 frames, ~57k points): the PCD parse beside
   the lidar model's element assignment (nearest laser, nearest azimuth column), and their ratio;
   the rays as the nearest float32 direction and distance beside the bit-exact ones
   (``transforms.lidar.rays.rays.exact_rays``), and the model measured from 3 frames' points (issue 38).

4. Reading back (issue 29): agent-frames per second through the OpenCOOD view of the converted
   scenario (``views.opencood``: the lidar points, the frame's YAML and its camera PNGs) beside
   reading the raw files the way the converter does (``read_pcd``, the safe YAML loader, the PNG
   bytes), interleaved frame by frame over a sample of agent-frames.

5. With --baseline-src OTHER/src: the whole 2-worker conversion of another checkout (e.g. the commit
   before a change, ``git worktree add /tmp/base <rev>``) interleaved with this one's, and the ratio.

Figures are medians over --repeat runs.

    python bench/bench_opencood.py [--work /tmp/ncore-bench] [--repeat 3] [--baseline-src /tmp/base/src]
"""

from __future__ import annotations

import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from bench_argoverse2 import bench_parser, cached, work_dir
from upath import UPath

FRAMES, CAVS, COLUMNS = 150, 4, 1024


def synth(work: Path) -> Path:
    """(Once, cached) the 150-frame, 4-CAV scenario; returns the dataset root."""
    from ncore_convert.synth.opencood import SynthConfig, write_dataset

    config = SynthConfig(dataset="opv2v", frames=FRAMES, cavs=CAVS, lidar_columns=COLUMNS)
    root = work / "opencood-150"
    cached(root, "the scenario", lambda r: write_dataset(UPath(r), config)[0].scenario)
    return root


def convert(root: Path, out: Path, workers: int, src: str | None = None) -> dict:
    """One whole ``opv2v-v4`` command; ``src``: run another checkout's ``src`` folder instead (on PYTHONPATH)."""
    shutil.rmtree(out, ignore_errors=True)
    cli = Path(sys.executable).parent / "ncore-convert"
    env = {**os.environ, "PYTHONPATH": src} if src else None
    started = time.perf_counter()
    run = subprocess.run(
        [
            str(cli),
            "--no-progress",
            "--no-validate",
            "--workers",
            str(workers),
            "--root-dir",
            str(root),
            "--output-dir",
            str(out),
            "opv2v-v4",
            "--split",
            "test",
        ],
        check=True,
        capture_output=True,
        text=True,
        env=env,
    )
    seconds = time.perf_counter() - started
    points = int(re.search(r"lidar frames, (\d+) points", run.stdout).group(1))
    scenario = next(p for p in out.iterdir() if p.is_dir())
    manifest = json.loads((scenario / "scenario.json").read_text())
    frames = sum(a["frames"] for a in manifest["agents"])
    return {"s": seconds, "frames": frames, "points": points}


def pcd_rates(root: Path, repeat: int) -> dict:
    from ncore_convert.sources.pcd import read_pcd

    files = sorted(root.glob("test/*/*/*.pcd"))[:: max(1, FRAMES // 5)][:8]
    rates: dict[str, list[float]] = {"read_pcd": [], "numpy.loadtxt": []}
    points = 0
    for _ in range(repeat):
        for path in files:
            started = time.perf_counter()
            columns = read_pcd(UPath(path))
            rates["read_pcd"].append(len(columns["x"]) / (time.perf_counter() - started))
            started = time.perf_counter()
            table = np.loadtxt(path, skiprows=11, dtype=np.float32)
            rates["numpy.loadtxt"].append(len(table) / (time.perf_counter() - started))
            assert np.array_equal(table[:, 0], columns["x"])  # the same points
            points = len(table)
    return {name: statistics.median(r) for name, r in rates.items()} | {"files": len(files), "points": points}


def model_cost(repeat: int) -> None:
    """Per real OPV2V frame, medians over frames and runs, side by side: the PCD parse, the rays as
    the nearest float32 direction and distance, the bit-exact rays (issue 38), the model-element
    assignment; and per agent, measuring the model from 3 frames' points (issue 38)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from conftest import find_opv2v_agent
    from test_carla_lidar import real_protocol

    from ncore_convert.sources.pcd import read_pcd
    from ncore_convert.transforms import carla
    from ncore_convert.transforms.lidar import carla as carla_lidar
    from ncore_convert.transforms.lidar.rays import exact_rays

    protocol = real_protocol()
    spec = carla_lidar.CarlaLidarSpec.from_protocol(protocol.cav_lidar, protocol.fixed_delta_seconds)
    model = carla_lidar.model(spec, np.pi)
    seconds: dict[str, list[float]] = {"parse": [], "nearest": [], "exact": [], "elements": [], "fit": []}
    points, inexact = [], []
    for _ in range(repeat):
        frames = []
        for path in sorted(find_opv2v_agent().glob("*.pcd")):
            started = time.perf_counter()
            data = read_pcd(UPath(path))
            parsed = time.perf_counter()
            xyz32 = carla.points_right_handed(np.stack([data["x"], data["y"], data["z"]], axis=1))
            xyz = xyz32.astype(np.float64)
            distance = np.linalg.norm(xyz, axis=1, keepdims=True)
            direction = (xyz / distance).astype(np.float32)
            nearest = time.perf_counter()
            _, _, left = exact_rays(xyz32)
            exact = time.perf_counter()
            carla_lidar.assign_elements(model, direction)
            done = time.perf_counter()
            for name, s in (
                ("parse", parsed - started),
                ("nearest", nearest - parsed),
                ("exact", exact - nearest),
                ("elements", done - exact),
            ):
                seconds[name].append(s)
            points.append(len(xyz))
            inexact.append(len(left))
            frames.append(direction.astype(np.float64))
        started = time.perf_counter()
        carla_lidar.fit_from_points([frames[i] for i in (0, 2, 3)], 0.05, None)  # 3, as the converter reads
        seconds["fit"].append(time.perf_counter() - started)
    ms = {name: statistics.median(s) * 1e3 for name, s in seconds.items()}
    print(
        f"  real OPV2V frame ({int(np.median(points))} points): PCD parse {ms['parse']:.1f} ms, model elements"
        f" {ms['elements']:.1f} ms, ratio {ms['elements'] / ms['parse']:.3f}",
        flush=True,
    )
    print(
        f"  rays: nearest float32 direction and distance {ms['nearest']:.1f} ms, bit-exact {ms['exact']:.1f} ms"
        f" (ratio {ms['exact'] / ms['nearest']:.1f}; {sum(inexact) / sum(points):.3%} of points stored beside"
        f" the rays); the model from 3 frames' points {ms['fit']:.0f} ms per agent",
        flush=True,
    )


def readback_rates(root: Path, out: Path, repeat: int, sample: int = 40) -> dict:
    """Agent-frames/s through the view and from the raw files (medians of per-frame times)."""
    from ncore_convert.sources.opencood import load_yaml
    from ncore_convert.sources.pcd import read_pcd
    from ncore_convert.views.opencood import OpenCoodScenario

    view = OpenCoodScenario.open(next(out.glob("*/scenario.json")))
    scenario_dir = root / "test" / view.manifest.scenario
    pairs = [(a, k) for a in view.agent_ids for k in view.keys(a)]
    pairs = pairs[:: max(1, len(pairs) // sample)][:sample]
    view_s, raw_s = [], []
    for _ in range(repeat):
        for agent_id, key in pairs:
            started = time.perf_counter()
            view.lidar_points(agent_id, key), view.params(agent_id, key), view.images(agent_id, key)
            view_s.append(time.perf_counter() - started)
            started = time.perf_counter()
            read_pcd(UPath(scenario_dir / agent_id / f"{key}.pcd"))
            load_yaml(UPath(scenario_dir / agent_id / f"{key}.yaml"))
            for png in sorted((scenario_dir / agent_id).glob(f"{key}_camera*.png")):
                png.read_bytes()
            raw_s.append(time.perf_counter() - started)
    return {"view": 1 / statistics.median(view_s), "raw": 1 / statistics.median(raw_s), "frames": len(pairs)}


def compare(root: Path, out: Path, baseline_src: str, repeat: int) -> None:
    """This checkout's conversion (2 workers) interleaved with another checkout's, medians of ``repeat``."""
    times: dict[str, list[float]] = {"baseline": [], "this": []}
    for _ in range(repeat):
        times["baseline"].append(convert(root, out, 2, baseline_src)["s"])
        times["this"].append(convert(root, out, 2)["s"])
    base, this = statistics.median(times["baseline"]), statistics.median(times["this"])
    print(
        f"  conversion, 2 workers, interleaved: baseline ({baseline_src}) {base:.1f} s, this checkout {this:.1f} s,"
        f" ratio {this / base:.3f}",
        flush=True,
    )


def main() -> None:
    parser = bench_parser(__doc__, repeat=3)
    parser.add_argument("--baseline-src", help="another checkout's src folder: its conversion, interleaved with ours")
    args = parser.parse_args()
    work = work_dir(args)
    model_cost(args.repeat)
    root = synth(work)
    if args.baseline_src:
        compare(root, work / "opencood-out", args.baseline_src, args.repeat)
    size_mb = sum(p.stat().st_size for p in root.rglob("*") if p.is_file()) / 1e6
    print(f"OPV2V scenario: {FRAMES} frames x {CAVS} CAVs, {size_mb:.0f} MB; medians of {args.repeat}", flush=True)
    rates = pcd_rates(root, args.repeat)
    ratio = rates["read_pcd"] / rates["numpy.loadtxt"]
    print(
        f"  PCD parse ({rates['files']} files of ~{rates['points']} points): read_pcd"
        f" {rates['read_pcd'] / 1e6:.2f} M points/s, numpy.loadtxt {rates['numpy.loadtxt'] / 1e6:.2f} M points/s,"
        f" ratio {ratio:.1f}x",
        flush=True,
    )
    for workers in (1, 2):
        runs = [convert(root, work / "opencood-out", workers) for _ in range(args.repeat)]
        seconds = statistics.median(r["s"] for r in runs)
        frames, points = runs[0]["frames"], runs[0]["points"]
        print(
            f"  conversion, {workers} worker(s): {seconds:.1f} s, {frames / seconds:.1f} agent-frames/s,"
            f" {points / seconds / 1e6:.2f} M points/s ({frames} lidar frames, {points} points,"
            f" {4 * frames} images)",
            flush=True,
        )
    rates = readback_rates(root, work / "opencood-out", args.repeat)
    print(
        f"  reading back {rates['frames']} agent-frames (points, YAML, 4 PNGs each): OpenCOOD view"
        f" {rates['view']:.1f} frames/s, raw files {rates['raw']:.1f} frames/s,"
        f" ratio {rates['view'] / rates['raw']:.2f}",
        flush=True,
    )


if __name__ == "__main__":
    main()
