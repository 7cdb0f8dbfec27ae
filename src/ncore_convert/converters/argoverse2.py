"""Argoverse 2 Sensor -> NCore V4 for one log: source readers -> transforms -> writer.

Frame mapping: AV2 ``egovehicle`` is NCore ``rig``; ``world`` is the city frame re-referenced to the
first ego pose; ``world_global`` is the AV2 city frame (static float64 edge = first city_SE3_ego).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
from upath import UPath

from ncore_convert import __version__
from ncore_convert.geometry import Trajectory, euler_xyz_from_rotation, invert_se3
from ncore_convert.lidar import (
    RayBundle,
    UnitSplit,
    beam_elevation_spread_rad,
    decide_unit_split,
    decompensate,
    ray_bundle,
)
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.argoverse2 import SourceError
from ncore_convert.writer import CameraStream, Cuboids, LidarStream, Profile, SequenceWriter, StoreType

SOURCE_DATASET = "argoverse2-sensor"
#: Sweeps sampled across the log for the up/down unit decision.
UNIT_DECISION_SWEEPS = 3
#: Below this margin the unit decision is reported as a warning.
UNIT_DECISION_MIN_MARGIN = 2.0


@dataclass(frozen=True)
class Argoverse2Options:
    """Options of the ``argoverse2-v4`` command (sensor selection: None = all available)."""

    split: str
    store_type: StoreType = "itar"
    profile: Profile = "separate-sensors"
    sequence_meta: bool = True
    lidar_model_source: str = "none"
    camera_ids: tuple[str, ...] | None = None
    lidar_ids: tuple[str, ...] | None = None


@dataclass
class LogSummary:
    """What one log conversion produced."""

    log_id: str
    sweeps: int = 0
    points: int = 0
    points_not_stored: int = 0
    images: int = 0
    cuboids: int = 0
    seconds: float = 0.0
    lidar_seconds: float = 0.0  #: read + decompensate + write of all sweeps
    camera_seconds: float = 0.0  #: read + write of all images
    warnings: list[str] = field(default_factory=list)

    def line(self) -> str:
        return (
            f"{self.log_id}: {self.sweeps} sweeps, {self.points} points"
            f" ({self.points_not_stored} not representable), {self.images} images,"
            f" {self.cuboids} cuboids, {self.seconds:.1f} s"
            + (f", {len(self.warnings)} warning(s)" if self.warnings else "")
        )


@dataclass(frozen=True)
class LogInputs:
    """Everything read from a log up front (no sweep points, no image bytes)."""

    log_dir: UPath
    pose_timestamps_ns: np.ndarray
    city_SE3_ego: np.ndarray
    ego_SE3_sensor: dict[str, np.ndarray]
    intrinsics: dict[str, av2.CameraIntrinsics]
    sweep_timestamps_ns: np.ndarray
    image_timestamps_ns: dict[str, np.ndarray]
    annotations: av2.Annotations | None


def read_log_inputs(log_dir: UPath, camera_ids: list[str]) -> LogInputs:
    if not log_dir.is_dir():
        raise SourceError(log_dir, "log directory not found")
    pose_ts, city_SE3_ego = av2.read_city_SE3_ego(log_dir)
    return LogInputs(
        log_dir=log_dir,
        pose_timestamps_ns=pose_ts,
        city_SE3_ego=city_SE3_ego,
        ego_SE3_sensor=av2.read_ego_SE3_sensors(log_dir),
        intrinsics=av2.read_intrinsics(log_dir),
        sweep_timestamps_ns=av2.list_sweep_timestamps_ns(log_dir),
        image_timestamps_ns={cam: av2.list_image_timestamps_ns(log_dir, cam) for cam in camera_ids},
        annotations=av2.read_annotations(log_dir),
    )


def select_sensors(requested: tuple[str, ...] | None, known: tuple[str, ...], kind: str) -> list[str]:
    """Resolve a sensor selection (None = all) against the dataset's sensor names."""
    if requested is None:
        return list(known)
    unknown = sorted(set(requested) - set(known))
    if unknown:
        raise ValueError(f"unknown {kind} id(s) {unknown}; known: {list(known)}")
    return [s for s in known if s in requested]


