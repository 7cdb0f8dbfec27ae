"""Argoverse 2 lidar decisions and rays, per log: which laser_number half is which unit, each unit's
structured model, the firing times (``offset_ns``, or reconstructed for TbV), and each sweep's
per-unit ray bundles with their model elements.

Frames: ``rig`` is av2's ``egovehicle``; ``T_sensor_rig`` maps a unit's points to the rig.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial

import numpy as np
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.reader import Reader
from ncore_convert.sources.store import ObjectInfo
from ncore_convert.transforms.geometry import Trajectory
from ncore_convert.transforms.lidar import timing as lidar_timing
from ncore_convert.transforms.lidar import vlp32c
from ncore_convert.transforms.lidar.frames import LidarFrame, LidarGeometry
from ncore_convert.transforms.lidar.model import SpinningLidarModel, column_time_remap, derive_model
from ncore_convert.transforms.lidar.rays import (
    MIN_RANGE_M,
    RayBundle,
    UnitSplit,
    beam_elevation_spread_rad,
    decide_unit_split,
    decompensate,
    rig_motion_columns,
)
from ncore_convert.transforms.sampling import spread_indices
from ncore_convert.transforms.timebase import NS_PER_US

#: Sweeps sampled across the log for the up/down unit decision and the lidar model.
CALIBRATION_SWEEPS = 5


#: Columns of the empirical lidar model per native VLP-32C column (firing cycle): its azimuth
#: quantisation (mean 0.003°) then stays below the float16 noise of AV2's coordinates.
MODEL_UPSAMPLE = 16


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
    start_ns, end_ns = T_rig_world.start_us * NS_PER_US, T_rig_world.end_us * NS_PER_US
    if len(times_ns) and not (start_ns <= times_ns.min() and times_ns.max() <= end_ns):
        raise SourceError(
            sweep.path,
            f"point times reach outside the log's time range {start_ns}..{end_ns} ns"
            " (set by the poses and the first and last sweeps)",
        )


def sweep_times_ns(
    sweep: av2.Sweep, calibration: LidarCalibration, T_rig_world: Trajectory, T_sensor_rig: dict[str, np.ndarray]
) -> np.ndarray:
    """Every row's own firing time, ns, int64 [N], computed once per sweep for its rays, flags and
    colours: ``timestamp_ns + offset_ns``, or (TbV: no offset_ns) reconstructed per laser_number half
    with the rotation knots of its unit in ``T_sensor_rig`` (the rows of a unit not converted keep
    the sweep time: they are not stored). SourceError if the log's time range does not cover them."""
    if sweep.offset_ns is not None:
        times_ns = sweep.timestamp_ns + sweep.offset_ns.astype(np.int64)
        _check_covered(sweep, times_ns, T_rig_world)
        return times_ns
    times_ns = np.full(len(sweep.laser_number), sweep.timestamp_ns, dtype=np.int64)
    split = calibration.unit_split
    for unit, low in ((split.low_half_unit, True), (split.high_half_unit, False)):
        if unit in T_sensor_rig:
            idx, times_ns[idx] = unit_rows(sweep, low, T_rig_world, T_sensor_rig[unit], calibration.knots[unit])
    return times_ns


