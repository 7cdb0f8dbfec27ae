"""Rigid-body geometry shared by all sources and transforms.

Conventions: ``T_a_b`` is a 4x4 SE(3) matrix mapping points in frame ``a`` to frame ``b``
(``p_b = R p_a + t``), the NCore naming. Dataset-side names like av2's ``city_SE3_ego`` are the
same thing read right to left (``city_SE3_ego == T_ego_city``). Angles are radians, lengths metres,
and times microseconds unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from ncore_convert.transforms.timebase import NS_PER_US


def se3_from_quat_wxyz(quat_wxyz: npt.ArrayLike, translation_m: npt.ArrayLike) -> np.ndarray:
    """Build SE(3) matrices from scalar-first quaternions and translations.

    Args:
        quat_wxyz: rotation quaternions (w, x, y, z), not necessarily with w >= 0, shape [N,4] or [4].
        translation_m: translations in metres, shape [N,3] or [3].

    Returns:
        float64 matrices, shape [N,4,4] (or [4,4] for single inputs).
    """
    quat_wxyz = np.asarray(quat_wxyz, dtype=np.float64)
    translation_m = np.asarray(translation_m, dtype=np.float64)
    single = quat_wxyz.ndim == 1
    quat_wxyz = np.atleast_2d(quat_wxyz)
    T = np.tile(np.eye(4), (len(quat_wxyz), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(quat_wxyz, scalar_first=True).as_matrix()
    T[:, :3, 3] = np.atleast_2d(translation_m)
    return T[0] if single else T


def quat_wxyz_from_se3(T: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternions of the rotation part of SE(3) matrices [...,4,4] -> [...,4]."""
    return Rotation.from_matrix(T[..., :3, :3]).as_quat(scalar_first=True)


def invert_se3(T: np.ndarray) -> np.ndarray:
    """Invert SE(3) matrices of shape [...,4,4] in closed form (same dtype)."""
    R_t = np.swapaxes(T[..., :3, :3], -1, -2)
    T_inv = np.zeros_like(T)
    T_inv[..., :3, :3] = R_t
    T_inv[..., :3, 3] = -np.einsum("...ij,...j->...i", R_t, T[..., :3, 3])
    T_inv[..., 3, 3] = 1.0
    return T_inv


def transform_points(T_a_b: np.ndarray, xyz_a: np.ndarray) -> np.ndarray:
    """Map points from frame a to frame b.

    Args:
        T_a_b: one transform [4,4], or one per point [N,4,4].
        xyz_a: points in frame a, shape [N,3].

    Returns:
        points in frame b, shape [N,3], in the promoted dtype of the inputs.
    """
    if T_a_b.ndim == 2:
        return xyz_a @ T_a_b[:3, :3].T + T_a_b[:3, 3]
    return np.einsum("nij,nj->ni", T_a_b[:, :3, :3], xyz_a) + T_a_b[:, :3, 3]


