"""Lidar transforms shared by the converters: pure, vectorised numpy functions.

Frames: ``rig`` is the ego/vehicle frame, ``world`` the sequence-local frame of the ``T_rig_world``
trajectory, ``sensor`` a lidar unit's own frame. Point times are passed as integer nanoseconds so
decompensation uses each point's exact firing time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ncore_convert.transforms.geometry import Trajectory, invert_se3, rotation_matrices_from_quats, sorted_run_starts
from ncore_convert.transforms.timebase import floor_us

#: Points closer than this to the sensor origin have no defined direction and cannot be stored.
MIN_RANGE_M = 1e-3


def unique_times(times_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique values and the inverse index of int64 times [N]; O(N) when already sorted (AV2 sweeps are).

    Lidar points share firing times (paired firings), so poses are interpolated once per time.
    """
    starts = sorted_run_starts(times_ns)
    if starts is None:
        return np.unique(times_ns, return_inverse=True)
    run_begins = np.zeros(len(times_ns), dtype=np.int64)
    run_begins[starts[1:]] = 1
    return times_ns[starts], np.cumsum(run_begins)


def _quat_conj_times(q_wxyz: np.ndarray, p_wxyz: np.ndarray) -> np.ndarray:
    """conj(q_u) * p for column-wise unit quaternions q [4,U] and one quaternion p [4] -> [4,U].

    The product is linear in conj(q), so it is one 4x4 matrix applied to all columns.
    """
    w, x, y, z = p_wxyz
    right = np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])  # q * p = right @ q
    return right @ (q_wxyz * np.array([1.0, -1.0, -1.0, -1.0])[:, None])


