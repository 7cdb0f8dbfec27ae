"""The occupancy check (``validate/occupancy.py``) before and after issue 74, on the same counts:
before, every near box of every sampled frame was an independent draw (allowance 3 sqrt(n p (1-p)),
decisive at 5 box-frames); after, the objects are (3 sqrt(p (1-p) sum m²), decisive at 5 effective
objects). One run reads each sequence's counts once and prints both verdicts.

1. Correct conversions: generated OPV2V (shapes, close range: a car just ahead and one alongside the
   first agent), V2XSet, one-tick scenarios and AV2 logs on seeds no test uses.
2. Planted faults on some of them, in a copy of the store: the lidar turned (yaw 90 / 180 degrees,
   upside down) or shifted (2 m forward) in its stored extrinsic, every box moved 3 m sideways.

    python bench/bench_occupancy.py [--seeds 7101,7102,7103] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from functools import partial
from pathlib import Path

import numpy as np
import zarr
from ncore.impl.data.stores import consolidate_compressed_metadata
from scipy.spatial.transform import Rotation
from upath import UPath

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from planted_faults import edit_cuboids  # noqa: E402

from ncore_convert.cli import cli  # noqa: E402
from ncore_convert.validate.cuboids import read_cuboids  # noqa: E402
from ncore_convert.validate.occupancy import OCCUPANCY_SIGMAS, _occupancy, occupancy_verdict  # noqa: E402
from ncore_convert.validate.readback import open_sequence  # noqa: E402


def _run(args: list[str]) -> None:
    try:
        cli.main(args, standalone_mode=False)
    except SystemExit as stop:
        if stop.code:
            raise


def convert(work: Path, name: str, synth: list[str], command: list[str]) -> list[Path]:
    """Generate and convert (``--no-validate``) one dataset; its sequences' JSON files."""
    src, out = work / name / "src", work / name / "out"
    if not out.exists():
        _run(["synth", *synth, "--out", str(src)])
        layout = ["--store-type", "directory", "--profile", "default"]  # the stores edited in place
        _run(["--root-dir", str(src), "--output-dir", str(out), "--no-validate", *command, *layout])
    return sorted(p for p in out.rglob("*.json") if "sequence_id" in json.loads(p.read_text()))


def before(counted) -> tuple[bool, bool]:
    """The box-frame verdict the check gave before issue 74, from the same counts."""
    near = int(counted.frames.sum())
    held, turned = int(counted.held.sum()), int(counted.turned.sum())
    if near < 5:
        return True, False
    share = (held + turned) / (2 * near)
    return turned - held <= OCCUPANCY_SIGMAS * np.sqrt(near * share * (1 - share)), True


def verdicts(sequence_json: Path) -> list[str]:
    """Per lidar: the counts and both verdicts."""
    sequence = open_sequence(UPath(sequence_json))
    cuboids = read_cuboids(sequence.reader)
    if cuboids is None:
        return []
    lines = []
    for lidar_id in sequence.loader.lidar_ids:
        counted = _occupancy(sequence, lidar_id, cuboids)
        (old, old_decisive), (new, new_decisive, slack) = before(counted), occupancy_verdict(counted)
        squares = float(np.sum(counted.frames.astype(float) ** 2))
        objects = int(counted.frames.sum()) ** 2 / squares if squares else 0.0
        lines.append(
            f"{lidar_id}: {int(counted.held.sum())}/{int(counted.frames.sum())} held,"
            f" turned {int(counted.turned.sum())},"
            f" {len(counted.frames)} tracks ({objects:.1f} effective); before {_word(old, old_decisive)},"
            f" after {_word(new, new_decisive)} (slack {slack:.1f})"
        )
    return lines


def _word(ok: bool, decisive: bool) -> str:
    return ("passes" if ok else "REFUSES") + ("" if decisive else " (not decisive)")


def _turn_lidar(group, lidar: str, euler_deg=None, shift_m=None) -> None:
    key = next(k for k in group["poses/default/static_poses"].attrs if k.startswith(f"('{lidar}'"))
    attrs = dict(group["poses/default/static_poses"].attrs)
    pose = np.array(attrs[key]["pose"])
    if euler_deg is not None:
        pose[:3, :3] = pose[:3, :3] @ Rotation.from_euler("xyz", euler_deg, degrees=True).as_matrix()
    if shift_m is not None:
        pose[:3, 3] += shift_m
    attrs[key]["pose"] = pose.tolist()
    group["poses/default/static_poses"].attrs.put(attrs)


def _move_boxes(observations: list, by_m: float) -> None:
    for o in observations:
        o["bbox3"]["centroid"][1] += by_m


def planted(sequence_json: Path, work: Path, label: str, edit) -> list[str]:
    copy = work / "planted" / label
    shutil.rmtree(copy, ignore_errors=True)
    shutil.copytree(sequence_json.parent, copy)
    (store_path,) = copy.glob("*.zarr")
    store = zarr.DirectoryStore(str(store_path))
    edit(zarr.open_group(store, mode="r+"))
    consolidate_compressed_metadata(store)
    return verdicts(copy / sequence_json.name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="7101,7102,7103")
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-occupancy-"))
    seeds = [int(s) for s in args.seeds.split(",")]
    print("1. correct conversions")
    faulted = []
    for seed in seeds:
        common = ["--seed", str(seed), "--render-step", "8"]
        groups = {
            f"opv2v-close-{seed}": (
                ["opv2v", *common, "--shapes", "--close-range", "--cavs", "3"],
                ["opv2v-v4", "--split", "test"],
            ),
            f"v2xset-{seed}": (["v2xset", *common, "--infrastructure", "1"], ["v2xset-v4", "--split", "test"]),
            f"opv2v-one-tick-{seed}": (["opv2v", *common, "--frames", "1"], ["opv2v-v4", "--split", "test"]),
            f"av2-{seed}": (
                ["argoverse2", "--seed", str(seed), "--seconds", "2"],
                ["argoverse2-v4", "--split", "val"],
            ),
        }
        for name, (synth, command) in groups.items():
            for sequence_json in convert(work, name, synth, command):
                for line in verdicts(sequence_json):
                    print(f"  {name} {sequence_json.stem}: {line}", flush=True)
                if name.startswith(("av2", "opv2v-close")) and len(faulted) < 4:
                    faulted.append(sequence_json)
    print("\n2. planted faults (each in a copy of the store)")
    for sequence_json in faulted:
        lidar = open_sequence(UPath(sequence_json)).loader.lidar_ids[0]
        faults = {
            "yaw-90": partial(_turn_lidar, lidar=lidar, euler_deg=(0, 0, 90)),
            "yaw-180": partial(_turn_lidar, lidar=lidar, euler_deg=(0, 0, 180)),
            "upside-down": partial(_turn_lidar, lidar=lidar, euler_deg=(180, 0, 0)),
            "shifted-2m": partial(_turn_lidar, lidar=lidar, shift_m=np.array([2.0, 0.0, 0.0])),
            "boxes-3m": edit_cuboids(partial(_move_boxes, by_m=3.0)),
        }
        for label, edit in faults.items():
            for line in planted(sequence_json, work, f"{sequence_json.stem}-{label}", edit):
                if line.startswith(lidar):
                    print(f"  {sequence_json.stem} {label}: {line}", flush=True)


if __name__ == "__main__":
    main()
