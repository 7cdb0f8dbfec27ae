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

from ncore_convert import __version__, lidar_timing, vlp32c
from ncore_convert.converters.common import Tally, select_sensors
from ncore_convert.geometry import Trajectory, euler_xyz_from_rotation, invert_se3
from ncore_convert.lidar import (
    MIN_RANGE_M,
    RayBundle,
    UnitSplit,
    beam_elevation_spread_rad,
    decide_unit_split,
    decompensate,
    ray_bundle,
)
from ncore_convert.lidar_model import SpinningLidarModel, column_time_remap, derive_model
from ncore_convert.pool import JobPool, Progress, run_inline
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.files import SourceError, require_folder
from ncore_convert.writer import (
    BASE,
    Cuboids,
    Profile,
    SequenceWriter,
    StoreType,
    independent_parts,
    write_sequence_meta,
)

SOURCE_DATASET = "argoverse2-sensor"
#: Sweeps sampled across the log for the up/down unit decision and the lidar model.
CALIBRATION_SWEEPS = 5
#: Columns of the empirical lidar model per native VLP-32C column (firing cycle): its azimuth
#: quantisation (mean 0.003°) then stays below the float16 noise of AV2's coordinates.
MODEL_UPSAMPLE = 16
#: Sensor data may reach this far (µs) beyond the pose table, or across a gap in it; further fails.
MAX_POSE_EXTRAPOLATION_US = 200_000
#: Below this margin the unit decision is reported as a warning.
UNIT_DECISION_MIN_MARGIN = 2.0


@dataclass(frozen=True)
class Argoverse2Options:
    """Options of the ``argoverse2-v4`` and ``tbv-v4`` commands (sensor selection: None = all available).

    ``split`` is the AV2 Sensor split folder; None for TbV, whose logs sit directly under the root
    and have no per-point times (they are reconstructed, see :mod:`ncore_convert.lidar_timing`).
    """

    split: str | None
    store_type: StoreType = "itar"
    profile: Profile = "separate-sensors"
    sequence_meta: bool = True
    lidar_model_source: str = "empirical"
    maps: bool = True
    camera_ids: tuple[str, ...] | None = None
    lidar_ids: tuple[str, ...] | None = None

    @property
    def tbv(self) -> bool:
        return self.split is None

    def log_dir(self, root_dir: UPath, log_id: str) -> UPath:
        return root_dir / log_id if self.tbv else root_dir / self.split / log_id


@dataclass
class Counts(Tally):
    """What a conversion, or one writer part of it, produced. Seconds are per-process path times."""

    sweeps: int = 0
    points: int = 0
    points_not_stored: int = 0
    images: int = 0
    cuboids: int = 0
    maps: int = 0
    lidar_seconds: float = 0.0  #: read + decompensate + write of all sweeps
    camera_seconds: float = 0.0  #: read + write of all images
    warnings: list[str] = field(default_factory=list)