def rotation_matrices_from_quats(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrices from unit quaternions stored column-wise: [4,M] (w,x,y,z rows) -> [3,3,M].

    Column-wise (structure-of-arrays) layout keeps every arithmetic step on contiguous rows, which
    is what makes per-firing-time transforms cheap on 100k-point sweeps.
    """
    w, x, y, z = quat_wxyz
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array(
        [
            [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
            [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
            [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
        ]
    )


@dataclass(frozen=True)
class Trajectory:
    """A time-stamped SE(3) trajectory ``T_source_target(t)`` with SLERP/linear interpolation.

    This is the interpolation NCore's pose graph uses (SLERP for rotation, linear for translation),
    so transforms computed here agree with what readers reconstruct. It is vectorised over query
    times: per-point lidar times can be interpolated directly.

    Attributes:
        timestamps_us: strictly increasing sample times, int64 microseconds, shape [N], N >= 2.
        poses: SE(3) samples T_source_target, float64, shape [N,4,4].
    """

    timestamps_us: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        if len(self.timestamps_us) < 2:
            raise ValueError("a trajectory needs at least two poses")
        if np.any(np.diff(self.timestamps_us) <= 0):
            raise ValueError("trajectory timestamps must be strictly increasing")
        t_rel_s = self.relative_seconds(self.timestamps_us * NS_PER_US)  # as query times are computed: exact at knots
        quats = quat_wxyz_from_se3(self.poses)
        # sign-align consecutive quaternions so every segment interpolates along the short arc
        flips = np.cumprod(np.where(np.einsum("ij,ij->i", quats[1:], quats[:-1]) < 0, -1.0, 1.0))
        quats[1:] *= flips[:, None]
        # per-segment slerp constants: arc angle and 1/sin(angle) (0 marks a degenerate, lerp segment)
        theta = np.arccos(np.clip(np.einsum("ij,ij->i", quats[1:], quats[:-1]), -1.0, 1.0))
        sin_theta = np.sin(theta)
        inv_sin = np.where(sin_theta > 1e-12, 1.0 / np.where(sin_theta > 1e-12, sin_theta, 1.0), 0.0)
        # one row per segment quantity, one column per segment: a single gather fetches them all
        dt_s = np.diff(t_rel_s)
        segments = np.concatenate(
            [
                t_rel_s[None, :-1],  # 0: segment start (s)
                (1.0 / dt_s)[None],  # 1: 1 / segment length
                theta[None],  # 2: slerp arc angle
                inv_sin[None],  # 3: 1 / sin(arc), 0 for a degenerate (lerp) segment
                quats[:-1].T,  # 4..7: start quaternion
                quats[1:].T,  # 8..11: end quaternion
                self.poses[:-1, :3, 3].T,  # 12..14: start translation
                np.diff(self.poses[:, :3, 3], axis=0).T,  # 15..17: translation change
            ]
        )
        object.__setattr__(self, "_t_rel_s", t_rel_s)
        object.__setattr__(self, "_segments", segments)
        object.__setattr__(self, "_has_lerp_segments", bool(np.any(inv_sin == 0.0)))

    @property
    def start_us(self) -> int:
        return int(self.timestamps_us[0])

    @property
    def end_us(self) -> int:
        return int(self.timestamps_us[-1])

    def interpolate_columns(self, t_rel_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotation and translation at times given in seconds relative to ``timestamps_us[0]``.

        Args:
            t_rel_s: float64 [M]. Seconds-relative input lets callers pass sub-microsecond times
                (ns-exact lidar firing times) without float64 precision loss on epoch timestamps.

        Returns:
            quat_wxyz [4,M] (unit quaternions, column-wise) and translation_m [3,M].

        Raises ValueError outside the sampled range (no extrapolation, as in NCore).
        """
        t_rel_s = np.asarray(t_rel_s, dtype=np.float64)
        knots = self._t_rel_s
        if t_rel_s.size and (t_rel_s.min() < 0.0 or t_rel_s.max() > knots[-1]):
            raise ValueError("interpolation time outside the trajectory")
        i = np.searchsorted(knots, t_rel_s, side="right") - 1
        np.clip(i, 0, len(knots) - 2, out=i)
        seg = _gather_columns(self._segments, i)
        alpha = (t_rel_s - seg[0]) * seg[1]
        theta, inv_sin = seg[2], seg[3]
        w1 = np.sin(alpha * theta) * inv_sin
        w0 = np.sin(theta - alpha * theta) * inv_sin
        if self._has_lerp_segments:
            lerp = inv_sin == 0.0
            w0[lerp], w1[lerp] = 1.0 - alpha[lerp], alpha[lerp]
        quat = w0 * seg[4:8] + w1 * seg[8:12]
        translation = seg[12:15] + alpha * seg[15:18]
        return quat, translation

    def interpolate(self, t_rel_s: np.ndarray) -> np.ndarray:
        """Poses [M,4,4] at times in seconds relative to ``timestamps_us[0]`` (float64 [M])."""
        quat, translation = self.interpolate_columns(t_rel_s)
        out = np.zeros((quat.shape[1], 4, 4))
        out[:, :3, :3] = np.moveaxis(rotation_matrices_from_quats(quat), -1, 0)
        out[:, :3, 3] = translation.T
        out[:, 3, 3] = 1.0
        return out

    def positions_at(self, point_source_m: np.ndarray, timestamps_us: np.ndarray, knots: int = 11) -> np.ndarray:
        """Where a point fixed in the source frame (``point_source_m`` [3]: a lidar's mount in the rig)
        was at each of ``timestamps_us`` (µs, [N]), target frame, float64 [N,3]: the pose at ``knots``
        times spread over them, linear between (a lidar sweep's 0.1 s is one gentle arc)."""
        timestamps_us = np.asarray(timestamps_us)
        if not len(timestamps_us):
            return np.zeros((0, 3))
        knots_us = np.linspace(float(np.min(timestamps_us)), float(np.max(timestamps_us)), knots)
        T = self.interpolate(self.relative_seconds(np.round(knots_us).astype(np.int64) * NS_PER_US))
        at_knots = T[:, :3, :3] @ np.asarray(point_source_m, np.float64) + T[:, :3, 3]
        return np.stack([np.interp(timestamps_us, knots_us, at_knots[:, a]) for a in range(3)], axis=1)

    def relative_seconds(self, times_ns: np.ndarray) -> np.ndarray:
        """Absolute int64 ns times [M] -> float64 seconds relative to the first sample."""
        return (np.asarray(times_ns, dtype=np.int64) - np.int64(self.start_us) * NS_PER_US).astype(np.float64) * 1e-9

    def extended(self, start_us: int, end_us: int) -> Trajectory:
        """Extend to cover [start_us, end_us] with constant-velocity end segments.

        Velocities (linear and angular) are taken from the first/last two samples. Returns self if
        already covered.
        """
        ts, poses = self.timestamps_us, self.poses
        if start_us < ts[0]:
            head = _constant_velocity_pose(poses[1], poses[0], ts[1] - ts[0], ts[0] - start_us)
            ts, poses = np.concatenate([[start_us], ts]), np.concatenate([head[None], poses])
        if end_us > ts[-1]:
            tail = _constant_velocity_pose(poses[-2], poses[-1], ts[-1] - ts[-2], end_us - ts[-1])
            ts, poses = np.concatenate([ts, [end_us]]), np.concatenate([poses, tail[None]])
        if ts is self.timestamps_us:
            return self
        return Trajectory(ts.astype(np.int64), poses)


def sorted_run_starts(values: np.ndarray) -> np.ndarray | None:
    """Start index of each run of equal values in a non-decreasing array [N] (None if unsorted or empty).

    Lidar firing times and their trajectory segments are sorted, so per-run work replaces general
    gathers and sorts.
    """
    if len(values) == 0 or np.any(values[1:] < values[:-1]):
        return None
    return np.flatnonzero(np.concatenate([[True], values[1:] != values[:-1]]))


def _gather_columns(table: np.ndarray, index: np.ndarray) -> np.ndarray:
    """``table[:, index]`` for a [R,K] table; sorted indices (lidar times) are expanded run by run,
    which is several times cheaper than a general gather."""
    starts = sorted_run_starts(index)
    if starts is None:
        return table.take(index, axis=1)
    return np.repeat(table[:, index[starts]], np.diff(np.append(starts, len(index))), axis=1)


def _constant_velocity_pose(T_prev: np.ndarray, T_last: np.ndarray, dt_us: int, ahead_us: int) -> np.ndarray:
    """Continue the motion T_prev -> T_last (over dt_us) for ahead_us further microseconds."""
    scale = float(ahead_us) / float(dt_us)
    delta = Rotation.from_matrix(T_last[:3, :3] @ T_prev[:3, :3].T).as_rotvec() * scale
    out = np.eye(4)
    out[:3, :3] = Rotation.from_rotvec(delta).as_matrix() @ T_last[:3, :3]
    out[:3, 3] = T_last[:3, 3] + (T_last[:3, 3] - T_prev[:3, 3]) * scale
    return out


#: A one-sample trajectory's second pose comes this long after the first: NCore's time quantum (µs).
ONE_TICK_STEP_US = 1


def one_tick_trajectory(timestamp_us: int, T_rig_world: np.ndarray, speed_mps: float) -> tuple[np.ndarray, np.ndarray]:
    """The two-pose trajectory NCore needs for a rig measured at a single instant.

    NCore interpolates dynamic poses, so it stores at least two. The measured pose is kept at
    ``timestamp_us``; a second one follows :data:`ONE_TICK_STEP_US` later, moved by the measured
    speed along the rig's x axis (forward), so no sample lies between them and a velocity derived
    from the two is the measured one (zero for a parked vehicle or infrastructure, and where the
    speed is unknown, NaN).

    Args:
        timestamp_us: the instant, µs.
        T_rig_world: rig -> world at that instant [4,4].
        speed_mps: forward speed, m/s.

    Returns:
        timestamps_us int64 [2] and T_rig_world [2,4,4].
    """
    step_m = 0.0 if not np.isfinite(speed_mps) else float(speed_mps) * ONE_TICK_STEP_US * 1e-6
    after = T_rig_world.copy()
    after[:3, 3] += T_rig_world[:3, 0] * step_m
    times = np.array([timestamp_us, timestamp_us + ONE_TICK_STEP_US], dtype=np.int64)
    return times, np.stack([T_rig_world, after])


def euler_xyz_from_rotation(R: np.ndarray) -> np.ndarray:
    """Extrinsic x-y-z Euler angles (NCore BBox3 ``rot``, R = Rz Ry Rx) of rotation matrices [N,3,3] -> [N,3]."""
    return Rotation.from_matrix(R).as_euler("xyz")


def rigid_mean(T: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Mean of samples of one rigid transform (e.g. an extrinsic measured every frame).

    Args:
        T: SE(3) samples [N,4,4] of the same transform.

    Returns:
        the mean [4,4] (median translation, chordal mean rotation), and the largest deviation of a
        sample from it: translation (m) and rotation angle (degrees).
    """
    mean = np.eye(4)
    rotations = Rotation.from_matrix(T[:, :3, :3])
    mean_rotation = rotations.mean()
    mean[:3, :3] = mean_rotation.as_matrix()
    mean[:3, 3] = np.median(T[:, :3, 3], axis=0)
    deviation_m = float(np.max(np.linalg.norm(T[:, :3, 3] - mean[:3, 3], axis=1)))
    deviation_deg = float(np.degrees(np.max((mean_rotation.inv() * rotations).magnitude())))
    return mean, deviation_m, deviation_deg
