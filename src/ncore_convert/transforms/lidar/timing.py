"""Per-point lidar firing times reconstructed without per-point timestamps (TbV has no offset_ns).

Facts used (measured on the real AV2 sample, where offset_ns gives the truth):
- each unit's points are stored in firing order;
- a point's firing azimuth (its azimuth in the unit's own frame minus its beam's azimuth offset)
  advances at about 3.6°/ms, one revolution per 100 ms;
- cameras are triggered on an exact 100 ms grid, each when one unit's firing azimuth crosses the
  camera's optical axis. The trigger times are every image timestamp, which the pose table also
  holds: every pose timestamp whose phase within 100 ms recurs is a trigger. So each unit gets
  one (time, azimuth) knot per camera and revolution, and a firing azimuth maps to a time within
  the 100 ms period by interpolating between knots (which also follows a non-uniform spin);
- the image timestamps lag the crossing by about 0.1 ms (:data:`TRIGGER_DELAY_MS`).

The knots fix the time within a period up to which of the two units (180° apart) a trigger
belongs to; the sweep timestamp settles that: a sweep's first firing is within
:data:`FIRST_FIRING_WINDOW_MS` of its timestamp (0.2 to 6.6 ms in AV2). Rows far from the start
of a sweep are placed in the right revolution by following the row order.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ncore_convert.transforms.geometry import Trajectory
from ncore_convert.transforms.lidar import vlp32c
from ncore_convert.transforms.lidar.rays import decompensate

PERIOD_NS = 100_000_000  #: trigger grid and nominal revolution
PERIOD_MS = PERIOD_NS / 1e6
RATE_DEG_PER_MS = 360.0 / PERIOD_MS  #: nominal spin rate
#: Image timestamps minus the unit's crossing of the camera axis, measured on the real AV2 sample
#: (up_lidar 0.09 ms, down_lidar 0.12 ms; the only real data with per-point times at hand).
TRIGGER_DELAY_MS = 0.1
#: A sweep's first firing lies within this many ms after (or before) its timestamp.
FIRST_FIRING_WINDOW_MS = (-25.0, 25.0)
#: Reconstructed firing times are kept within this range of the sweep timestamp: the first firing
#: window, then one revolution and a bit (real AV2 sweeps span 0.2 to 106.1 ms).
SWEEP_SPAN_MS = (FIRST_FIRING_WINDOW_MS[0], FIRST_FIRING_WINDOW_MS[1] + 110.0)
#: Phases within this many ns are one trigger phase (image timestamps sit exactly on the grid).
PHASE_TOLERANCE_NS = 20_000
#: A phase is a trigger phase if it recurs in at least this share of the periods spanned.
MIN_PHASE_SHARE = 0.3
#: Rows per block for the row-order revolution tracking.
BLOCK_ROWS = 32


class TimingError(ValueError):
    """The data do not allow reconstructing firing times (no trigger grid, too few triggers)."""


class TriggerGrid(NamedTuple):
    """The camera-trigger grid: a reference time and the phases that recur every period."""

    epoch_ns: int  #: time origin of the grid
    phases_ns: np.ndarray  #: sorted distinct phases, ns within one period after the epoch, int64 [P]


def trigger_phases_ns(times_ns: np.ndarray, period_ns: int = PERIOD_NS) -> TriggerGrid:
    """The recurring phases of a set of timestamps: camera triggers on a fixed grid.

    Args:
        times_ns: candidate trigger times (image and pose timestamps), int64 [N], ns.

    Returns:
        (epoch_ns, phases_ns): a reference time and the sorted distinct phases (ns within one
        period after the epoch) that recur in at least MIN_PHASE_SHARE of the periods. Stray
        timestamps (sweep timestamps, which drift against the grid) are left out.
    """
    times_ns = np.unique(np.asarray(times_ns, dtype=np.int64))
    if len(times_ns) < 2:
        raise TimingError("fewer than two trigger timestamps")
    epoch = int(times_ns[0])
    phase = (times_ns - epoch) % period_ns
    periods = max(1, int((times_ns[-1] - times_ns[0]) // period_ns))
    bins = np.round(phase / PHASE_TOLERANCE_NS).astype(np.int64) % (period_ns // PHASE_TOLERANCE_NS)
    values, counts = np.unique(bins, return_counts=True)
    keep = values[counts >= max(2, MIN_PHASE_SHARE * periods)]
    if len(keep) == 0:
        raise TimingError(f"no timestamps recur on a {period_ns / 1e6:g} ms grid (no camera triggers)")
    centers = keep * PHASE_TOLERANCE_NS  # medians taken around each bin's centre, across the period wrap
    phases = [
        c + np.median((phase[bins == b] - c + period_ns / 2) % period_ns - period_ns / 2)
        for b, c in zip(keep, centers, strict=True)
    ]
    return TriggerGrid(epoch, np.sort(np.asarray(phases) % period_ns))


@dataclass(frozen=True)
class RotationKnots:
    """One unit's periodic rotation: its firing azimuth at trigger times.

    Attributes:
        epoch_ns: time origin of the grid, ns.
        times_ms: knot times within one period after the epoch, sorted, float64 [K], ms.
        azimuth_deg: firing azimuth at each knot, own frame, unwrapped, float64 [K], degrees.
        spin: +1 if the azimuth increases with time, -1 if it decreases.
        residual_ms: RMS distance of the knots from a uniform rotation at the nominal rate, ms.
        first_firing_ms: median time of the sweeps' first firing after their timestamps (set by
            :func:`unit_rotation`), ms.
    """

    epoch_ns: int
    times_ms: np.ndarray
    azimuth_deg: np.ndarray
    spin: int
    residual_ms: float
    first_firing_ms: float = float("nan")

    def phase_ms(self, firing_azimuth_deg: np.ndarray) -> np.ndarray:
        """Time within the period (ms after the epoch grid, [0, 100)) at which the unit fires
        towards each azimuth ([N] degrees, own frame)."""
        turn = self.spin * 360.0
        k_az = self.spin * np.r_[self.azimuth_deg - turn, self.azimuth_deg, self.azimuth_deg + turn]
        k_t = np.r_[self.times_ms - PERIOD_MS, self.times_ms, self.times_ms + PERIOD_MS]
        a0 = self.spin * self.azimuth_deg[0]
        a = a0 + (self.spin * np.asarray(firing_azimuth_deg) - a0) % 360.0
        return np.interp(a, k_az, k_t) % PERIOD_MS


def fit_rotation_knots(
    camera_azimuth_deg: np.ndarray, spin: int, epoch_ns: int, phases_ns: np.ndarray, half_turn: bool = False
) -> RotationKnots:
    """Assign trigger phases to one unit's crossings of the camera axes.

    Args:
        camera_azimuth_deg: each camera's optical axis as an azimuth in the unit's own frame, [C] degrees.
        spin: the unit's spin direction (+1: azimuth increases with time).
        epoch_ns, phases_ns: the trigger grid (see :func:`trigger_phases_ns`).
        half_turn: take the other of the two fits 180° apart (the other unit's triggers).

    Returns:
        The knots: each camera's azimuth at the trigger phase its crossing matches best, assuming
        a uniform spin at the nominal rate to match, then TRIGGER_DELAY_MS earlier.
    """
    psi = np.asarray(camera_azimuth_deg, dtype=np.float64)
    phases_ms = np.asarray(phases_ns) / 1e6

    def gaps(a0: np.ndarray) -> np.ndarray:  # [A,C] ms from each predicted crossing to its nearest trigger phase
        t = ((psi[None, :] - a0[:, None]) / (spin * RATE_DEG_PER_MS)) % PERIOD_MS
        d = (t[:, :, None] - phases_ms[None, None, :] + PERIOD_MS / 2) % PERIOD_MS - PERIOD_MS / 2
        return np.abs(d).min(axis=2)

    grid = np.arange(0.0, 360.0, 0.05)
    score = np.minimum(gaps(grid), 1.0).sum(axis=1)
    best = grid[np.argmin(score)]
    if half_turn:
        near = np.abs((grid - best + 180.0) % 360.0 - 180.0) > 90.0  # the other half of the circle
        best = grid[near][np.argmin(score[near])]
    t = ((psi - best) / (spin * RATE_DEG_PER_MS)) % PERIOD_MS
    d = (t[:, None] - phases_ms[None, :] + PERIOD_MS / 2) % PERIOD_MS - PERIOD_MS / 2
    j = np.abs(d).argmin(axis=1)
    residual = float(np.sqrt(np.mean(d[np.arange(len(psi)), j] ** 2)))
    times = (phases_ms[j] - TRIGGER_DELAY_MS) % PERIOD_MS
    order = np.argsort(times)
    azimuth = np.degrees(np.unwrap(np.radians(psi[order])))
    return RotationKnots(epoch_ns, times[order], azimuth, spin, residual)


def spin_direction(firing_azimuth_deg: np.ndarray) -> int:
    """+1 if the azimuth increases along the rows (firing order), else -1 ([N] degrees)."""
    steps = np.diff(np.degrees(np.unwrap(np.radians(firing_azimuth_deg))))
    return 1 if np.median(steps) >= 0 and steps.sum() >= 0 else -1


@dataclass(frozen=True)
class SweepTimes:
    """Reconstructed firing times of one unit's rows and how well they follow the row order.

    Attributes:
        times_ns: absolute firing time per row, int64 [N], ns.
        out_of_order: share of rows more than 0.5 ms earlier than the row before them.
    """

    times_ns: np.ndarray
    out_of_order: float


def firing_times(firing_azimuth_deg: np.ndarray, knots: RotationKnots, sweep_ts_ns: int) -> SweepTimes:
    """Absolute firing time of each row of one unit in one sweep.

    Args:
        firing_azimuth_deg: firing azimuth per row in firing (row) order, own frame, [N] degrees.
        knots: the unit's rotation.
        sweep_ts_ns: the sweep timestamp, ns.

    The time within the period comes from the knots. The revolution of each row follows a smooth
    track of the row order (circular means of blocks of rows, unwrapped), which a few noisy rows
    cannot derail; the first rows are placed within FIRST_FIRING_WINDOW_MS of the sweep timestamp.
    """
    n = len(firing_azimuth_deg)
    if n == 0:
        return SweepTimes(np.zeros(0, dtype=np.int64), 0.0)
    phase_ms = knots.phase_ms(firing_azimuth_deg)
    angle = phase_ms * (2 * np.pi / PERIOD_MS)
    blocks = np.arange(0, n, BLOCK_ROWS)
    mean_angle = np.angle(np.add.reduceat(np.exp(1j * angle), blocks))
    track_ms = np.unwrap(mean_angle) * (PERIOD_MS / (2 * np.pi))
    centers = np.minimum(blocks + BLOCK_ROWS / 2 - 0.5, (blocks + n - 1) / 2)
    track = np.interp(np.arange(n), centers, track_ms)
    rel_ms = phase_ms + PERIOD_MS * np.round((track - phase_ms) / PERIOD_MS)
    # absolute: epoch + rel + whole periods, with the first block inside the window after the timestamp
    start_ms = (sweep_ts_ns - knots.epoch_ns) / 1e6 + FIRST_FIRING_WINDOW_MS[0]
    shift = PERIOD_MS * np.ceil((start_ms - track_ms[0]) / PERIOD_MS)
    times_ns = knots.epoch_ns + np.round((rel_ms + shift) * 1e6).astype(np.int64)
    span_ns = [sweep_ts_ns + int(bound * 1e6) for bound in SWEEP_SPAN_MS]
    times_ns = np.clip(times_ns, *span_ns)  # a wrong hypothesis (unit, spin) must not run off the trajectory
    out_of_order = float(np.mean(np.diff(times_ns) < -500_000)) if n > 1 else 0.0
    return SweepTimes(times_ns, out_of_order)


def firing_azimuth_deg(xyz_sensor_m: np.ndarray, beam: np.ndarray) -> np.ndarray:
    """Firing (column) azimuth of each return: its azimuth in the unit's frame minus its beam's
    azimuth offset. xyz_sensor_m: [N,3] metres, own frame; beam: [N] AV2 beam index; -> [N] degrees."""
    azimuth = np.degrees(np.arctan2(xyz_sensor_m[:, 1], xyz_sensor_m[:, 0]))
    return azimuth - vlp32c.BEAM_AZIMUTH_OFFSET_DEG[beam]


def camera_azimuths_deg(T_sensor_rig: np.ndarray, T_cameras_rig: list[np.ndarray]) -> np.ndarray:
    """Each camera's optical axis (+z) as an azimuth in the lidar's own frame.

    Args:
        T_sensor_rig: lidar-to-rig extrinsic [4,4] (AV2 T_sensor_ego).
        T_cameras_rig: camera-to-rig extrinsics [4,4] each (AV2 ego_SE3_cam, OpenCV camera frame).

    Returns:
        [C] degrees.
    """
    axes = np.stack([T_sensor_rig[:3, :3].T @ T[:3, :3][:, 2] for T in T_cameras_rig])
    return np.degrees(np.arctan2(axes[:, 1], axes[:, 0]))


def reconstruct_times(
    xyz_rig_ref_m: np.ndarray,
    beam: np.ndarray,
    sweep_ts_ns: int,
    knots: RotationKnots,
    T_rig_world: Trajectory,
    T_sensor_rig: np.ndarray,
    iterations: int = 3,
) -> SweepTimes:
    """Firing times of one unit's returns in one sweep, alternating with decompensation.

    The stored points are compensated to the sweep time, which shifts azimuths by the ego motion;
    each pass decompensates with the previous pass's times and maps the new azimuths to times.

    Args:
        xyz_rig_ref_m: the unit's returns in row (firing) order, rig frame at ``sweep_ts_ns``, [N,3] metres.
        beam: AV2 beam index per return, [N].
        T_rig_world: ego trajectory covering the sweep; T_sensor_rig: the unit's extrinsic [4,4].
    """
    times_ns = np.full(len(beam), sweep_ts_ns, dtype=np.int64)
    for _ in range(iterations):
        xyz_sensor = decompensate(xyz_rig_ref_m, times_ns, sweep_ts_ns, T_rig_world, T_sensor_rig)
        result = firing_times(firing_azimuth_deg(xyz_sensor, beam), knots, sweep_ts_ns)
        times_ns = result.times_ns
    return result


def unit_rotation(
    camera_azimuth_deg: np.ndarray,
    sweeps: list[tuple[np.ndarray, np.ndarray, int]],
    trigger_grid: TriggerGrid,
    T_rig_world: Trajectory,
    T_sensor_rig: np.ndarray,
) -> RotationKnots:
    """One unit's rotation knots, from the trigger grid and a few of its sweeps.

    Args:
        camera_azimuth_deg: camera axes in the unit's frame, [C] degrees (:func:`camera_azimuths_deg`).
        sweeps: (xyz_rig_ref_m [N,3], beam [N], sweep_ts_ns) of the unit's returns in row order.
        trigger_grid: from :func:`trigger_phases_ns`.

    The spin direction is the majority over the sweeps; of the two fits 180° apart, the one that
    puts the sweeps' first firings within FIRST_FIRING_WINDOW_MS of their timestamps is kept (or,
    if neither does, the nearer one: see :func:`check_first_firing`).
    """
    # azimuths with every return at the sweep time: the first pass of reconstruct_times
    static = [
        (
            firing_azimuth_deg(decompensate(xyz, np.full(len(b), sweep_ns), sweep_ns, T_rig_world, T_sensor_rig), b),
            sweep_ns,
        )
        for xyz, b, sweep_ns in sweeps
        if len(b)
    ]
    if not any(len(az) > BLOCK_ROWS for az, _ in static):
        raise TimingError("no sweep with enough returns to find the spin direction")
    spin = 1 if sum(spin_direction(az) for az, _ in static if len(az) > BLOCK_ROWS) >= 0 else -1
    epoch, phases = trigger_grid.epoch_ns, trigger_grid.phases_ns
    fits = []
    for half_turn in (False, True):
        knots = fit_rotation_knots(camera_azimuth_deg, spin, epoch, phases, half_turn=half_turn)
        first_ms = [(firing_times(az, knots, sweep_ns).times_ns[0] - sweep_ns) / 1e6 for az, sweep_ns in static]
        fits.append(dataclasses.replace(knots, first_firing_ms=float(np.median(first_ms))))
    center = sum(FIRST_FIRING_WINDOW_MS) / 2
    return min(fits, key=lambda k: abs(k.first_firing_ms - center))


def check_first_firing(knots: RotationKnots) -> None:
    """Raise TimingError unless the sweeps' first firings fall within FIRST_FIRING_WINDOW_MS."""
    lo, hi = FIRST_FIRING_WINDOW_MS
    if not lo <= knots.first_firing_ms < hi:
        raise TimingError(
            f"the camera triggers put the first firing {knots.first_firing_ms:.1f} ms after the sweep"
            f" timestamp, outside [{lo:g}, {hi:g}) ms"
        )
