"""Faults planted in a converted sequence's directory store, just beyond the validator's bands (issue
65): edits for ``zarr`` groups, applied by ``tests/test_validate.py`` and ``bench/bench_planted_faults.py``.

Each takes the sequence's zarr root group (one store: ``--store-type directory --profile default``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr
from scipy.spatial.transform import Rotation
from upath import UPath

from ncore_convert.transforms.objects.boxes import in_box
from ncore_convert.validate.cuboids import read_cuboids
from ncore_convert.validate.poses import lever_arm_m, sensor_poses
from ncore_convert.validate.readback import boxes_at, open_sequence, sample_frames
from ncore_convert.validate.source import rig_motion_bounds, round_trip_margin_m


def frame_key(group: zarr.Group, lidar: str, index: int) -> str:
    return sorted(group[f"lidars/{lidar}/frames"].group_keys(), key=int)[index]


def _frame(group: zarr.Group, lidar: str, index: int) -> zarr.Group:
    return group[f"lidars/{lidar}/frames/{frame_key(group, lidar, index)}"]


def remove_ray(group: zarr.Group, lidar: str, index: int, ray: int) -> None:
    """Delete one ray (and its return) from a lidar frame: every per-ray array loses its row."""
    frame = _frame(group, lidar, index)
    for path in ("ray_bundle/direction", "ray_bundle/model_element", "ray_bundle/timestamp_us"):
        if path in frame:
            _delete_row(frame[path], ray, axis=0)
    for name in frame["generic_data"].array_keys() if "generic_data" in frame else ():
        _delete_row(frame[f"generic_data/{name}"], ray, axis=0)
    for path in ("ray_bundle_returns/distance_m", "ray_bundle_returns/intensity"):
        _delete_row(frame[path], ray, axis=1)
    frame["ray_bundle"].attrs["n_rays"] = frame["ray_bundle/timestamp_us"].shape[0]
    packed = frame["ray_bundle_returns_valid_mask_packed"]
    n = frame["ray_bundle/timestamp_us"].shape[0] + 1
    valid = np.delete(np.unpackbits(packed[:])[:n], ray)
    repacked = np.packbits(valid)
    packed.resize(repacked.shape)
    packed[:] = repacked


def _delete_row(array: zarr.Array, row: int, axis: int) -> None:
    values = np.delete(array[:], row, axis=axis)
    array.resize(values.shape)
    array[:] = values


def shorten_rays(group: zarr.Group, lidar: str, index: int, by_m) -> None:
    """Shorten every return of a frame by ``by_m(distance_m)`` metres (float32 [N] -> [N])."""
    distance = _frame(group, lidar, index)["ray_bundle_returns/distance_m"]
    values = distance[:].astype(np.float64)
    distance[:] = (values - by_m(values)).astype(np.float32)


#: Half the diagonal of the largest box the generator annotates (a bus, 12 x 2.6 x 3.5 m), metres.
BOX_HALF_DIAGONAL_M = 6.5


def band_multiple(sequence_json: Path, lidar: str, index: int, k: float):
    """``by_m`` for :func:`shorten_rays`: ``k`` times the validator's ε of a box the return can lie on.
    The check's ε of a box is taken at its reach (its centre's distance from the rig origin, plus half
    its diagonal, plus the lidars' lever arm); for a return on the box, that reach is at most its
    distance plus two lever arms plus a whole diagonal of the largest box."""
    loader = open_sequence(UPath(sequence_json)).loader
    frames_us = loader.get_lidar_sensor(lidar).frames_timestamps_us
    speed_mps, turn_rate_radps = rig_motion_bounds(loader, int(frames_us[index, 0]), int(frames_us[index, 1]))
    lever_m = lever_arm_m(loader, loader.lidar_ids)

    def by_m(distance_m):
        reach_m = distance_m + 2 * lever_m + 2 * BOX_HALF_DIAGONAL_M
        return k * round_trip_margin_m(reach_m, speed_mps, turn_rate_radps)

    return by_m


def a_ray_inside_a_box(sequence_json: Path, lidar: str = "up_lidar") -> tuple[int, int, int]:
    """(frame index, ray index, cuboid row) of a ray inside an annotated box, on the first sweep the
    interior check samples (read back as the check reads it)."""
    sequence = open_sequence(UPath(sequence_json))
    cuboids = read_cuboids(sequence.reader)
    frames_us = sequence.loader.get_lidar_sensor(lidar).frames_timestamps_us
    frame = int(sample_frames(len(frames_us))[0])
    boxes = boxes_at(cuboids, int(frames_us[frame, 0]), int(frames_us[frame, 1]))
    xyz_world, _ = sequence.world_points(lidar, frame)
    T_rig_world = sensor_poses(sequence.loader, "rig", "world", boxes.reference_frame_timestamp_us[:1])[0]
    xyz_rig = (xyz_world - T_rig_world[:3, 3]) @ T_rig_world[:3, :3]
    R_box_rig = Rotation.from_euler("xyz", boxes.rot_rad).as_matrix()
    for k in range(len(boxes)):
        inside = np.flatnonzero(in_box(xyz_rig, boxes.centroid_m[k], R_box_rig[k], boxes.dim_m[k] / 2))
        if len(inside):
            row = next(i for i, stored in enumerate(cuboids.stored) if stored is boxes.stored[k])
            return frame, int(inside[len(inside) // 2]), row
    raise AssertionError(f"{sequence_json}: no ray inside a box on the first sampled sweep")


def a_frame_where_shortening_shows(sequence_json: Path, k: float, lidar: str = "up_lidar") -> int:
    """The sampled sweep on which shortening every return by ``k`` x ε (:func:`band_multiple`) moves
    the most returns out of their box's ε band. A return d inside its box's nearest face, met at
    incidence θ, leaves the grown box when k·ε·cos θ > d + ε: the source's float16 points scatter
    millimetres about a face, ε is tens of µm, so only the returns that happen to lie within about
    ε of a face can show the fault, and a sweep may have none."""
    sequence = open_sequence(UPath(sequence_json))
    cuboids = read_cuboids(sequence.reader)
    frames_us = sequence.loader.get_lidar_sensor(lidar).frames_timestamps_us
    shown = {}
    for frame in sample_frames(len(frames_us)).tolist():
        boxes = boxes_at(cuboids, int(frames_us[frame, 0]), int(frames_us[frame, 1]))
        xyz_world, sensor_world = sequence.world_points(lidar, frame)
        T_rig_world = sensor_poses(sequence.loader, "rig", "world", boxes.reference_frame_timestamp_us[:1])[0]
        xyz_rig = (xyz_world - T_rig_world[:3, 3]) @ T_rig_world[:3, :3]
        rays_rig = (xyz_world - sensor_world) @ T_rig_world[:3, :3]
        distance_m = np.linalg.norm(rays_rig, axis=1)
        epsilon_m = band_multiple(sequence_json, lidar, frame, 1.0)(distance_m)
        R_box_rig = Rotation.from_euler("xyz", boxes.rot_rad).as_matrix()
        shown[frame] = 0
        for c in range(len(boxes)):
            half = boxes.dim_m[c] / 2
            inside = np.flatnonzero(in_box(xyz_rig, boxes.centroid_m[c], R_box_rig[c], half))
            local = (xyz_rig[inside] - boxes.centroid_m[c]) @ R_box_rig[c]
            depth_m = half - np.abs(local)
            face = np.argmin(depth_m, axis=1)
            cos = np.abs(np.einsum("nj,jn->n", rays_rig[inside] / distance_m[inside, None], R_box_rig[c][:, face]))
            moved_m = k * epsilon_m[inside] * cos
            shown[frame] += int(np.sum(moved_m > depth_m[np.arange(len(inside)), face] + epsilon_m[inside]))
    return max(shown, key=shown.get)


def shift_times(group: zarr.Group, lidar: str, index: int, steps_us: int) -> None:
    """Shift every per-ray time of a frame by ``steps_us`` µs steps."""
    times = _frame(group, lidar, index)["ray_bundle/timestamp_us"]
    times[:] = (times[:].astype(np.int64) + steps_us).astype(np.uint64)


def edit_cuboids(edit):
    """A store edit: ``edit(observations)`` on the stored JSON objects of the default cuboids
    component (``cuboids/default/cuboids``, attribute ``cuboid_track_observations``: NCore's
    documented layout)."""

    def apply(group):
        attrs = group["cuboids/default/cuboids"].attrs
        observations = attrs["cuboid_track_observations"]
        edit(observations)
        attrs["cuboid_track_observations"] = observations

    return apply


def shift_box(observations: list, row: int, by_m: float) -> None:
    """Move one cuboid observation's centre by ``by_m`` along its reference frame's x axis."""
    observations[row]["bbox3"]["centroid"][0] += by_m