def read_covered_sweeps(
    log_dir: UPath,
    timestamps_ns: list[int],
    T_rig_world: Trajectory,
    with_offsets: bool,
    listing: dict[str, ObjectInfo] | None = None,
    reader: Reader | None = None,
) -> list[av2.Sweep]:
    """Read sweeps (fetched ahead); with offset_ns, check that the trajectory covers all their point
    times (SourceError if not). Reconstructed times are checked when they are computed."""
    sweeps = list(av2.read_sweeps(log_dir, timestamps_ns, with_offsets, listing, reader=reader))
    if with_offsets:
        for sweep in sweeps:
            _check_covered(sweep, sweep.timestamp_ns + sweep.offset_ns.astype(np.int64), T_rig_world)
    return sweeps


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

    grid: lidar_timing.TriggerGrid
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
    listing: dict[str, ObjectInfo] | None = None,
    reader: Reader | None = None,
) -> LidarCalibration:
    """Decide the unit split, then derive the structured model of each unit in ``model_units``.

    On a few sweeps spread over the log, each laser_number half is decompensated into each candidate
    unit's frame; the assignment with the flatter beams wins. The models are fitted to the same
    decompensated (per-point-time) returns in the winning frames. Without offset_ns (``timing``
    given), each hypothesis gets its own reconstructed firing times.
    """
    picks = spread_indices(len(sweep_timestamps_ns), CALIBRATION_SWEEPS)
    stamps = [int(sweep_timestamps_ns[i]) for i in picks]
    sweeps = read_covered_sweeps(log_dir, stamps, T_rig_world, timing is None, listing, reader)
    knots = _unit_knots(sweeps, T_rig_world, T_sensor_rig, timing) if timing is not None else {}
    spread: dict[tuple[str, str], float] = {}
    halves: dict[tuple[str, str], list] = {}
    for k, sweep in enumerate(sweeps):
        for half, low in (("low", True), ("high", False)):
            motion = None  # with offset_ns, both units' rows of a half share their times: one rig motion
            for unit, T in T_sensor_rig.items():
                idx, times_ns = unit_rows(sweep, low, T_rig_world, T, knots.get((half, unit)))
                beam = sweep.laser_number[idx].astype(np.int64) % vlp32c.N_BEAMS
                if not knots and motion is None and len(times_ns):
                    motion = rig_motion_columns(T_rig_world, times_ns, sweep.timestamp_ns)
                xyz = decompensate(sweep.xyz_ego_m[idx], times_ns, sweep.timestamp_ns, T_rig_world, T, motion)
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
        "trigger_phases": len(timing.grid.phases_ns),
        "trigger_delay_ms": lidar_timing.TRIGGER_DELAY_MS,
        "knot_residual_ms": round(knots.residual_ms, 4),
        "first_firing_ms": round(knots.first_firing_ms, 3),
        "knots": {"times_ms": knots.times_ms.round(4).tolist(), "azimuth_deg": knots.azimuth_deg.round(4).tolist()},
    }


def sweep_frame(
    sweep: av2.Sweep,
    times_ns: np.ndarray,
    calibration: LidarCalibration,
    T_rig_world: Trajectory,
    T_sensor_rig: dict[str, np.ndarray],
) -> tuple[LidarFrame, dict[str, LidarGeometry]]:
    """One sweep as :func:`lidar_frames.lidar_frame` takes it: the compensated ego-frame points with
    their own times (``times_ns``: :func:`sweep_times_ns`) and the sweep's pose in ``world``, each
    converted unit's laser_number half; and how each unit's rays are made (decompensated into its
    frame at each point's time; its model's nearest elements)."""
    split = calibration.unit_split
    halves = [
        (unit, low)
        for unit, low in ((split.low_half_unit, True), (split.high_half_unit, False))
        if unit in T_sensor_rig
    ]
    rows = {unit: np.flatnonzero((sweep.laser_number < 32) == low) for unit, low in halves}
    T_sweep_world = T_rig_world.interpolate(T_rig_world.relative_seconds(np.array([sweep.timestamp_ns])))[0]
    frame = LidarFrame(sweep.xyz_ego_m, times_ns, sweep.intensity, sweep.timestamp_ns, rows, T_sweep_world)
    geometry = {
        unit: LidarGeometry(
            to_sensor=partial(
                decompensate, ref_time_ns=sweep.timestamp_ns, T_rig_world=T_rig_world, T_sensor_rig=T_sensor_rig[unit]
            ),
            elements=None
            if unit not in calibration.models
            else partial(_elements, calibration.models[unit], sweep, times_ns),
            row_steps_rad=calibration.models[unit].row_steps_rad(MODEL_UPSAMPLE)
            if unit in calibration.models
            else None,
        )
        for unit, _ in halves
    }
    return frame, geometry


def _elements(
    model: SpinningLidarModel, sweep: av2.Sweep, times_ns: np.ndarray, rays: RayBundle, rows: np.ndarray
) -> tuple[np.ndarray, dict]:
    """Each ray's nearest element of its unit's model (its beam row), and the sweep's column-time
    alignment (``rows``: each ray's sweep row)."""
    beam = sweep.laser_number[rows].astype(np.int64) % vlp32c.N_BEAMS
    elements = model.assign_elements(rays.direction, beam)
    time_s = (times_ns[rows] - sweep.timestamp_ns) * 1e-9
    return elements, column_time_remap(
        elements[:, 1], time_s, len(model.column_azimuths_rad), model.spinning_frequency_hz
    )


def lidar_meta(calibration: LidarCalibration, unit: str, model_source: str) -> dict:
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
