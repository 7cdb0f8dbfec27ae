"""How much a vehicle's mask (``mask.dynamic`` / ``segmentation.instance``) covers beyond the
vehicle, on the real AV2 sample: the area of each vehicle's ``box_index`` picture, as a box and as
the mask cut to where the sweep's points show it (issue 52), against the convex hull of its own
lidar points' projections, per ring camera of the real calibration (each camera looks at a sweep
from the ego pose of the sweep's time; the sample has no pictures); and the share of the own
points' pixels the mask holds.

The hull is a lower bound of the vehicle's picture (the lidar sees one side of it, sparsely), so
the ratio is an upper bound of the over-cover; the pixel of an own point of the body (``BODY_ABOVE_M``
over the box's floor: lower ones may be the street under it) outside the mask is an under-cover the
real data proves.

    python bench/bench_box_masks.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull
from upath import UPath

from ncore_convert.converters.argoverse2.plan import camera_pinhole
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import argoverse2_annotations as av2_annotations
from ncore_convert.transforms.camera.labels import box_index
from ncore_convert.transforms.camera.visibility import CameraView
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.lidar.range_image import RangeImage
from ncore_convert.transforms.objects.boxes import in_box

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from samples import ensure as real_samples  # noqa: E402  (the manifest's samples, as the tests get them)

LOG_ID = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
BODY_ABOVE_M = 0.3  #: an own point this far over its box's floor is the vehicle's body, not the street under it
VEHICLE_CLASSES = ("REGULAR_VEHICLE", "LARGE_VEHICLE", "BUS", "BOX_TRUCK", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER")


def ratios(log: UPath) -> list[tuple[str, float, float, float, float]]:
    """(class, distance m, box picture area / own-point hull area, mask area / hull area, share of
    the own points' pixels in the mask) per vehicle and camera that sees it whole with at least 50
    of its points."""
    intrinsics, T_sensor_ego = av2.read_intrinsics(log), av2.read_sensor_extrinsics(log)
    lidar_m = np.mean([T_sensor_ego[unit][:3, 3] for unit in ("up_lidar", "down_lidar")], axis=0)  # ego frame
    cams = [CameraView(c, 0, invert_se3(T_sensor_ego[c]), camera_pinhole(intrinsics[c])) for c in av2.RING_CAMERAS]
    boxes = av2_annotations.read_annotations(log)
    out = []
    for ts in av2.list_sweep_timestamps_ns(log):
        points = av2.read_sweep(log, int(ts)).xyz_ego_m.astype(np.float64)
        sight = RangeImage(points, lidar_m)  # the sweep's lines of sight (its points are motion-compensated)
        for row in np.flatnonzero((boxes.timestamps_ns == ts) & np.isin(boxes.categories, VEHICLE_CLASSES)):
            T, half = boxes.T_object_ego[row], boxes.dims_m[row] / 2
            members = points[in_box(points, T[:3, 3], T[:3, :3], half)]
            for view in cams:
                camera_xyz = members @ view.T_world_camera[:3, :3].T + view.T_world_camera[:3, 3]
                u, v = view.pinhole.project(camera_xyz) if len(members) >= 50 else (np.zeros(0), np.zeros(0))
                width, height = view.pinhole.resolution_px
                whole = len(u) and camera_xyz[:, 2].min() > 0.3 and u.min() >= 0 and u.max() < width
                if not whole or v.min() < 0 or v.max() >= height:
                    continue
                area = np.count_nonzero(box_index(view, T[None], half[None]).index == 0)
                mask = box_index(view, T[None], half[None], None, points, None, lidar_m, sight=sight).index == 0
                hull = ConvexHull(np.c_[u, v]).volume
                body = (members - T[:3, 3]) @ T[:3, 2] > BODY_ABOVE_M - half[2]  # not the street under it
                held = np.mean(mask[v[body].astype(np.int64), u[body].astype(np.int64)])
                out.append((boxes.categories[row], float(np.hypot(*T[:2, 3])), area / hull, mask.sum() / hull, held))
    return out


def main() -> None:
    found = ratios(UPath(real_samples()["av2-sample"]) / "val" / LOG_ID)
    r = np.array([x[2] for x in found])
    near = np.array([x[1] < 15.0 for x in found])
    print(f"real AV2 sample, {len(found)} vehicle views: box picture / own-point hull area")
    print(f"  median {np.median(r):.2f}, 10th-90th percentile {np.percentile(r, 10):.2f}-{np.percentile(r, 90):.2f}")
    print(f"  within 15 m: median {np.median(r[near]):.2f} ({near.sum()} views); beyond: {np.median(r[~near]):.2f}")
    m, held = np.array([x[3] for x in found]), np.array([x[4] for x in found])
    print("masks cut to where the points show the vehicle / own-point hull area")
    print(f"  median {np.median(m):.2f}, 10th-90th percentile {np.percentile(m, 10):.2f}-{np.percentile(m, 90):.2f}")
    print(f"  within 15 m: median {np.median(m[near]):.2f}; beyond: {np.median(m[~near]):.2f}")
    print(f"  the body's own points' pixels in the mask: median {np.median(held):.4f}, lowest {held.min():.4f}")


if __name__ == "__main__":
    sys.exit(main())
