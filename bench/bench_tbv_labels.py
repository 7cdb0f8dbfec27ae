"""TbV camera labels from the lidar's own movers (issue 53), against the generator's truth.

A synthetic TbV log (shaped objects, nothing drives through a standing object) is converted twice
with ``--camera-labels``:

- ``--dynamic-source annotations``: no flags on TbV, so every point may be on a mover and labels depth
  only within 5 ms of its frame (how TbV was converted before issue 53);
- the default (``lidar``): the points the lidar saw move, and those it could not judge, label depth only
  within 5 ms; every other point from any time; ``mask.dynamic`` from the movers the lidar found.

Every third frame of two cameras is scored against the scene ray-cast from the camera at the frame's
time (``synth.raycast.seen_through``), each labelled pixel sampled on a 3 x 3 grid over it:

- depth: labelled pixels per frame; the median |error| (the smallest over the samples); occlusion
  errors (more than 0.5 m behind everything the pixel shows) and stale surfaces (more than 0.5 m in
  front of it);
- the conversion's wall time (one process) and its label jobs' seconds (``label_seconds``);
- ``mask.dynamic`` (default run): recall (the moving objects' true pixels the mask holds: objects
  faster than 0.2 m/s at the frame's time, every fourth pixel), the mask's area over the truth's,
  and its IoU.

    python bench/bench_tbv_labels.py [--seeds 211,212] [--seconds 2]
"""

from __future__ import annotations

import statistics
import time

import numpy as np
from bench_argoverse2 import bench_parser, work_dir
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from ncore.impl.data.types import LabelType
from upath import UPath

from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
from ncore_convert.synth.argoverse2 import SynthConfig, write_log
from ncore_convert.synth.raycast import seen_through
from ncore_convert.transforms.camera.models import Pinhole

CAMERAS = ("ring_front_center", "ring_side_left")
MOVING_MPS = 0.2
SUBPIXEL = np.linspace(0.1, 0.9, 3)


def _loader(folder, log_id: str) -> SequenceLoaderV4:
    return SequenceLoaderV4(SequenceComponentGroupsReader([UPath(folder / f"{log_id}.json")]))


def _frames(truth, loader, cam: str):
    """Every third label time of ``cam``: (µs, seconds into the log, camera -> city pose, pinhole)."""
    (labels,) = loader.query_camera_labels(cam, label_type=LabelType.DEPTH_Z_M)
    f, cx, cy = truth.intrinsics[cam]
    pinhole = Pinhole((f, f), (cx + 0.5, cy + 0.5), loader.get_camera_sensor(cam).model_parameters.resolution)
    for ts in labels.label_timestamps_us[1::3]:
        t_s = (int(ts) * 1000 - truth.t0_ns) * 1e-9
        yield int(ts), t_s, truth.scene.ego.T_ego_city(np.array([t_s]))[0] @ truth.T_sensor_ego[cam], pinhole, labels


def depth_figures(truth, loader) -> dict:
    """Labelled pixels per frame, median |error|, occlusion errors and stale surfaces."""
    du, dv = (a.reshape(-1) for a in np.meshgrid(SUBPIXEL, SUBPIXEL))
    counts, smallest, behind, ahead = [], [], [], []
    for cam in CAMERAS:
        for ts, t_s, T_camera_city, pinhole, labels in _frames(truth, loader, cam):
            depth = labels.get_label(ts).get_data()
            lines, cols = np.nonzero(depth)
            counts.append(len(lines))
            if not len(lines):
                continue
            u, v = (cols[:, None] + du).reshape(-1), (lines[:, None] + dv).reshape(-1)
            z_m, _ = seen_through(truth.scene, T_camera_city, pinhole, t_s, u, v)
            error = depth[lines, cols][:, None] - z_m.reshape(len(lines), -1)
            smallest.append(np.abs(error).min(axis=1))
            behind.append(np.all(error > 0.5, axis=1))
            ahead.append(np.all(error < -0.5, axis=1))
    smallest, behind, ahead = (np.concatenate(a) for a in (smallest, behind, ahead))
    return {
        "pixels/frame": float(np.mean(counts)),
        "median err cm": 100 * float(np.median(smallest)),
        "occluded %": 100 * float(np.mean(behind)),
        "stale %": 100 * float(np.mean(ahead)),
    }


def mask_figures(truth, loader) -> dict:
    """``mask.dynamic``'s recall of the moving objects' true pixels, its area over theirs, its IoU."""
    held = true_n = ours_n = union = 0
    for cam in CAMERAS:
        (masks,) = loader.query_camera_labels(cam, label_type=LabelType.MASK_DYNAMIC)
        for ts, t_s, T_camera_city, pinhole, _ in _frames(truth, loader, cam):
            label = masks.get_label(ts)
            if "moving_objects_unknown" in label.generic_meta_data:
                continue
            ours = label.get_data()[::4, ::4] == 1
            width, height = pinhole.resolution_px
            v, u = np.mgrid[0:height:4, 0:width:4] + 0.5
            _, box = seen_through(truth.scene, T_camera_city, pinhole, t_s, u.reshape(-1), v.reshape(-1))
            speed = np.r_[[b.speed_mps(t_s) for b in truth.scene.boxes], 0.0]
            moving = (speed[box] > MOVING_MPS).reshape(u.shape)
            held, true_n = held + np.sum(ours & moving), true_n + np.sum(moving)
            ours_n, union = ours_n + np.sum(ours), union + np.sum(ours | moving)
    return {"mask recall": held / max(true_n, 1), "mask area/true": ours_n / max(true_n, 1), "mask IoU": held / union}


def main() -> None:
    parser = bench_parser(__doc__, repeat=1)
    parser.add_argument("--seeds", default="211,212")
    parser.add_argument("--seconds", type=float, default=2.0)
    args = parser.parse_args()
    work = work_dir(args) / "tbv-labels"
    rows = {}
    for seed in (int(s) for s in args.seeds.split(",")):
        config = SynthConfig(
            seconds=args.seconds,
            seed=seed,
            tbv=True,
            keep_truth=True,
            camera_fps=10,
            image_cameras=CAMERAS,
            pictures=2,
            shapes=True,
            clear_paths=True,
        )
        root = work / str(seed)
        truth = write_log(UPath(root / "src"), config)
        row = {}
        for source, kinds in (("annotations", ("depth",)), ("lidar", ("depth", "dynamic"))):
            folder = root / source / truth.log_id
            options = Argoverse2Options(
                split=None, camera_ids=CAMERAS, camera_labels=kinds, dynamic_source=source, ego_masks="none"
            )
            started = time.perf_counter()
            summary = convert_log(UPath(root / "src"), UPath(folder), truth.log_id, options)
            row[f"{source} s"], row[f"{source} label s"] = time.perf_counter() - started, summary.label_seconds
            loader = _loader(folder, truth.log_id)
            row.update({f"{source} {k}": v for k, v in depth_figures(truth, loader).items()})
            if "dynamic" in kinds:
                row.update(mask_figures(truth, loader))
        row["depth gain"] = row["lidar pixels/frame"] / row["annotations pixels/frame"]
        rows[seed] = row
        print(f"  seed {seed}: " + ", ".join(f"{k} {v:.4f}" for k, v in row.items()), flush=True)
    print(f"{args.seconds:g} s synthetic TbV logs, seeds {args.seeds}: medians")
    for key in next(iter(rows.values())):
        print(f"  {key:<30} {statistics.median(r[key] for r in rows.values()):.4f}")


if __name__ == "__main__":
    main()
