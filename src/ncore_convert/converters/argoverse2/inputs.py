"""Argoverse 2 Sensor and TbV, per log: the small inputs read once (poses, calibration, sweep and
image timestamps, annotations) and the ego trajectory they give the sequence (``world`` at the first
kept pose; the pose table checked for gaps and extended at constant velocity by at most
``MAX_POSE_EXTRAPOLATION_US``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import argoverse2_annotations as av2_annotations
from ncore_convert.sources.reader import Reader, ReadSettings
from ncore_convert.sources.store import ObjectInfo
from ncore_convert.transforms.geometry import Trajectory, invert_se3
from ncore_convert.transforms.lidar import timing as lidar_timing
from ncore_convert.transforms.timebase import NS_PER_US, ceil_us, floor_us

#: Sensor data may reach this far (µs) beyond the pose table, or across a gap in it; further fails.
MAX_POSE_EXTRAPOLATION_US = 200_000


@dataclass(frozen=True)
class LogInputs:
    """Everything read from a log up front (no sweep points, no image bytes)."""

    log_dir: UPath
    pose_timestamps_ns: np.ndarray
    T_ego_city: np.ndarray  #: [N,4,4], av2 egovehicle -> city
    T_sensor_ego: dict[str, np.ndarray]  #: [4,4] each, sensor -> av2 egovehicle (= NCore T_sensor_rig)
    intrinsics: dict[str, av2.CameraIntrinsics]
    sweep_timestamps_ns: np.ndarray
    image_timestamps_ns: dict[str, np.ndarray]
    annotations: av2_annotations.Annotations | None
    files: dict[str, ObjectInfo]  #: remote sweeps' and images' sizes and ETags, from their folders' listings
    reading: ReadSettings  #: for the readers of the log's jobs (``Reader.shared`` of the log's reader)


def read_log_inputs(
    log_dir: UPath, camera_ids: list[str], reader: Reader, intrinsics: dict[str, av2.CameraIntrinsics] | None = None
) -> LogInputs:
    """Read a log's small inputs through the log's ``reader``; ``intrinsics``: already read (TbV
    reads them to pick the cameras)."""
    # remote sizes and ETags, every file read checked against them: the log folder's and the
    # calibration's listings here; the sweeps' and images' folders add theirs
    files = {**reader.list_folder(log_dir), **reader.list_folder(log_dir / "calibration")}
    pose_timestamps_ns, T_ego_city = av2.read_ego_poses(log_dir, files, reader)
    return LogInputs(
        log_dir=log_dir,
        pose_timestamps_ns=pose_timestamps_ns,
        T_ego_city=T_ego_city,
        T_sensor_ego=av2.read_sensor_extrinsics(log_dir, files, reader),
        intrinsics=intrinsics if intrinsics is not None else av2.read_intrinsics(log_dir, files, reader),
        sweep_timestamps_ns=av2.list_sweep_timestamps_ns(log_dir, files, reader),
        image_timestamps_ns={cam: av2.list_image_timestamps_ns(log_dir, cam, files, reader) for cam in camera_ids},
        annotations=av2_annotations.read_annotations(log_dir, files, reader),
        files=files,
        reading=reader.shared(),
    )


def ego_trajectory(
    inputs: LogInputs, needed_us: tuple[int, int], warnings: list[str], cut: bool = False
) -> tuple[Trajectory, np.ndarray]:
    """``T_rig_world`` relative to the first pose, and ``T_world_city`` (= the first ``T_ego_city``).

    With ``cut`` (a clip window), only the poses that cover ``needed_us`` are kept (with one pose
    either side), so the first kept pose is ``world``.

    Timestamps go ns -> µs (floor) with duplicate µs dropped (first kept). Where sensor data reach
    up to ``MAX_POSE_EXTRAPOLATION_US`` outside the pose table, the trajectory is extended at
    constant velocity (reported as a warning); further, or across a gap in the poses longer than
    that, the log fails naming the pose table. The returned trajectory holds the float32-rounded
    poses that are stored, so every transform computed from it matches what NCore readers reconstruct.
    """
    path = av2.poses_path(inputs.log_dir)
    pose_timestamps_us, first = np.unique(floor_us(inputs.pose_timestamps_ns), return_index=True)
    T_ego_city = inputs.T_ego_city[first]
    if cut:
        lo = max(0, int(np.searchsorted(pose_timestamps_us, needed_us[0], side="right")) - 1)
        hi = min(len(pose_timestamps_us), int(np.searchsorted(pose_timestamps_us, needed_us[1], side="left")) + 1)
        lo = min(lo, max(0, hi - 2))  # at least two poses
        pose_timestamps_us, T_ego_city = pose_timestamps_us[lo:hi], T_ego_city[lo:hi]
    T_world_city = T_ego_city[0]
    T_rig_world = invert_se3(T_world_city) @ T_ego_city
    traj = Trajectory(pose_timestamps_us.astype(np.int64), T_rig_world)
    start_us, end_us = needed_us
    _check_pose_gaps(path, pose_timestamps_us, needed_us)
    if start_us < traj.start_us or end_us > traj.end_us:
        before = max(0, traj.start_us - start_us) / 1e3
        after = max(0, end_us - traj.end_us) / 1e3
        if max(before, after) > MAX_POSE_EXTRAPOLATION_US / 1e3:
            raise SourceError(
                path,
                f"poses do not cover the sensor data: {before:.1f} ms missing before and {after:.1f} ms after"
                f" (at most {MAX_POSE_EXTRAPOLATION_US / 1e3:g} ms is extrapolated)",
            )
        warnings.append(
            f"{path}: poses do not cover the sensor data;"
            f" extended at constant velocity by {before:.3f} ms before and {after:.3f} ms after"
        )
        traj = traj.extended(min(start_us, traj.start_us), max(end_us, traj.end_us))
    stored = traj.poses.astype(np.float32).astype(np.float64)
    return Trajectory(traj.timestamps_us, stored), T_world_city


def _check_pose_gaps(path: UPath, pose_timestamps_us: np.ndarray, needed_us: tuple[int, int]) -> None:
    """SourceError if consecutive poses inside the sensor time range are further apart than
    ``MAX_POSE_EXTRAPOLATION_US`` (interpolating across the gap would invent the motion)."""
    gaps_us = np.diff(pose_timestamps_us)
    inside = (pose_timestamps_us[1:] > needed_us[0]) & (pose_timestamps_us[:-1] < needed_us[1])
    bad = np.flatnonzero(inside & (gaps_us > MAX_POSE_EXTRAPOLATION_US))
    if bad.size:
        i = int(bad[0])
        raise SourceError(
            path,
            f"no pose for {gaps_us[i] / 1e3:.1f} ms between timestamp_ns {pose_timestamps_us[i] * NS_PER_US} and"
            f" {pose_timestamps_us[i + 1] * NS_PER_US}, where sensor data exist"
            f" (at most {MAX_POSE_EXTRAPOLATION_US / 1e3:g} ms)",
        )


def sensor_time_range_us(
    inputs: LogInputs, camera_ids: list[str], with_lidar: bool, with_offsets: bool, reader: Reader
) -> tuple[int, int]:
    """Inclusive µs range the trajectory must cover: lidar points at their exact ns times (so the
    end rounds up), camera frames and cuboids at their stored (floored) µs times.

    The lidar range comes from the first and the last sweep (each sweep's points span ~106 ms from
    its timestamp, so they bound all others); every other sweep is checked when it is converted.
    Without offset_ns, the range is the widest that reconstructed times can take (SWEEP_SPAN_MS).
    """
    lo, hi = [], []
    if with_lidar and not with_offsets:
        lo.append(floor_us(int(inputs.sweep_timestamps_ns[0]) + int(lidar_timing.SWEEP_SPAN_MS[0] * 1e6)))
        hi.append(ceil_us(int(inputs.sweep_timestamps_ns[-1]) + int(lidar_timing.SWEEP_SPAN_MS[1] * 1e6)))
    elif with_lidar:
        for sweep_ns in {int(inputs.sweep_timestamps_ns[0]), int(inputs.sweep_timestamps_ns[-1])}:
            first_ns, last_ns = av2.read_sweep_offset_range_ns(inputs.log_dir, sweep_ns, inputs.files, reader)
            lo.append(floor_us(sweep_ns + min(first_ns, 0)))
            hi.append(ceil_us(sweep_ns + last_ns))
    for cam in camera_ids:
        if len(stamps_ns := inputs.image_timestamps_ns[cam]):
            lo.append(floor_us(int(stamps_ns[0])))
            hi.append(floor_us(int(stamps_ns[-1])))
    if inputs.annotations is not None and len(inputs.annotations):
        lo.append(floor_us(int(inputs.annotations.timestamps_ns.min())))
        hi.append(floor_us(int(inputs.annotations.timestamps_ns.max())))
    pose_timestamps_us = floor_us(inputs.pose_timestamps_ns)
    return min(lo, default=int(pose_timestamps_us[0])), max(hi, default=int(pose_timestamps_us[-1]))