def rig_motion_columns(
    T_rig_world: Trajectory, point_times_ns: np.ndarray, ref_time_ns: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rig motion from the reference time to each unique point time (absolute ns, int64 [N]).

    Returns R [3,3,U] and d [3,U] with ``p_rig(t_u) = R[:, :, u] p_rig(ref) + d[:, u]``, i.e.
    ``T_rig_world(t_u)^-1 T_rig_world(ref)`` per unique time (float64, column-wise), and the
    point -> unique-time index [N]. :func:`decompensate` takes it for points that share their times
    (the same rows decompensated into each candidate unit's frame).
    """
    times_ns, inverse = unique_times(point_times_ns)
    quat, t = T_rig_world.interpolate_columns(T_rig_world.relative_seconds(times_ns))
    quat_ref, t_ref = T_rig_world.interpolate_columns(T_rig_world.relative_seconds(np.array([ref_time_ns])))
    R_ref = rotation_matrices_from_quats(quat_ref)[:, :, 0]
    R = rotation_matrices_from_quats(_quat_conj_times(quat, quat_ref[:, 0]))  # R(t)^T R_ref
    w = R_ref.T @ (t_ref - t)  # R(t)^T (t_ref - t) = R(t)^T R_ref R_ref^T (t_ref - t)
    d = np.einsum("iju,ju->iu", R, w)
    return R, d, inverse


def _apply_columns(M: np.ndarray, b: np.ndarray, inverse: np.ndarray, xyz_m: np.ndarray) -> np.ndarray:
    """p'_n = M[:, :, inverse[n]] p_n + b[:, inverse[n]] for points xyz_m [N,3] -> [N,3] (F-ordered).

    M and b are composed in float64; the per-point step runs in the points' dtype. For float32
    points (AV2's float16 coordinates are exact in float32) the result is accurate to ~1e-5 m at
    200 m, far below the source quantisation.
    """
    dtype = xyz_m.dtype
    per_time = np.concatenate([M.reshape(9, -1), b]).astype(dtype)
    per_point = per_time.take(inverse, axis=1)  # one gather of all 12 coefficients
    x, y, z = xyz_m[:, 0], xyz_m[:, 1], xyz_m[:, 2]
    out = np.empty((len(inverse), 3), dtype=dtype, order="F")
    for k in range(3):
        row = per_point[3 * k : 3 * k + 3]
        out[:, k] = row[0] * x + row[1] * y + row[2] * z + per_point[9 + k]
    return out


def decompensate(
    xyz_rig_ref_m: np.ndarray,
    point_times_ns: np.ndarray,
    ref_time_ns: int,
    T_rig_world: Trajectory,
    T_sensor_rig: np.ndarray,
    motion: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Undo ego-motion compensation: rig-frame points at a reference time -> sensor frame at each point's time.

    p_sensor(t_i) = T_sensor_rig^-1 · T_rig_world(t_i)^-1 · T_rig_world(t_ref) · p_rig_ref

    Args:
        xyz_rig_ref_m: points in the rig frame at the reference time, [N,3] float32 or float64, metres.
        point_times_ns: absolute per-point times, int64 [N], nanoseconds.
        ref_time_ns: absolute time the input points are compensated to, nanoseconds.
        T_rig_world: ego trajectory, must cover all times.
        T_sensor_rig: static sensor->rig extrinsic [4,4].
        motion: :func:`rig_motion_columns` of these times and reference, when already computed.

    Returns:
        points in the sensor frame at their own time, [N,3] in the input dtype, metres.
    """
    if len(point_times_ns) == 0:
        return np.zeros((0, 3), dtype=xyz_rig_ref_m.dtype)
    R, d, inverse = motion or rig_motion_columns(T_rig_world, point_times_ns, ref_time_ns)
    T_rig_sensor = invert_se3(T_sensor_rig)
    A, a = T_rig_sensor[:3, :3], T_rig_sensor[:3, 3]
    # sensor(t) <- rig(t) <- rig(ref):  A (R p + d) + a ; A is folded in per time with one matrix product
    M = (A @ R.reshape(3, -1)).reshape(3, 3, -1)
    b = A @ d + a[:, None]
    return _apply_columns(M, b, inverse, xyz_rig_ref_m)


def beam_elevation_spread_rad(xyz_sensor_m: np.ndarray, beam: np.ndarray, n_beams: int = 32) -> float:
    """Flatness score of a spinning lidar: median over beams of the per-beam elevation std (radians).

    A beam traces a constant-elevation cone only in its own sensor frame, so a wrong extrinsic
    inflates this score.

    Args:
        xyz_sensor_m: points in the candidate sensor frame, float64 [N,3].
        beam: beam index per point, int [N], in 0..n_beams-1.
    """
    elevation = np.arctan2(xyz_sensor_m[:, 2], np.hypot(xyz_sensor_m[:, 0], xyz_sensor_m[:, 1]))
    count = np.bincount(beam, minlength=n_beams).astype(np.float64)
    total = np.bincount(beam, weights=elevation, minlength=n_beams)
    total_sq = np.bincount(beam, weights=elevation**2, minlength=n_beams)
    used = count >= 10
    if not np.any(used):
        return float("nan")
    mean = total[used] / count[used]
    var = np.maximum(total_sq[used] / count[used] - mean**2, 0.0)
    return float(np.median(np.sqrt(var)))


#: How far (float32 steps of the distance) :func:`exact_rays` moves a ray's distance off the nearest
#: float32 of its range to make direction x distance reproduce the source point: 8 steps change the
#: direction's length by at most 8 * 2**-23 (1e-6), far inside NCore's unit-norm check (|d|^2 within 1e-4).
EXACT_DISTANCE_STEPS = 8
#: The first steps are tried one at a time on the points still left (most are done by then), the
#: rest at once on the few that remain.
LOOPED_STEPS = 4


def _directions_for(xyz_m: np.ndarray, bits: np.ndarray, distance_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For float32 distances [M], the float32 direction components [M,3] whose correctly rounded
    product with the distance is the source point (``bits``: the float32 point's bits, uint32 [M,3];
    ``xyz_m``: the same values, float64), and which components have one ([M,3] bool). Only the
    float32 nearest the quotient and its two neighbours can round to the point; the neighbours are
    tried only where the nearest misses."""
    r = distance_m.astype(np.float64)[:, None]
    best = (xyz_m / r).astype(np.float32)
    # a float32 x float32 product is exact in float64, so one rounding to float32: IEEE float32 multiplication
    ok = (best.astype(np.float64) * r).astype(np.float32).view(np.uint32) == bits
    rows, cols = np.nonzero(~ok)
    nearest, r_miss, bits_miss = best[rows, cols], r[rows, 0], bits[rows, cols]
    for towards in (np.float32(np.inf), np.float32(-np.inf)):
        candidate = np.nextafter(nearest, towards)
        hit = (candidate.astype(np.float64) * r_miss).astype(np.float32).view(np.uint32) == bits_miss
        best[rows[hit], cols[hit]] = candidate[hit]
        ok[rows[hit], cols[hit]] = True
    return best, ok


def exact_rays(xyz_sensor_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Float32 unit directions and distances whose float32 product is each source point, bit for bit.

    NCore stores a point as a float32 direction and a float32 distance; a reader gets the point back
    as ``direction * distance`` (float32 multiplication, or float64 then rounded to float32: the same
    bits). The nearest float32 of ``x / |x|`` times the nearest float32 of ``|x|`` misses the source
    float32 by one unit in the last place for about half the points. Here each distance is moved by
    up to :data:`EXACT_DISTANCE_STEPS` float32 steps from the nearest to ``|x|`` and each direction
    component chosen among the three float32 next to ``x / distance`` so that every product rounds to
    the source value (the direction stays unit to 1e-6). Some points have no such pair that close to
    unit length: when a component's float32 spacing is coarser than the point's, the products step
    over the point's rounding interval; those keep the nearest pair and are listed.

    Args:
        xyz_sensor_m: finite points [N,3], float32, metres, none at the origin.

    Returns:
        direction float32 [N,3], distance_m float32 [N], and the indices [K] of the points whose
        product is not their source bits (within one unit in the last place).
    """
    xyz_m = xyz_sensor_m.astype(np.float64)
    bits = np.ascontiguousarray(xyz_sensor_m, dtype=np.float32).view(np.uint32)
    nearest_m = np.sqrt(np.einsum("ij,ij->i", xyz_m, xyz_m)).astype(np.float32)
    direction, ok = _directions_for(xyz_m, bits, nearest_m)
    distance_m = nearest_m.copy()
    todo = np.flatnonzero(~ok.all(axis=1))
    steps = [sign * k for k in range(1, EXACT_DISTANCE_STEPS + 1) for sign in (1, -1)]
    for step in steps[:LOOPED_STEPS]:  # about a quarter of the points reach here, fewer each step
        if not len(todo):
            return direction, distance_m, todo
        moved_m = (nearest_m[todo].view(np.int32) + np.int32(step)).view(np.float32)  # positive floats: +1 ulp
        candidate, ok = _directions_for(xyz_m[todo], bits[todo], moved_m)
        done = ok.all(axis=1)
        direction[todo[done]], distance_m[todo[done]] = candidate[done], moved_m[done]
        todo = todo[~done]
    if not len(todo):
        return direction, distance_m, todo
    # the few left (~2 %): every further step at once, the nearest that works kept
    tail = np.array(steps[LOOPED_STEPS:], dtype=np.int32)
    moved_m = (nearest_m[todo, None].view(np.int32) + tail[None, :]).view(np.float32)  # [M,S]
    candidate, ok = _directions_for(
        np.repeat(xyz_m[todo], len(tail), axis=0), np.repeat(bits[todo], len(tail), axis=0), moved_m.reshape(-1)
    )
    good = ok.all(axis=1).reshape(len(todo), len(tail))
    first = np.argmax(good, axis=1)
    found = good[np.arange(len(todo)), first]
    rows = np.flatnonzero(found)
    direction[todo[rows]] = candidate.reshape(len(todo), len(tail), 3)[rows, first[rows]]
    distance_m[todo[rows]] = moved_m[rows, first[rows]]
    return direction, distance_m, todo[~found]


@dataclass(frozen=True)
class RayBundle:
    """Raw per-point-time rays of one lidar frame, ready for NCore.

    Attributes:
        direction: unit directions in the sensor frame at each ray's own time, float32 [N,3].
        distance_m: range along the ray, float32 [N].
        timestamp_us: per-ray time, uint64 [N], microseconds (floor of the ns time).
        intensity: normalised to [0,1], float32 [N].
        frame_timestamps_us: (start, end) of the frame, uint64 [2].
        source_index: index of each ray in the source point array, int64 [N].
        n_zero_range: source points not stored because their range is below ``MIN_RANGE_M``.
        n_non_finite: source points not stored because a coordinate is NaN or infinite.
        inexact: with ``exact``, the rays [K] whose float32 ``direction * distance`` is not the source
            float32 point (:func:`exact_rays`); None without.
    """

    direction: np.ndarray
    distance_m: np.ndarray
    timestamp_us: np.ndarray
    intensity: np.ndarray
    frame_timestamps_us: np.ndarray
    source_index: np.ndarray
    n_zero_range: int
    n_non_finite: int
    inexact: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.distance_m)


def ray_bundle(
    xyz_sensor_m: np.ndarray,
    point_times_ns: np.ndarray,
    intensity: np.ndarray,
    frame_start_us: int,
    exact: bool = False,
) -> RayBundle:
    """Turn sensor-frame points at their own times into a ray bundle.

    Args:
        xyz_sensor_m: [N,3] points in the sensor frame at their own times, metres: float64, or
            float32 with ``exact``.
        point_times_ns: int64 [N] absolute point times (ns).
        intensity: uint8 [N] raw intensity (0..255, stored / 255), or float [N] already in [0, 1].
        frame_start_us: frame start (µs); the frame spans [min(start, first ray), last ray].
        exact: the points are the source's own float32 values (a point cloud file in the sensor
            frame): store each ray so that ``direction * distance`` gives them back bit for bit
            (:func:`exact_rays`).

    Points with a non-finite coordinate or a range below ``MIN_RANGE_M`` have no direction and are
    counted in ``n_non_finite`` / ``n_zero_range`` instead of stored.
    """
    x, y, z = (xyz_sensor_m[:, k].astype(np.float64) for k in range(3))
    distance = np.sqrt(x * x + y * y + z * z)
    finite = np.isfinite(distance)
    keep = finite & (distance >= MIN_RANGE_M)
    index = np.flatnonzero(keep)
    take = slice(None) if len(index) == len(keep) else index  # usually every point is kept: no gathers
    inexact = None
    if exact:
        if xyz_sensor_m.dtype != np.float32:
            raise TypeError("exact rays need the source's float32 points")
        direction, dist, inexact = exact_rays(xyz_sensor_m[take])
    else:
        dist = distance[take]
        inv = 1.0 / dist
        direction = np.empty((len(index), 3), dtype=np.float32)
        for k, c in enumerate((x, y, z)):
            direction[:, k] = c[take] * inv
        dist = dist.astype(np.float32)
    timestamp_us = floor_us(point_times_ns[take]).astype(np.uint64)
    start = frame_start_us if len(index) == 0 else min(frame_start_us, int(timestamp_us.min()))
    end = start if len(index) == 0 else int(timestamp_us.max())
    return RayBundle(
        direction=direction,
        distance_m=dist,
        timestamp_us=timestamp_us,
        intensity=(intensity[take].astype(np.float32) / np.float32(255.0))
        if intensity.dtype == np.uint8
        else intensity[take].astype(np.float32),
        frame_timestamps_us=np.array([start, end], dtype=np.uint64),
        source_index=index,
        n_zero_range=int(np.count_nonzero(finite & ~keep)),
        n_non_finite=int(np.count_nonzero(~finite)),
        inexact=inexact,
    )


@dataclass(frozen=True)
class UnitSplit:
    """Which laser-number half belongs to which unit, decided from the data.

    Attributes:
        low_half_unit: unit that owns the low half (laser_number < 32).
        high_half_unit: unit that owns the high half.
        cost_chosen, cost_rejected: summed beam elevation spread (radians) under each hypothesis.
        margin: cost_rejected / cost_chosen (how decisive the choice is; > 1).
    """

    low_half_unit: str
    high_half_unit: str
    cost_chosen: float
    cost_rejected: float

    @property
    def margin(self) -> float:
        return self.cost_rejected / self.cost_chosen if self.cost_chosen > 0 else float("inf")

    def to_meta(self) -> dict:
        return {
            "method": "per-beam elevation flatness of decompensated points in each candidate sensor frame",
            "laser_number_lt_32": self.low_half_unit,
            "laser_number_ge_32": self.high_half_unit,
            "cost_chosen_deg": float(np.degrees(self.cost_chosen)),
            "cost_rejected_deg": float(np.degrees(self.cost_rejected)),
            "margin": float(self.margin),
        }


def decide_unit_split(spread_rad: dict[tuple[str, str], float]) -> UnitSplit:
    """Choose the half->unit assignment with the lower total beam elevation spread.

    Args:
        spread_rad: flatness score (see :func:`beam_elevation_spread_rad`) for each
            (half, unit) with half in {"low", "high"} and exactly two unit names.
    """
    units = sorted({unit for _, unit in spread_rad})
    if len(units) != 2:
        raise ValueError(f"expected two candidate units, got {units}")
    a, b = units
    cost_ab = spread_rad[("low", a)] + spread_rad[("high", b)]
    cost_ba = spread_rad[("low", b)] + spread_rad[("high", a)]
    if cost_ab <= cost_ba:
        return UnitSplit(a, b, cost_ab, cost_ba)
    return UnitSplit(b, a, cost_ba, cost_ab)