def ego_trajectory(inputs: LogInputs, needed_us: tuple[int, int], warnings: list[str]) -> tuple[Trajectory, np.ndarray]:
    """``T_rig_world`` relative to the first pose, and ``T_world_world_global`` (= first city_SE3_ego).

    Timestamps go ns -> µs (floor) with duplicate µs dropped (first kept). The trajectory is extended
    at constant velocity when sensor data reach outside the pose table (reported as a warning).
    The returned trajectory holds the float32-rounded poses that are stored, so every transform
    computed from it matches what NCore readers reconstruct.
    """
    ts_us, first = np.unique(inputs.pose_timestamps_ns // 1000, return_index=True)
    city_SE3_ego = inputs.city_SE3_ego[first]
    T_world_world_global = city_SE3_ego[0]
    T_rig_world = invert_se3(T_world_world_global) @ city_SE3_ego
    traj = Trajectory(ts_us.astype(np.int64), T_rig_world)
    start_us, end_us = needed_us
    if start_us < traj.start_us or end_us > traj.end_us:
        before = max(0, traj.start_us - start_us) / 1e3
        after = max(0, end_us - traj.end_us) / 1e3
        warnings.append(
            f"{inputs.log_dir / 'city_SE3_egovehicle.feather'}: poses do not cover the sensor data;"
            f" extended at constant velocity by {before:.3f} ms before and {after:.3f} ms after"
        )
        traj = traj.extended(min(start_us, traj.start_us), max(end_us, traj.end_us))
    stored = traj.poses.astype(np.float32).astype(np.float64)
    return Trajectory(traj.timestamps_us, stored), T_world_world_global


def _half(sweep: av2.Sweep, low_half: bool) -> tuple[np.ndarray, np.ndarray]:
    """Indices of one laser_number half (< 32 or >= 32) and their absolute point times (ns, int64)."""
    idx = np.flatnonzero((sweep.laser_number < 32) == low_half)
    return idx, sweep.timestamp_ns + sweep.offset_ns[idx].astype(np.int64)


def decide_units(
    log_dir: UPath, sweep_timestamps_ns: np.ndarray, T_rig_world: Trajectory, T_sensor_rig: dict[str, np.ndarray]
) -> UnitSplit:
    """Decide which laser_number half is which unit from per-beam elevation flatness.

    Each half is decompensated into each candidate unit's frame on a few sweeps spread over the
    log; the assignment with the flatter beams wins.
    """
    picks = np.unique(np.linspace(0, len(sweep_timestamps_ns) - 1, UNIT_DECISION_SWEEPS).round().astype(int))
    spread: dict[tuple[str, str], float] = {}
    for i in picks:
        sweep = av2.read_sweep(log_dir, int(sweep_timestamps_ns[i]))
        for half, low in (("low", True), ("high", False)):
            idx, times_ns = _half(sweep, low)
            for unit, T in T_sensor_rig.items():
                xyz = decompensate(sweep.xyz_ego_m[idx], times_ns, sweep.timestamp_ns, T_rig_world, T)
                score = beam_elevation_spread_rad(xyz, sweep.laser_number[idx].astype(np.int64) % 32)
                spread[(half, unit)] = spread.get((half, unit), 0.0) + score
    return decide_unit_split(spread)


def sweep_ray_bundles(
    sweep: av2.Sweep, split: UnitSplit, T_rig_world: Trajectory, T_sensor_rig: dict[str, np.ndarray]
) -> dict[str, RayBundle]:
    """Split one sweep by unit and decompensate each half into its unit's frame at per-point time."""
    out = {}
    for unit, low in ((split.low_half_unit, True), (split.high_half_unit, False)):
        if unit not in T_sensor_rig:
            continue
        idx, times_ns = _half(sweep, low)
        xyz = decompensate(sweep.xyz_ego_m[idx], times_ns, sweep.timestamp_ns, T_rig_world, T_sensor_rig[unit])
        out[unit] = ray_bundle(xyz, times_ns, sweep.intensity[idx], sweep.timestamp_ns // 1000)
    return out


def annotation_cuboids(annotations: av2.Annotations) -> Cuboids:
    """AV2 cuboids (ego frame at the sweep time) as rig-frame observations with full xyz-Euler rotation."""
    return Cuboids(
        track_ids=annotations.track_uuids,
        class_ids=annotations.categories,
        timestamps_us=annotations.timestamps_ns // 1000,
        centroids_m=annotations.ego_SE3_object[:, :3, 3],
        dims_m=annotations.dims_m,
        euler_xyz_rad=euler_xyz_from_rotation(annotations.ego_SE3_object[:, :3, :3]),
    )


def _sensor_time_range_us(inputs: LogInputs, camera_ids: list[str], with_lidar: bool) -> tuple[int, int]:
    """Inclusive µs range the trajectory must cover: lidar points at their exact ns times (so the
    end rounds up), camera frames and cuboids at their stored (floored) µs times."""
    lo, hi = [], []
    if with_lidar:
        for ts in inputs.sweep_timestamps_ns:
            first, last = av2.read_sweep_offset_range_ns(inputs.log_dir, int(ts))
            lo.append((int(ts) + min(first, 0)) // 1000)
            hi.append(-(-(int(ts) + last) // 1000))
    for cam in camera_ids:
        if len(stamps := inputs.image_timestamps_ns[cam]):
            lo.append(int(stamps[0]) // 1000)
            hi.append(int(stamps[-1]) // 1000)
    if inputs.annotations is not None and len(inputs.annotations):
        lo.append(int(inputs.annotations.timestamps_ns.min()) // 1000)
        hi.append(int(inputs.annotations.timestamps_ns.max()) // 1000)
    pose_ts_us = inputs.pose_timestamps_ns // 1000
    return min(lo, default=int(pose_ts_us[0])), max(hi, default=int(pose_ts_us[-1]))


def _camera_meta(intr: av2.CameraIntrinsics) -> dict:
    return {
        "av2_original_distortion": {"k1": intr.k1, "k2": intr.k2, "k3": intr.k3},
        "av2_principal_point_px": {"cx": intr.cx_px, "cy": intr.cy_px},
        "principal_point_note": "stored principal point = av2 (cx, cy) + 0.5 (NCore pixel-corner convention)",
    }


def _write_sweeps(
    log_dir: UPath,
    sweeps_ns: np.ndarray,
    unit_split: UnitSplit,
    T_rig_world: Trajectory,
    T_sensor_rig: dict[str, np.ndarray],
    lidars: dict[str, LidarStream],
    summary: LogSummary,
    on_frame: Callable[[int], None] | None,
) -> None:
    """Stream sweeps one at a time: read, split by unit, decompensate, store. Memory stays flat."""
    started = time.perf_counter()
    selected_T = {unit: T_sensor_rig[unit] for unit in lidars}
    not_stored = {unit: {"zero_range": 0, "non_finite": 0} for unit in lidars}
    source_points = {unit: 0 for unit in lidars}
    for ts in sweeps_ns:
        sweep = av2.read_sweep(log_dir, int(ts))
        for unit, rays in sweep_ray_bundles(sweep, unit_split, T_rig_world, selected_T).items():
            lidars[unit].store_frame(
                rays,
                {
                    "av2_sweep_timestamp_ns": int(ts),
                    "points_zero_range": rays.n_zero_range,
                    "points_non_finite": rays.n_non_finite,
                },
            )
            not_stored[unit]["zero_range"] += rays.n_zero_range
            not_stored[unit]["non_finite"] += rays.n_non_finite
            source_points[unit] += len(rays) + rays.n_zero_range + rays.n_non_finite
            summary.points += len(rays)
            summary.points_not_stored += rays.n_zero_range + rays.n_non_finite
        summary.sweeps += 1
        if on_frame:
            on_frame(1)
    for unit, stream in lidars.items():
        stream.set_meta({"source_points": source_points[unit], "points_not_stored": not_stored[unit]})
    summary.lidar_seconds = time.perf_counter() - started


def _write_images(
    log_dir: UPath,
    image_timestamps_ns: dict[str, np.ndarray],
    cameras: dict[str, CameraStream],
    summary: LogSummary,
    on_frame: Callable[[int], None] | None,
) -> None:
    """Copy every JPEG as-is into its camera component, with frame times [t, t] (global shutter)."""
    started = time.perf_counter()
    for cam, stream in cameras.items():
        for ts in image_timestamps_ns[cam]:
            path = av2.image_path(log_dir, cam, int(ts))
            data = path.read_bytes()
            if data[:2] != b"\xff\xd8":
                raise SourceError(path, "not a JPEG file (missing SOI marker)")
            t_us = int(ts) // 1000
            stream.store_frame(data, "jpeg", (t_us, t_us))
            summary.images += 1
            if on_frame:
                on_frame(1)
    summary.camera_seconds = time.perf_counter() - started


def convert_log(
    root_dir: UPath,
    output_dir: UPath,
    log_id: str,
    options: Argoverse2Options,
    on_frame: Callable[[int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
) -> LogSummary:
    """Convert one AV2 log into ``output_dir`` (which becomes the sequence directory).

    Args:
        on_total: called once with the number of frames (sweeps + images) to write.
        on_frame: called with 1 after each written frame (progress).
    """
    started = time.perf_counter()
    summary = LogSummary(log_id)
    warnings = summary.warnings
    log_dir = root_dir / options.split / log_id

    camera_ids = select_sensors(options.camera_ids, av2.CAMERAS, "camera")
    lidar_ids = select_sensors(options.lidar_ids, av2.LIDARS, "lidar")
    inputs = read_log_inputs(log_dir, camera_ids)

    calib_path = log_dir / "calibration"
    for sensor in av2.LIDARS + tuple(camera_ids):
        if sensor not in inputs.ego_SE3_sensor:
            raise SourceError(calib_path / "egovehicle_SE3_sensor.feather", f"no extrinsic for {sensor!r}")
    for cam in camera_ids:
        if cam not in inputs.intrinsics:
            raise SourceError(calib_path / "intrinsics.feather", f"no intrinsics for {cam!r}")
    missing = [cam for cam in camera_ids if len(inputs.image_timestamps_ns[cam]) == 0]
    if missing:
        warnings.append(f"{log_dir / 'sensors' / 'cameras'}: no images for {', '.join(missing)}; cameras not written")
        camera_ids = [cam for cam in camera_ids if cam not in missing]
    sweeps_ns = inputs.sweep_timestamps_ns if lidar_ids else np.zeros(0, dtype=np.int64)
    if lidar_ids and len(sweeps_ns) == 0:
        warnings.append(f"{log_dir / 'sensors' / 'lidar'}: no sweeps; lidars not written")
        lidar_ids = []

    needed_us = _sensor_time_range_us(inputs, camera_ids, bool(lidar_ids))
    T_rig_world, T_world_world_global = ego_trajectory(inputs, needed_us, warnings)
    T_sensor_rig = inputs.ego_SE3_sensor  # av2 ego_SE3_sensor is NCore T_sensor_rig

    unit_split = None
    if lidar_ids:
        unit_split = decide_units(log_dir, sweeps_ns, T_rig_world, {u: T_sensor_rig[u] for u in av2.LIDARS})
        if unit_split.margin < UNIT_DECISION_MIN_MARGIN:
            warnings.append(
                f"{log_dir}: up/down lidar decision has a low margin {unit_split.margin:.2f}"
                f" (laser_number < 32 -> {unit_split.low_half_unit})"
            )

    generic_meta = {
        "source_dataset": SOURCE_DATASET,
        "argoverse2_split": options.split,
        "argoverse2_log_id": log_id,
        "converter": {"name": "ncore-convert", "version": __version__, "options": asdict(options)},
    }
    writer = SequenceWriter(
        output_dir=output_dir,
        sequence_id=log_id,
        interval_us=(T_rig_world.start_us, T_rig_world.end_us),
        generic_meta_data=generic_meta,
        camera_ids=camera_ids,
        lidar_ids=lidar_ids,
        store_type=options.store_type,
        profile=options.profile,
        poses_meta={"calibration_type": "argoverse2-calibration", "egomotion_type": "argoverse2-city_SE3_egovehicle"},
    )
    writer.store_trajectory(T_rig_world.timestamps_us, T_rig_world.poses, T_world_world_global)

    if on_total:
        on_total(len(sweeps_ns) + sum(len(inputs.image_timestamps_ns[c]) for c in camera_ids))

    lidars = {
        unit: writer.add_lidar(
            unit,
            T_sensor_rig[unit],
            {"av2_unit_decision": unit_split.to_meta(), "lidar_model_source": options.lidar_model_source},
        )
        for unit in lidar_ids
    }
    cameras = {}
    for cam in camera_ids:
        intr = inputs.intrinsics[cam]
        cameras[cam] = writer.add_camera(
            cam,
            T_sensor_rig[cam],
            focal_length_px=(intr.fx_px, intr.fy_px),
            principal_point_px=(intr.cx_px + 0.5, intr.cy_px + 0.5),
            resolution_px=(intr.width_px, intr.height_px),
            generic_meta_data=_camera_meta(intr),
        )

    _write_sweeps(log_dir, sweeps_ns, unit_split, T_rig_world, T_sensor_rig, lidars, summary, on_frame)
    _write_images(log_dir, inputs.image_timestamps_ns, cameras, summary, on_frame)
    if summary.points_not_stored:
        warnings.append(
            f"{summary.points_not_stored} lidar points with zero range or non-finite coordinates not stored"
        )

    cuboids = annotation_cuboids(inputs.annotations) if inputs.annotations is not None else None
    writer.store_cuboids(cuboids)
    summary.cuboids = 0 if cuboids is None else len(cuboids)
    writer.finalize(write_sequence_meta=options.sequence_meta)
    summary.seconds = time.perf_counter() - started
    return summary
