"""AV2 / TbV ``--dynamic-source lidar|both``: which points move, from the lidar itself (issue 53;
docs/motion.md). The sweeps stream through :class:`~ncore_convert.transforms.lidar.motion_window.MotionWindow`,
which needs the sweeps up to ``max(motion_window.OFFSETS)`` after each: :func:`with_motion` holds the
frames that long and hands each on with what moved in it.

Each unit's sweep is seen from where that unit was as it fired each return (its mount on the rig at
the return's own time) and ordered by its beams (``laser_number``).
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np

from ncore_convert import contract
from ncore_convert.transforms.geometry import Trajectory, transform_points
from ncore_convert.transforms.lidar import free_space, motion_window
from ncore_convert.transforms.lidar.frames import LidarFrame, LidarGeometry, Moved
from ncore_convert.transforms.timebase import NS_PER_US

#: What a lidar's metadata says of the flags the lidar itself found (``point_data_notes``).
LIDAR_FLAGS = (
    "on a mover the lidar itself saw move: other sweeps saw through the place where it was (lidar free space;"
    " the sequence metadata's dynamic_flag_source says how)"
)
#: What the sequence metadata records of the lidar's flags.
MOTION_META = {
    "method": "lidar free space (ncore-convert transforms.lidar.free_space; docs/motion.md): a point is on a mover"
    " when other sweeps saw through its place (all four rays around it, the rows above and below in the columns"
    " either side, ended beyond it), grouped into objects by depth clustering in its own sweep, carried to the"
    " objects that continue a mover in the sweeps next to it",
    "parameters": {
        "sweep_offsets": list(motion_window.OFFSETS),
        "beyond_m": free_space.BEYOND_M,
        "beyond_fraction": free_space.BEYOND_FRACTION,
        "column_deg": float(np.degrees(free_space.COLUMN_RAD)),
        "tested_over_ground_m": free_space.GROUND_CLEARANCE_M,
        "object_over_ground_m": free_space.OBJECT_CLEARANCE_M,
        "samples_per_object": free_space.SAMPLES_PER_OBJECT,
        "min_evidence": free_space.MIN_EVIDENCE,
        "min_evidence_share": free_space.MIN_EVIDENCE_SHARE,
        "ground_cell_m": free_space.GROUND_CELL_M,
        "surface_angle_deg": float(np.degrees(free_space.SURFACE_ANGLE_RAD)),
        "join_depth_m": free_space.JOIN_DEPTH_M,
        "join_depth_fraction": free_space.JOIN_DEPTH_FRACTION,
        "max_row_gap_deg": float(np.degrees(free_space.MAX_ROW_GAP_RAD)),
        "follow_m": motion_window.FOLLOW_M,
        "follow_share": motion_window.FOLLOW_SHARE,
        "follow_stride": motion_window.FOLLOW_STRIDE,
        "settled_share": free_space.SETTLED_SHARE,
    },
    "judged_share": free_space.JUDGED_SHARE,
    "not_known": "a point the method cannot judge (its object's tested returns: fewer than judged_share in view"
    " of another sweep, all four rays around the place reaching it; hidden, beyond the range, or untested) has"
    f" {contract.DYNAMIC_UNKNOWN} 1 (and dynamic_flag 0): consumers that read only dynamic_flag take it as static",
}


def unit_sights(
    frame: LidarFrame, beams: np.ndarray, T_rig_world: Trajectory, T_sensor_rig: dict[str, np.ndarray]
) -> tuple[list[free_space.SweepSight], list[np.ndarray]]:
    """Each unit's returns of ``frame`` (its ``rows``, in order) as a :class:`free_space.SweepSight` in
    ``world``, from their finite returns; and which of the unit's rows those are (bool [K] each).
    ``beams``: every row's beam (``laser_number``) [N]."""
    sights, finite = [], []
    for unit, rows in frame.rows.items():
        xyz_m = transform_points(frame.T_reference_fixed, frame.xyz_m[rows].astype(np.float64))
        ok = np.isfinite(xyz_m).all(axis=1)
        times_us = frame.times_ns[rows][ok] // NS_PER_US
        origins_m = T_rig_world.positions_at(T_sensor_rig[unit][:3, 3], times_us)
        sights.append(free_space.SweepSight(xyz_m[ok], origins_m, beams[rows][ok]))
        finite.append(ok)
    return sights, finite


def with_motion(
    frames: Iterator[tuple[int, LidarFrame, dict[str, LidarGeometry], np.ndarray]],
    T_rig_world: Trajectory,
    T_sensor_rig: dict[str, np.ndarray],
) -> Iterator[tuple[int, LidarFrame, dict[str, LidarGeometry], Moved, float]]:
    """``frames`` (sweep time ns, frame, how its units' rays are made, every row's beam), each handed
    on with what moved in it and what could not be judged (:class:`Moved`, per row of
    ``frame.rows[unit]``; a non-finite row: neither) and the seconds spent finding it since the
    previous one. Holds the frames a :class:`motion_window.MotionWindow` needs
    ahead; memory does not grow with the log."""
    window = motion_window.MotionWindow()
    held: dict[int, tuple] = {}
    spent = 0.0

    def hand_on(k: int, flags: free_space.SweepFlags):
        nonlocal spent
        sweep_ns, frame, geometry, sights, finite = held.pop(k)
        found, unknown = {}, {}
        parts = zip(
            frame.rows.items(),
            flags.unit_parts(sights, flags.dynamic),
            flags.unit_parts(sights, flags.not_judged),
            finite,
            strict=True,
        )
        for (unit, rows), dynamic, not_judged, ok in parts:
            found[unit], unknown[unit] = np.zeros(len(rows), bool), np.zeros(len(rows), bool)
            found[unit][ok], unknown[unit][ok] = dynamic, not_judged
        seconds, spent = spent, 0.0
        return sweep_ns, frame, geometry, Moved(found, unknown=unknown), seconds

    for k, (sweep_ns, frame, geometry, beams) in enumerate(frames):
        started = time.perf_counter()
        sights, finite = unit_sights(frame, beams, T_rig_world, T_sensor_rig)
        held[k] = (sweep_ns, frame, geometry, sights, finite)
        ready = window.push(sights)
        spent += time.perf_counter() - started
        for j, flags in ready:
            yield hand_on(j, flags)
    started = time.perf_counter()
    ready = window.finish()
    spent += time.perf_counter() - started
    for j, flags in ready:
        yield hand_on(j, flags)