@dataclass
class LogSummary(Counts):
    """What one log conversion produced."""

    log_id: str = ""
    seconds: float = 0.0  #: wall time of the whole log
    validation: dict | None = None  #: set by validate.convert_and_validate (None: not validated)
    lidar_model_seconds: float = 0.0  #: slowest per-unit lidar model derivation

    def line(self) -> str:
        return (
            f"{self.log_id}: {self.sweeps} sweeps, {self.points} points"
            f" ({self.points_not_stored} not representable), {self.images} images,"
            f" {self.cuboids} cuboids, {'an HD map' if self.maps else 'no HD map'}, {self.seconds:.1f} s"
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


def read_log_inputs(
    log_dir: UPath, camera_ids: list[str], intrinsics: dict[str, av2.CameraIntrinsics] | None = None
) -> LogInputs:
    """Read a log's small inputs; ``intrinsics``: already read (TbV reads them to pick the cameras)."""
    pose_ts, city_SE3_ego = av2.read_city_SE3_ego(log_dir)
    return LogInputs(
        log_dir=log_dir,
        pose_timestamps_ns=pose_ts,
        city_SE3_ego=city_SE3_ego,
        ego_SE3_sensor=av2.read_ego_SE3_sensors(log_dir),
        intrinsics=intrinsics if intrinsics is not None else av2.read_intrinsics(log_dir),
        sweep_timestamps_ns=av2.list_sweep_timestamps_ns(log_dir),
        image_timestamps_ns={cam: av2.list_image_timestamps_ns(log_dir, cam) for cam in camera_ids},
        annotations=av2.read_annotations(log_dir),
    )


def ego_trajectory(inputs: LogInputs, needed_us: tuple[int, int], warnings: list[str]) -> tuple[Trajectory, np.ndarray]:
    """``T_rig_world`` relative to the first pose, and ``T_world_world_global`` (= first city_SE3_ego).

    Timestamps go ns -> µs (floor) with duplicate µs dropped (first kept). Where sensor data reach
    up to ``MAX_POSE_EXTRAPOLATION_US`` outside the pose table, the trajectory is extended at
    constant velocity (reported as a warning); further, or across a gap in the poses longer than
    that, the log fails naming the pose table. The returned trajectory holds the float32-rounded
    poses that are stored, so every transform computed from it matches what NCore readers reconstruct.
    """
    path = inputs.log_dir / "city_SE3_egovehicle.feather"
    ts_us, first = np.unique(inputs.pose_timestamps_ns // 1000, return_index=True)
    city_SE3_ego = inputs.city_SE3_ego[first]
    T_world_world_global = city_SE3_ego[0]
    T_rig_world = invert_se3(T_world_world_global) @ city_SE3_ego
    traj = Trajectory(ts_us.astype(np.int64), T_rig_world)
    start_us, end_us = needed_us
    _check_pose_gaps(path, ts_us, needed_us)
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
    return Trajectory(traj.timestamps_us, stored), T_world_world_global


def _check_pose_gaps(path: UPath, pose_us: np.ndarray, needed_us: tuple[int, int]) -> None:
    """SourceError if consecutive poses inside the sensor time range are further apart than
    ``MAX_POSE_EXTRAPOLATION_US`` (interpolating across the gap would invent the motion)."""
    gaps = np.diff(pose_us)
    inside = (pose_us[1:] > needed_us[0]) & (pose_us[:-1] < needed_us[1])
    bad = np.flatnonzero(inside & (gaps > MAX_POSE_EXTRAPOLATION_US))
    if bad.size:
        i = int(bad[0])
        raise SourceError(
            path,
            f"no pose for {gaps[i] / 1e3:.1f} ms between timestamp_ns {pose_us[i] * 1000} and"
            f" {pose_us[i + 1] * 1000}, where sensor data exist (at most {MAX_POSE_EXTRAPOLATION_US / 1e3:g} ms)",
        )


def unit_rows(
    sweep: av2.Sweep,
    low_half: bool,
    T_rig_world: Trajectory,
    T_sensor_rig: np.ndarray,
    knots: lidar_timing.RotationKnots | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Row indices of one laser_number half (< 32 or >= 32) and their absolute firing times (ns,
    int64): from offset_ns, or reconstructed with the unit's rotation ``knots`` (TbV)."""
    idx = np.flatnonzero((sweep.laser_number < 32) == low_half)
    if sweep.offset_ns is not None:
        return idx, sweep.timestamp_ns + sweep.offset_ns[idx].astype(np.int64)
    beam = sweep.laser_number[idx].astype(np.int64) % vlp32c.N_BEAMS
    times_ns = lidar_timing.reconstruct_times(
        sweep.xyz_ego_m[idx], beam, sweep.timestamp_ns, knots, T_rig_world, T_sensor_rig
    ).times_ns
    _check_covered(sweep, times_ns, T_rig_world)
    return idx, times_ns


def _check_covered(sweep: av2.Sweep, times_ns: np.ndarray, T_rig_world: Trajectory) -> None:
    start_ns, end_ns = T_rig_world.start_us * 1000, T_rig_world.end_us * 1000
    if len(times_ns) and not (start_ns <= times_ns.min() and times_ns.max() <= end_ns):
        raise SourceError(
            sweep.path,
            f"point times reach outside the log's time range {start_ns}..{end_ns} ns"
            " (set by the poses and the first and last sweeps)",
        )


def read_covered_sweep(log_dir: UPath, timestamp_ns: int, T_rig_world: Trajectory, with_offsets: bool) -> av2.Sweep:
    """Read a sweep; with offset_ns, check that the trajectory covers all its point times
    (SourceError if not). Reconstructed times are checked when they are computed."""
    sweep = av2.read_sweep(log_dir, timestamp_ns, with_offsets)
    if with_offsets:
        _check_covered(sweep, timestamp_ns + sweep.offset_ns.astype(np.int64), T_rig_world)
    return sweep


@dataclass(frozen=True)
class LidarCalibration:
    """Per-log lidar decisions: which laser_number half is which unit, each unit's model, and
    (without offset_ns) each unit's rotation knots for the firing times."""

    unit_split: UnitSplit
    models: dict[str, SpinningLidarModel]
    model_seconds: dict[str, float]  #: derivation time of each model (benchmark figure)
    knots: dict[str, lidar_timing.RotationKnots]  #: empty when offset_ns gives the times
    timing_meta: dict[str, dict]  #: per unit: how its firing times were obtained, with residuals


@dataclass(frozen=True)
class TriggerTiming:
    """What reconstructing firing times needs beyond the sweeps: the camera-trigger grid
    (:func:`lidar_timing.trigger_phases_ns`) and the ring cameras' extrinsics (T_camera_rig)."""

    grid: tuple[int, np.ndarray]
    T_cameras_rig: list[np.ndarray]


def _unit_knots(
    sweeps: list[av2.Sweep], T_rig_world: Trajectory, T_sensor_rig: dict[str, np.ndarray], timing: TriggerTiming
) -> dict[tuple[str, str], lidar_timing.RotationKnots]:
    """Rotation knots for every (laser_number half, unit) hypothesis."""
    knots = {}
    for half, low in (("low", True), ("high", False)):
        rows = []
        for sweep in sweeps:
            idx = np.flatnonzero((sweep.laser_number < 32) == low)
            beam = sweep.laser_number[idx].astype(np.int64) % vlp32c.N_BEAMS
            rows.append((sweep.xyz_ego_m[idx], beam, sweep.timestamp_ns))
        for unit, T in T_sensor_rig.items():
            camera_azimuths = lidar_timing.camera_azimuths_deg(T, timing.T_cameras_rig)
            try:
                knots[(half, unit)] = lidar_timing.unit_rotation(camera_azimuths, rows, timing.grid, T_rig_world, T)
            except lidar_timing.TimingError as err:
                raise SourceError(sweeps[0].path.parent, f"cannot time the lidar points of {unit}: {err}") from None
    return knots


def calibrate_lidars(
    log_dir: UPath,
    sweep_timestamps_ns: np.ndarray,
    T_rig_world: Trajectory,
    T_sensor_rig: dict[str, np.ndarray],
    model_units: list[str],
    timing: TriggerTiming | None = None,
) -> LidarCalibration:
    """Decide the unit split, then derive the structured model of each unit in ``model_units``.

    On a few sweeps spread over the log, each laser_number half is decompensated into each candidate
    unit's frame; the assignment with the flatter beams wins. The models are fitted to the same
    decompensated (per-point-time) returns in the winning frames. Without offset_ns (``timing``
    given), each hypothesis gets its own reconstructed firing times.
    """
    picks = np.unique(np.linspace(0, len(sweep_timestamps_ns) - 1, CALIBRATION_SWEEPS).round().astype(int))
    sweeps = [read_covered_sweep(log_dir, int(sweep_timestamps_ns[i]), T_rig_world, timing is None) for i in picks]
    knots = _unit_knots(sweeps, T_rig_world, T_sensor_rig, timing) if timing is not None else {}
    spread: dict[tuple[str, str], float] = {}
    halves: dict[tuple[str, str], list] = {}
    for k, sweep in enumerate(sweeps):
        for half, low in (("low", True), ("high", False)):
            for unit, T in T_sensor_rig.items():
                idx, times_ns = unit_rows(sweep, low, T_rig_world, T, knots.get((half, unit)))
                beam = sweep.laser_number[idx].astype(np.int64) % vlp32c.N_BEAMS
                xyz = decompensate(sweep.xyz_ego_m[idx], times_ns, sweep.timestamp_ns, T_rig_world, T)
                spread[(half, unit)] = spread.get((half, unit), 0.0) + beam_elevation_spread_rad(xyz, beam)
                halves.setdefault((half, unit), []).append((xyz, beam, (times_ns - sweep.timestamp_ns) * 1e-9, k))
    split = decide_unit_split(spread)
    chosen = {split.low_half_unit: "low", split.high_half_unit: "high"}
    models, seconds = {}, {}
    for unit in model_units:
        started = time.perf_counter()
        half = chosen[unit]
        xyz = np.concatenate([h[0] for h in halves[(half, unit)]]).astype(np.float64)
        distance = np.linalg.norm(xyz, axis=1)
        ok = np.isfinite(distance) & (distance >= MIN_RANGE_M)
        models[unit] = derive_model(
            direction=xyz[ok] / distance[ok, None],
            distance_m=distance[ok],
            beam=np.concatenate([h[1] for h in halves[(half, unit)]])[ok],
            time_s=np.concatenate([h[2] for h in halves[(half, unit)]])[ok],
            frame=np.concatenate([np.full(len(h[1]), h[3]) for h in halves[(half, unit)]])[ok],
            n_beams=vlp32c.N_BEAMS,
            firing_cycle_s=vlp32c.FIRING_CYCLE_NS * 1e-9,
            upsample=MODEL_UPSAMPLE,
        )
        seconds[unit] = time.perf_counter() - started
    unit_knots = {unit: knots[(half, unit)] for unit, half in chosen.items() if knots}
    for unit, unit_knot in unit_knots.items():
        try:
            lidar_timing.check_first_firing(unit_knot)
        except lidar_timing.TimingError as err:
            raise SourceError(log_dir / "sensors" / "lidar", f"cannot time the lidar points of {unit}: {err}") from None
    timing_meta = {unit: _timing_meta(unit_knots.get(unit), timing) for unit in chosen}
    return LidarCalibration(split, models, seconds, unit_knots, timing_meta)


def _timing_meta(knots: lidar_timing.RotationKnots | None, timing: TriggerTiming | None) -> dict:
    if knots is None:
        return {"method": "offset_ns", "note": "per-point time = sweep timestamp + offset_ns"}
    return {
        "method": "reconstructed",
        "note": "firing azimuth (own-frame azimuth minus beam offset) mapped to time through the unit's"
        " crossings of the camera axes, taken from the 100 ms camera-trigger grid (image and pose timestamps);"
        " revolution from the row (firing) order",
        "spin": knots.spin,
        "trigger_phases": len(timing.grid[1]),
        "trigger_delay_ms": lidar_timing.TRIGGER_DELAY_MS,
        "knot_residual_ms": round(knots.residual_ms, 4),
        "first_firing_ms": round(knots.first_firing_ms, 3),
        "knots": {"times_ms": knots.times_ms.round(4).tolist(), "azimuth_deg": knots.azimuth_deg.round(4).tolist()},
    }


def sweep_ray_bundles(
    sweep: av2.Sweep,
    calibration: LidarCalibration,
    T_rig_world: Trajectory,
    T_sensor_rig: dict[str, np.ndarray],
) -> dict[str, tuple[RayBundle, np.ndarray | None, dict]]:
    """Split one sweep by unit, decompensate each half into its unit's frame at per-point time, and
    give each ray its nearest model element (uint16 [N,2], or None without a model), plus the
    frame's affine column-time alignment (see :func:`column_time_remap`; empty without a model)."""
    out = {}
    split = calibration.unit_split
    for unit, low in ((split.low_half_unit, True), (split.high_half_unit, False)):
        if unit not in T_sensor_rig:
            continue
        idx, times_ns = unit_rows(sweep, low, T_rig_world, T_sensor_rig[unit], calibration.knots.get(unit))
        xyz = decompensate(sweep.xyz_ego_m[idx], times_ns, sweep.timestamp_ns, T_rig_world, T_sensor_rig[unit])
        rays = ray_bundle(xyz, times_ns, sweep.intensity[idx], sweep.timestamp_ns // 1000)
        model = calibration.models.get(unit)
        elements, remap = None, {}
        if model is not None:
            beam = sweep.laser_number[idx[rays.source_index]].astype(np.int64) % vlp32c.N_BEAMS
            elements = model.assign_elements(rays.direction, beam)
            time_s = (times_ns[rays.source_index] - sweep.timestamp_ns) * 1e-9
            remap = column_time_remap(
                elements[:, 1], time_s, len(model.column_azimuths_rad), model.spinning_frequency_hz
            )
        out[unit] = (rays, elements, remap)
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


def _sensor_time_range_us(
    inputs: LogInputs, camera_ids: list[str], with_lidar: bool, with_offsets: bool
) -> tuple[int, int]:
    """Inclusive µs range the trajectory must cover: lidar points at their exact ns times (so the
    end rounds up), camera frames and cuboids at their stored (floored) µs times.

    The lidar range comes from the first and the last sweep (each sweep's points span ~106 ms from
    its timestamp, so they bound all others); every other sweep is checked when it is converted.
    Without offset_ns, the range is the widest that reconstructed times can take (SWEEP_SPAN_MS).
    """
    lo, hi = [], []
    if with_lidar and not with_offsets:
        lo.append((int(inputs.sweep_timestamps_ns[0]) + int(lidar_timing.SWEEP_SPAN_MS[0] * 1e6)) // 1000)
        hi.append(-(-(int(inputs.sweep_timestamps_ns[-1]) + int(lidar_timing.SWEEP_SPAN_MS[1] * 1e6)) // 1000))
    elif with_lidar:
        for ts in {int(inputs.sweep_timestamps_ns[0]), int(inputs.sweep_timestamps_ns[-1])}:
            first, last = av2.read_sweep_offset_range_ns(inputs.log_dir, ts)
            lo.append((ts + min(first, 0)) // 1000)
            hi.append(-(-(ts + last) // 1000))
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


@dataclass(frozen=True)
class LogPlan:
    """Everything the writing jobs of one log need, read and decided once (picklable).

    Attributes:
        T_rig_world: stored (float32-rounded) ego trajectory, µs.
        T_world_world_global: first city_SE3_ego [4,4], float64.
        lidar_calibration: unit split and models (None without lidars).
    """

    inputs: LogInputs
    options: Argoverse2Options
    log_id: str
    camera_ids: list[str]
    lidar_ids: list[str]
    T_rig_world: Trajectory
    T_world_world_global: np.ndarray
    lidar_calibration: LidarCalibration | None
    generic_meta: dict
    warnings: list[str]

    @property
    def sweep_timestamps_ns(self) -> np.ndarray:
        return self.inputs.sweep_timestamps_ns if self.lidar_ids else np.zeros(0, dtype=np.int64)

    @property
    def n_frames(self) -> int:
        return len(self.sweep_timestamps_ns) + sum(len(self.inputs.image_timestamps_ns[c]) for c in self.camera_ids)

    def writer(self, output_dir: UPath, base: bool) -> SequenceWriter:
        return SequenceWriter(
            output_dir=output_dir,
            sequence_id=self.log_id,
            interval_us=(self.T_rig_world.start_us, self.T_rig_world.end_us),
            generic_meta_data=self.generic_meta,
            camera_ids=self.camera_ids,
            lidar_ids=self.lidar_ids,
            store_type=self.options.store_type,
            profile=self.options.profile,
            base=base,
            poses_meta={
                "calibration_type": "argoverse2-calibration",
                "egomotion_type": "argoverse2-city_SE3_egovehicle",
            },
        )


def _trigger_timing(inputs: LogInputs) -> TriggerTiming:
    """The camera-trigger grid from every image and pose timestamp, and the ring cameras' extrinsics."""
    candidates = np.concatenate([inputs.pose_timestamps_ns, *inputs.image_timestamps_ns.values()])
    try:
        grid = lidar_timing.trigger_phases_ns(np.setdiff1d(candidates, inputs.sweep_timestamps_ns))
    except lidar_timing.TimingError as err:
        raise SourceError(
            inputs.log_dir / "city_SE3_egovehicle.feather", f"cannot time the lidar points: {err}"
        ) from None
    rings = [cam for cam in av2.RING_CAMERAS if cam in inputs.ego_SE3_sensor]
    if not rings:
        raise SourceError(inputs.log_dir / "calibration" / "egovehicle_SE3_sensor.feather", "no ring camera extrinsics")
    return TriggerTiming(grid, [inputs.ego_SE3_sensor[cam] for cam in rings])


def plan_log(root_dir: UPath, log_id: str, options: Argoverse2Options) -> LogPlan:
    """Read a log's small inputs, check them, and make the per-log decisions (trajectory, unit split)."""
    warnings: list[str] = []
    log_dir = options.log_dir(root_dir, log_id)
    require_folder(log_dir, "log directory")
    lidar_ids = select_sensors(options.lidar_ids, av2.LIDARS, "lidar")
    intrinsics = None
    if options.tbv:  # the cameras are those of the log's calibration
        intrinsics = av2.read_intrinsics(log_dir)
        try:
            camera_ids = select_sensors(options.camera_ids, tuple(intrinsics), "camera")
        except ValueError as err:
            raise SourceError(log_dir / "calibration" / "intrinsics.feather", str(err)) from None
    else:
        camera_ids = select_sensors(options.camera_ids, av2.CAMERAS, "camera")
    inputs = read_log_inputs(log_dir, camera_ids, intrinsics)

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
    if lidar_ids and len(inputs.sweep_timestamps_ns) == 0:
        warnings.append(f"{log_dir / 'sensors' / 'lidar'}: no sweeps; lidars not written")
        lidar_ids = []

    needed_us = _sensor_time_range_us(inputs, camera_ids, bool(lidar_ids), not options.tbv)
    T_rig_world, T_world_world_global = ego_trajectory(inputs, needed_us, warnings)
    lidar_calibration = None
    if lidar_ids:
        T_lidar_rig = {unit: inputs.ego_SE3_sensor[unit] for unit in av2.LIDARS}
        model_units = lidar_ids if options.lidar_model_source == "empirical" else []
        timing = _trigger_timing(inputs) if options.tbv else None
        lidar_calibration = calibrate_lidars(
            log_dir, inputs.sweep_timestamps_ns, T_rig_world, T_lidar_rig, model_units, timing
        )
        split = lidar_calibration.unit_split
        if split.margin < UNIT_DECISION_MIN_MARGIN:
            warnings.append(
                f"{log_dir}: up/down lidar decision has a low margin {split.margin:.2f}"
                f" (laser_number < 32 -> {split.low_half_unit})"
            )
    generic_meta = {
        "source_dataset": "argoverse2-tbv" if options.tbv else SOURCE_DATASET,
        "argoverse2_split": options.split,
        "argoverse2_log_id": log_id,
        "converter": {"name": "ncore-convert", "version": __version__, "options": asdict(options)},
    }
    return LogPlan(
        inputs=inputs,
        options=options,
        log_id=log_id,
        camera_ids=camera_ids,
        lidar_ids=lidar_ids,
        T_rig_world=T_rig_world,
        T_world_world_global=T_world_world_global,
        lidar_calibration=lidar_calibration,
        generic_meta=generic_meta,
        warnings=warnings,
    )


@dataclass
class JobResult(Counts):
    """Counts of the jobs of one writer part, and its sequence-meta part (None without meta)."""

    meta: object = None


def _write_base(plan: LogPlan, writer: SequenceWriter, result: JobResult, progress: Callable[[int], None]) -> None:
    """Poses (trajectory, world_global, sensor extrinsics), camera and lidar models, masks and cuboids."""
    inputs = plan.inputs
    writer.store_trajectory(plan.T_rig_world.timestamps_us, plan.T_rig_world.poses, plan.T_world_world_global)
    for sensor in plan.lidar_ids + plan.camera_ids:
        writer.store_extrinsic(sensor, inputs.ego_SE3_sensor[sensor])  # av2 ego_SE3_sensor is T_sensor_rig
    for cam in plan.camera_ids:
        intr = inputs.intrinsics[cam]
        writer.store_pinhole_camera(
            cam,
            focal_length_px=(intr.fx_px, intr.fy_px),
            principal_point_px=(intr.cx_px + 0.5, intr.cy_px + 0.5),
            resolution_px=(intr.width_px, intr.height_px),
        )
    if plan.lidar_calibration is not None:
        for unit, model in plan.lidar_calibration.models.items():
            writer.store_lidar_model(unit, model)
    cuboids = annotation_cuboids(inputs.annotations) if inputs.annotations is not None else None
    writer.store_cuboids(cuboids)
    if plan.options.maps:
        _store_map(inputs.log_dir, writer, result)
    result.cuboids = 0 if cuboids is None else len(cuboids)


def _store_map(log_dir: UPath, writer: SequenceWriter, result: JobResult) -> None:
    """The log's HD map, as stored, in the city frame (= world_global), or a warning without one."""
    log_map = av2.read_log_map(log_dir)
    if log_map is None:
        result.warnings.append(f"{log_dir / 'map'}: no map folder; no HD map written")
        return
    vector_name, raster_name, sim2_name = log_map.file_names
    writer.store_map(
        log_map.vector_map_json,
        log_map.ground_height_m,
        {
            "frame": "world_global (the AV2 city frame)",
            "vector_map_file": vector_name,
            "ground_height_file": raster_name,
            "img_Sim2_city_file": sim2_name,
            "city": vector_name.split("____")[1].split("_")[0] if "____" in vector_name else None,
            "img_Sim2_city": log_map.img_Sim2_city,
            "raster_lookup": "p_img = s * (R @ [x, y] + t) with (x, y) in world_global metres, R row-major 2x2;"
            " value = ground_height_m[int(p_img[1]), int(p_img[0])] (truncation; NaN outside the region of interest)",
            "resolution_m": 1.0 / float(log_map.img_Sim2_city["s"]),
        },
    )
    result.maps = 1


def _lidar_meta(calibration: LidarCalibration, unit: str, model_source: str) -> dict:
    """Lidar component metadata: the unit decision and, with a model, how it was derived and the
    laser_number -> model row map (the NCore model itself has no place for it)."""
    meta = {
        "av2_unit_decision": calibration.unit_split.to_meta(),
        "lidar_model_source": model_source,
        "point_timing": calibration.timing_meta[unit],
    }
    if (model := calibration.models.get(unit)) is not None:
        first_laser = 0 if unit == calibration.unit_split.low_half_unit else vlp32c.N_BEAMS
        meta["lidar_model"] = {
            "laser_number_to_row": {str(first_laser + b): int(r) for b, r in enumerate(model.beam_to_row)},
            "columns_per_firing_cycle": MODEL_UPSAMPLE,
            "firing_cycle_ns": vlp32c.FIRING_CYCLE_NS,
            "calibration_sweeps": CALIBRATION_SWEEPS,
            "element_assignment": "beam row; nearest column to the ray azimuth minus the row offset",
        }
    return meta


def _write_lidars(plan: LogPlan, writer: SequenceWriter, result: JobResult, progress: Callable[[int], None]) -> None:
    """Stream sweeps one at a time: read, split by unit, decompensate, assign model elements, store.
    Memory stays flat."""
    started = time.perf_counter()
    log_dir = plan.inputs.log_dir
    calibration = plan.lidar_calibration
    T_sensor_rig = {unit: plan.inputs.ego_SE3_sensor[unit] for unit in plan.lidar_ids}
    lidars = {  # one metadata dict per lidar: the writer updates it in place
        unit: writer.add_lidar(unit, _lidar_meta(calibration, unit, plan.options.lidar_model_source))
        for unit in plan.lidar_ids
    }
    not_stored = {unit: {"zero_range": 0, "non_finite": 0} for unit in lidars}
    source_points = {unit: 0 for unit in lidars}
    for ts in plan.sweep_timestamps_ns:
        sweep = read_covered_sweep(log_dir, int(ts), plan.T_rig_world, not plan.options.tbv)
        bundles = sweep_ray_bundles(sweep, calibration, plan.T_rig_world, T_sensor_rig)
        for unit, (rays, elements, remap) in bundles.items():
            frame_meta = {
                "av2_sweep_timestamp_ns": int(ts),
                "points_zero_range": rays.n_zero_range,
                "points_non_finite": rays.n_non_finite,
            }
            if remap:
                frame_meta["model_column_time_remap"] = remap
            lidars[unit].store_frame(rays, frame_meta, model_element=elements)
            not_stored[unit]["zero_range"] += rays.n_zero_range
            not_stored[unit]["non_finite"] += rays.n_non_finite
            source_points[unit] += len(rays) + rays.n_zero_range + rays.n_non_finite
            result.points += len(rays)
            result.points_not_stored += rays.n_zero_range + rays.n_non_finite
        result.sweeps += 1
        progress(1)
    for unit, stream in lidars.items():
        stream.set_meta({"source_points": source_points[unit], "points_not_stored": not_stored[unit]})
    if result.points_not_stored:
        result.warnings.append(
            f"{result.points_not_stored} lidar points with zero range or non-finite coordinates not stored"
        )
    result.lidar_seconds = time.perf_counter() - started


def _write_camera(
    plan: LogPlan, writer: SequenceWriter, cam: str, result: JobResult, progress: Callable[[int], None]
) -> None:
    """Copy every JPEG as-is into its camera component, with frame times [t, t] (global shutter)."""
    started = time.perf_counter()
    stream = writer.add_camera(cam, _camera_meta(plan.inputs.intrinsics[cam]))
    for ts in plan.inputs.image_timestamps_ns[cam]:
        t_us = int(ts) // 1000
        stream.store_frame(av2.read_jpeg(plan.inputs.log_dir, cam, int(ts)), "jpeg", (t_us, t_us))
        result.images += 1
        progress(1)
    result.camera_seconds += time.perf_counter() - started


def write_part(
    plan: LogPlan, output_dir: UPath, jobs: list[tuple[str, ...]], progress: Callable[[int], None]
) -> JobResult:
    """Write the jobs of one independent part (see :func:`log_jobs`) with one writer; runs in a worker."""
    result = JobResult()
    writer = plan.writer(output_dir, base=(BASE,) in jobs)
    for job in jobs:
        if job == (BASE,):
            _write_base(plan, writer, result, progress)
        elif job == tuple(plan.lidar_ids):
            _write_lidars(plan, writer, result, progress)
        else:
            (cam,) = job
            _write_camera(plan, writer, cam, result, progress)
    result.meta = writer.finalize(with_meta=plan.options.sequence_meta)
    return result


#: Rough single-core costs used to start the longest parts first (seconds per item).
_COST_S = {"sweep": 0.05, "image": 0.0035, "cuboid": 0.00025}


def log_jobs(plan: LogPlan) -> list[tuple[list[tuple[str, ...]], float]]:
    """The log's writing jobs grouped into independent parts, with an estimated cost per part.

    Jobs: the base components, all lidars (they share each sweep read), and one per camera.
    Parts are in store order: base first, then lidars, then cameras.
    """
    jobs: list[tuple[str, ...]] = [(BASE,)] + ([tuple(plan.lidar_ids)] if plan.lidar_ids else [])
    jobs += [(cam,) for cam in plan.camera_ids]
    n_cuboids = 0 if plan.inputs.annotations is None else len(plan.inputs.annotations)
    cost = [_COST_S["cuboid"] * n_cuboids]
    cost += [_COST_S["sweep"] * len(plan.sweep_timestamps_ns)] if plan.lidar_ids else []
    cost += [_COST_S["image"] * len(plan.inputs.image_timestamps_ns[cam]) for cam in plan.camera_ids]
    parts = independent_parts(jobs, plan.camera_ids, plan.lidar_ids, plan.options.profile)
    return [([jobs[i] for i in part], sum(cost[i] for i in part)) for part in parts]


def convert_log(
    root_dir: UPath,
    output_dir: UPath,
    log_id: str,
    options: Argoverse2Options,
    pool: JobPool | None = None,
    progress: Progress | None = None,
) -> LogSummary:
    """Convert one AV2 log into ``output_dir`` (which becomes the sequence directory).

    Args:
        pool: worker processes for the log's independent store parts; None writes them in this process.
        progress: told the number of frames (sweeps + images) to write, then each written frame.
    """
    started = time.perf_counter()
    progress = progress or Progress()
    plan = plan_log(root_dir, log_id, options)
    progress.total(plan.n_frames)
    parts = log_jobs(plan)
    output_dir.mkdir(parents=True, exist_ok=True)
    longest_first = sorted(range(len(parts)), key=lambda i: -parts[i][1])
    calls = [(write_part, (plan, output_dir, parts[i][0])) for i in longest_first]
    done = pool.run(calls, progress) if pool else run_inline(calls, progress)
    results = [done[longest_first.index(i)] for i in range(len(parts))]

    if options.sequence_meta:
        write_sequence_meta(output_dir, log_id, [r.meta for r in results if r.meta is not None])
    summary = LogSummary(log_id=log_id, warnings=list(plan.warnings))
    if plan.lidar_calibration is not None:
        summary.lidar_model_seconds = max(plan.lidar_calibration.model_seconds.values(), default=0.0)
    for result in results:
        summary.add(result)
    summary.seconds = time.perf_counter() - started
    return summary
