"""The smallest planted fault each validator check catches, before (the validator of ``--before``,
default bef5368) and after (this tree), and the round trip's point displacement the interior band is
derived from (issue 65; docs/validation.md, "Bands").

1. Displacement: every returned point of seed 31 (1 s) and seed 5 (4 s), read back as the validator
   reads it (motion-compensated with the per-point times, in the rig at the sweep time), against its
   source point: the largest by range, the largest share of the band ε at its range, and the µs-floor
   term's share (the rest is float32 rounding).
2. Planted faults on seed 31 (1 s, one directory store): one interior point removed; every return of a
   sampled frame shortened by k x ε; one box shifted by d; a frame's point times shifted by n µs. Each
   corrupted copy is validated by both validators (``ncore-convert validate --source``, as a conversion
   does before it publishes); the smallest fault each check refuses is printed.

    python bench/bench_planted_faults.py [--before REV] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from functools import partial
from pathlib import Path

import numpy as np
import zarr
from ncore.impl.data.stores import consolidate_compressed_metadata
from scipy.spatial import cKDTree
from upath import UPath

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from planted_faults import (  # noqa: E402
    a_ray_inside_a_box,
    band_multiple,
    edit_cuboids,
    remove_ray,
    shift_box,
    shift_times,
    shorten_rays,
)

from ncore_convert import contract  # noqa: E402
from ncore_convert.sources import argoverse2 as av2  # noqa: E402
from ncore_convert.transforms.timebase import floor_us  # noqa: E402
from ncore_convert.validate.poses import lever_arm_m, sensor_poses  # noqa: E402
from ncore_convert.validate.readback import open_sequence, sample_frames, world_points  # noqa: E402
from ncore_convert.validate.source import (  # noqa: E402
    FLOAT32_ROUNDINGS,
    TIME_FLOORS,
    TIME_STEP_S,
    UNIT_ROUNDOFF_F32,
    rig_motion_bounds,
    round_trip_margin_m,
)

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "import sys; from ncore_convert.cli import main; sys.argv[0] = 'ncore-convert'; main()"]


def cli(args: list[str], env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + args, capture_output=True, text=True, env=env)


def convert(work: Path, seed: int, seconds: float, store: bool) -> tuple[Path, Path]:
    """Generate and convert (without validation) one AV2 log; (its sequence json, the source root)."""
    root, out = work / f"src-{seed}", work / f"out-{seed}{'-directory' if store else ''}"
    if not out.exists():
        cli(
            ["synth", "argoverse2", "--out", str(root), "--seconds", str(seconds), "--seed", str(seed)]
            + ["--camera-fps", "0"]
        )
        layout = ["--store-type", "directory", "--profile", "default"] if store else []
        done = cli(
            ["--no-progress", "--no-validate", "--root-dir", str(root), "--output-dir", str(out)]
            + ["argoverse2-v4", "--split", "val", *layout]
        )
        assert done.returncode == 0, done.stdout + done.stderr
    return next(out.glob("*/*.json")), root


def displacement(sequence_json: Path, root: Path) -> dict:
    """Every returned point against its source point (nearest neighbour: the displacements are µm,
    the point spacing cm); by range, the largest displacement and share of ε, and the µs term's share."""
    sequence = open_sequence(UPath(sequence_json))
    loader = sequence.loader
    meta = loader.generic_meta_data
    log_dir = av2.log_dir(UPath(root), meta.get(contract.AV2_SPLIT), meta[contract.AV2_LOG_ID])
    lever_m = lever_arm_m(loader, av2.LIDARS)
    d_all, r_all, eps_all, time_share = [], [], [], []
    for ts in av2.list_sweep_timestamps_ns(log_dir):
        source = av2.read_sweep(log_dir, int(ts)).xyz_ego_m.astype(np.float64)
        t_us = int(floor_us(np.array([ts]))[0])
        T_rig_world = sensor_poses(loader, "rig", "world", np.array([t_us], np.uint64))[0]
        xyz = []
        for unit in av2.LIDARS:
            frames = loader.get_lidar_sensor(unit).frames_timestamps_us
            frame = int(np.flatnonzero(frames[:, 0] == t_us)[0])
            xyz.append(world_points(loader, unit, frame)[0])
            speed, turn = rig_motion_bounds(loader, int(frames[frame, 0]), int(frames[frame, 1]))
        xyz_rig = (np.concatenate(xyz) - T_rig_world[:3, 3]) @ T_rig_world[:3, :3]
        d_m, k = cKDTree(source).query(xyz_rig)
        reach_m = np.linalg.norm(source[k], axis=1) + lever_m
        eps_m = round_trip_margin_m(reach_m, speed, turn)
        d_all.append(d_m), r_all.append(reach_m - lever_m), eps_all.append(eps_m)
        time_share.append(TIME_FLOORS * (speed + turn * reach_m) * TIME_STEP_S / eps_m)
    d, r, eps, share = (np.concatenate(a) for a in (d_all, r_all, eps_all, time_share))
    bins = [(0, 10), (10, 30), (30, 60), (60, 100), (100, 400)]
    by_range = {f"{lo}-{hi} m": float(d[(r >= lo) & (r < hi)].max(initial=0) * 1e6) for lo, hi in bins}
    worst = int(np.argmax(d / eps))
    return {
        "points": len(d),
        "max_um": float(d.max() * 1e6),
        "median_um": float(np.median(d) * 1e6),
        "max_um_by_range": by_range,
        "max_share_of_eps": float((d / eps).max()),
        "at_worst": {"range_m": float(r[worst]), "d_um": float(d[worst] * 1e6), "eps_um": float(eps[worst] * 1e6)},
        "max_over_range": float((d / np.maximum(r, 1.0)).max()),
        "float32_bound_over_range": FLOAT32_ROUNDINGS * UNIT_ROUNDOFF_F32,
        "time_term_share_of_eps_median": float(np.median(share)),
    }


