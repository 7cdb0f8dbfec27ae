"""Depth labels on the real OPV2V agent (``opv2v-agent-sample`` of ``tests/samples.toml``: four ticks,
its YAMLs, four cameras): how many of the pixels that a real raw point facing the camera shows are
labelled.

The real scenario is converted with ``--camera-labels depth``. The figure is over every real point
(the real vehicles are not told apart from the rest), by issue 52's measure (OpenCOOD's projection,
independent of the converter):

- a pixel's nearest raw point **faces the camera**: the normal of its 8 nearest raw points (the
  smallest principal axis) points within 80 degrees of the line back to the camera;
- it is **not behind a nearer point**: no raw point within two pixels of it is nearer by more than
  5 % + 0.3 m (the kernel's own depth tolerance);
- the share of those pixels that hold a depth label, split at 2.5 m above the ground (CARLA's
  cars, people and street furniture are lower; walls, trees and poles go above).

Run it at both ends of a change to compare kernels:

    python bench/bench_real_opv2v_labels.py [--work DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from ncore.impl.data.types import LabelType
from scipy.ndimage import minimum_filter
from scipy.spatial import cKDTree
from upath import UPath

from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.sources.opencood import load_yaml
from ncore_convert.sources.pcd import read_pcd
from ncore_convert.synth import carla as synth_carla

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from samples import ensure as real_samples  # noqa: E402  (the manifest's samples, as the tests get them)

CAMERAS = ("camera_front", "camera_right_rear", "camera_left_rear", "camera_back")
FACING_DEG = 80.0
NEIGHBOURS = 8
WINDOW_PX = 2


def camera_facing_pixels(points_m: np.ndarray, frame: dict, index: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixels (flat index, [K]) whose nearest raw point faces camera ``index`` and is not behind
    a nearer point, and that point's height above the lidar (m, [K]). ``points_m``: the raw points,
    lidar frame [N,3]; ``frame``: the tick's YAML."""
    E, K = np.array(frame[f"camera{index}"]["extrinsic"]), np.array(frame[f"camera{index}"]["intrinsic"])
    ue4 = points_m @ E[:3, :3].T + E[:3, 3]
    x, y, z = ue4[:, 1], -ue4[:, 2], ue4[:, 0]
    ahead = np.flatnonzero(z > 0.3)
    u = K[0, 0] * x[ahead] / z[ahead] + K[0, 2]
    v = K[1, 1] * y[ahead] / z[ahead] + K[1, 2]
    inside = (u >= 0) & (u < synth_carla.WIDTH) & (v >= 0) & (v < synth_carla.HEIGHT)
    rows, cols, lines, depth = ahead[inside], u[inside].astype(int), v[inside].astype(int), z[ahead][inside]
    pixel = lines * synth_carla.WIDTH + cols
    order = np.lexsort((depth, pixel))
    first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]]  # the nearest point per pixel
    nearest = np.full((synth_carla.HEIGHT, synth_carla.WIDTH), np.inf)
    nearest[lines[first], cols[first]] = depth[first]
    window = minimum_filter(nearest, size=2 * WINDOW_PX + 1, mode="constant", cval=np.inf)
    unhidden = depth[first] <= window[lines[first], cols[first]] * 1.05 + 0.3
    _, near = cKDTree(points_m).query(points_m[rows[first]], k=NEIGHBOURS + 1)
    local = points_m[near] - points_m[near].mean(axis=1, keepdims=True)
    normal = np.linalg.svd(local, full_matrices=False)[2][:, -1]  # the smallest principal axis
    camera_lidar = -E[:3, :3].T @ E[:3, 3]  # the camera's centre in the lidar frame
    back = camera_lidar - points_m[rows[first]]
    cosine = np.abs(np.sum(normal * back, axis=1)) / np.linalg.norm(back, axis=1)
    facing = cosine >= np.cos(np.radians(FACING_DEG))
    keep = first[unhidden & facing]
    return pixel[keep], points_m[rows[keep], 2]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=None, help="where to write (default: a temporary directory)")
    parser.add_argument("--sample", type=Path, default=None, help="the real agent's dataset root (default: the tests')")
    args = parser.parse_args()
    root = args.sample or real_samples()["opv2v-agent-sample"]
    scenario, agent = "2021_08_18_19_48_05", "1045"
    agent_dir = root / "validate" / scenario / agent
    if not (agent_dir / "000070.pcd").is_file():
        sys.exit(f"{agent_dir}: the real OPV2V sample is not there")
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-real-opv2v-"))
    out = work / "out" / scenario
    options = OpenCoodOptions("opv2v", "validate", camera_labels=("depth",))
    convert_scenario(UPath(root), UPath(out), scenario, options)
    keys = sorted(p.stem for p in agent_dir.glob("*.pcd"))
    sequence = UPath(out / agent / f"{scenario}_agent{agent}.json")
    loader = SequenceLoaderV4(SequenceComponentGroupsReader([sequence]))
    low, high = [], []
    for position, key in enumerate(keys):
        frame = load_yaml(UPath(agent_dir) / f"{key}.yaml")
        cloud = read_pcd(UPath(agent_dir) / f"{key}.pcd")
        points_m = np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1).astype(np.float64)
        for index, cam in enumerate(CAMERAS):
            if f"camera{index}" not in frame:
                continue
            (labels,) = loader.query_camera_labels(cam, label_type=LabelType.DEPTH_Z_M)
            depth = labels.get_label(int(np.sort(labels.label_timestamps_us)[position])).get_data()
            pixel, height_m = camera_facing_pixels(points_m, frame, index)
            labelled = depth.reshape(-1)[pixel] > 0
            ground_m = np.percentile(points_m[:, 2], 5)  # the lidar's height over the road, from below
            low.append(labelled[height_m - ground_m <= 2.5])
            high.append(labelled[height_m - ground_m > 2.5])
    low, high = np.concatenate(low), np.concatenate(high)
    every = np.r_[low, high]
    print(f"the real OPV2V agent {agent} of {scenario}, ticks {keys[0]}-{keys[-1]}, 4 cameras each:")
    print(f"  camera-facing, unhidden raw-point pixels labelled: {every.mean():.3f} of {len(every)}")
    print(f"    up to 2.5 m above the road (vehicles, people, furniture): {low.mean():.3f} of {len(low)}")
    print(f"    higher (walls, trees, poles):                             {high.mean():.3f} of {len(high)}")


if __name__ == "__main__":
    main()