def failed_checks(sequence_json: Path, root: Path, env: dict | None) -> set[str]:
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        done = cli(["validate", str(sequence_json), "--source", str(root), "--json", f.name], env=env)
        text = Path(f.name).read_text()
    if not text:  # the validator itself failed
        return {f"validate failed: {(done.stderr.strip().splitlines() or ['?'])[-1][:160]}"}
    reports = json.loads(text)
    return {c["name"] for r in reports for c in r["checks"] if not c["ok"]}


def planted(sequence_json: Path, root: Path, work: Path, edit, label: str, envs: dict) -> dict[str, set[str]]:
    """Copy the sequence, apply ``edit(group)``, validate with each validator."""
    copy = work / "planted" / label
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(sequence_json.parent, copy)
    (store_path,) = copy.glob("*.ncore4.zarr")
    store = zarr.DirectoryStore(str(store_path))
    edit(zarr.open_group(store, mode="r+"))
    consolidate_compressed_metadata(store)
    return {name: failed_checks(copy / sequence_json.name, root, env) for name, env in envs.items()}


def _apply_all(edits, group) -> None:
    for edit in edits:
        edit(group)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", default="bef5368")
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-planted-"))
    tree = work / f"before-{args.before}"
    if not tree.exists():
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "-f", str(tree), args.before], check=True)
    envs = {"before": {**os.environ, "PYTHONPATH": str(tree / "src")}, "after": None}

    print("1. displacement across the round trip (returned points against their source points)")
    for seed, seconds in ((31, 1.0), (5, 4.0)):
        print(f"seed {seed} ({seconds:g} s):", json.dumps(displacement(*convert(work, seed, seconds, False)), indent=1))

    print("\n2. planted faults on seed 31 (1 s): the checks each one fails, before and after")
    sequence_json, root = convert(work, 31, 1.0, True)
    for name, env in envs.items():
        print(f"  unplanted, {name}: {sorted(failed_checks(sequence_json, root, env)) or 'passes'}")
    frame, ray, row = a_ray_inside_a_box(sequence_json)
    faults = [("one interior point removed", partial(remove_ray, lidar="up_lidar", index=frame, ray=ray))]
    n_frames = len(open_sequence(UPath(sequence_json)).loader.get_lidar_sensor("up_lidar").frames_timestamps_us)
    for k in (0.25, 0.5, 1.0, 1.5, 2.0, 4.0, 16.0, 64.0):  # every frame the check samples, both lidars
        edits = [
            partial(shorten_rays, lidar=unit, index=int(i), by_m=band_multiple(sequence_json, unit, int(i), k))
            for unit in av2.LIDARS
            for i in sample_frames(n_frames)
        ]
        faults.append((f"returns shortened by {k:g} eps", partial(_apply_all, edits)))
    for d_m in (1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 5e-3, 2e-2):
        faults.append((f"box shifted {d_m * 1e3:g} mm", edit_cuboids(partial(shift_box, row=row, by_m=d_m))))
    for n in (1, -1, 10, 1000):
        faults.append(
            (f"point times shifted {n:+d} us", partial(shift_times, lidar="down_lidar", index=frame, steps_us=n))
        )
    for label, edit in faults:
        found = planted(sequence_json, root, work, edit, label.replace(" ", "-"), envs)
        before, after = (sorted(found[name]) or "-" for name in ("before", "after"))
        print(f"  {label:34s} before: {before}\n  {'':34s} after:  {after}")


if __name__ == "__main__":
    main()
