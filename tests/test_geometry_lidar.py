"""Shared geometry and lidar transforms against independent references (scipy, naive matrix chains)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import naive_compensate
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

from ncore_convert.transforms.geometry import Trajectory, invert_se3, se3_from_quat_wxyz, transform_points
from ncore_convert.transforms.lidar.rays import (
    MIN_RANGE_M,
    beam_elevation_spread_rad,
    decide_unit_split,
    decompensate,
    ray_bundle,
)


def random_trajectory(seed: int, n: int = 40) -> Trajectory:
    rng = np.random.default_rng(seed)
    ts = np.cumsum(rng.integers(1_000, 20_000, n)).astype(np.int64) + 315_966_000_000_000
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    T[:, :3, 3] = rng.normal(scale=50.0, size=(n, 3))
    return Trajectory(ts, T)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_interpolation_matches_scipy_slerp(seed):
    traj = random_trajectory(seed)
    rel = (traj.timestamps_us - traj.timestamps_us[0]) * 1e-6
    rng = np.random.default_rng(seed)
    q = np.concatenate([rng.uniform(0, rel[-1], 300), rel])  # including the knots themselves
    ours = traj.interpolate(q)
    rot_ref = Slerp(rel, Rotation.from_matrix(traj.poses[:, :3, :3]))(q).as_matrix()
    t_ref = np.stack([np.interp(q, rel, traj.poses[:, k, 3]) for k in range(3)], axis=1)
    np.testing.assert_allclose(ours[:, :3, :3], rot_ref, atol=1e-12)
    np.testing.assert_allclose(ours[:, :3, 3], t_ref, atol=1e-9)


def test_interpolation_refuses_to_extrapolate():
    traj = random_trajectory(0)
    with pytest.raises(ValueError):
        traj.interpolate(traj.relative_seconds(np.array([traj.end_us + 1]) * 1000))


def test_constant_velocity_extension_continues_the_motion():
    # straight line at 10 m/s with constant yaw rate 0.2 rad/s, sampled every 10 ms
    ts = np.arange(0, 1_000_001, 10_000, dtype=np.int64)
    t = ts * 1e-6
    T = np.tile(np.eye(4), (len(ts), 1, 1))
    T[:, :3, :3] = Rotation.from_euler("z", 0.2 * t[:, None]).as_matrix()
    T[:, 0, 3] = 10.0 * t
    traj = Trajectory(ts[10:-10], T[10:-10])
    ext = traj.extended(0, int(ts[-1]))
    assert ext.start_us == 0 and ext.end_us == ts[-1]
    np.testing.assert_allclose(
        ext.interpolate(ext.relative_seconds(np.array([0, ts[-1]]) * 1000)), T[[0, -1]], atol=1e-9
    )
    assert traj.extended(traj.start_us, traj.end_us) is traj


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_decompensation_matches_naive_chain_and_inverts(seed):
    rng = np.random.default_rng(seed)
    traj = random_trajectory(seed)
    T_sensor_rig = se3_from_quat_wxyz(
        Rotation.random(random_state=seed + 1).as_quat(scalar_first=True), rng.normal(size=3)
    )
    n = 500
    ref_ns = (traj.start_us + (traj.end_us - traj.start_us) // 2) * 1000
    times_ns = np.sort(rng.integers(traj.start_us * 1000, traj.end_us * 1000, n // 2)).repeat(2)  # paired firings
    xyz = rng.normal(scale=30.0, size=(n, 3))
    out = decompensate(xyz, times_ns, ref_ns, traj, T_sensor_rig)
    T_t = traj.interpolate(traj.relative_seconds(times_ns))
    T_ref = traj.interpolate(traj.relative_seconds(np.array([ref_ns])))[0]
    naive = transform_points(invert_se3(T_sensor_rig)[None] @ invert_se3(T_t) @ T_ref[None], xyz)
    np.testing.assert_allclose(out, naive, atol=1e-9)
    np.testing.assert_allclose(naive_compensate(out, times_ns, ref_ns, traj, T_sensor_rig), xyz, atol=1e-9)
    # unsorted times take the general path and give the same answer
    perm = rng.permutation(n)
    np.testing.assert_allclose(
        decompensate(xyz[perm], times_ns[perm], ref_ns, traj, T_sensor_rig), naive[perm], atol=1e-9
    )


def test_ray_bundle_counts_points_it_cannot_store():
    xyz = np.array([[10.0, 0, 0], [0, 0, 0], [0, 3.0, 4.0], [np.nan, 1, 1], [MIN_RANGE_M / 2, 0, 0]])
    times_ns = np.array([5_000_400, 5_000_900, 5_001_999, 5_002_000, 5_003_000], dtype=np.int64)
    rays = ray_bundle(xyz, times_ns, np.array([0, 10, 255, 7, 9], dtype=np.uint8), frame_start_us=5_000)
    assert len(rays) == 2 and rays.n_zero_range == 2 and rays.n_non_finite == 1
    np.testing.assert_array_equal(rays.source_index, [0, 2])
    np.testing.assert_allclose(rays.direction, [[1, 0, 0], [0, 0.6, 0.8]], atol=1e-7)
    np.testing.assert_allclose(rays.distance_m, [10.0, 5.0])
    np.testing.assert_array_equal(rays.timestamp_us, [5_000, 5_001])
    np.testing.assert_allclose(rays.intensity, [0.0, 1.0])
    np.testing.assert_array_equal(rays.frame_timestamps_us, [5_000, 5_001])


def test_beam_flatness_prefers_the_true_frame():
    rng = np.random.default_rng(0)
    beam = rng.integers(0, 32, 20_000)
    elevation = np.radians(np.linspace(-25, 15, 32))[beam]
    azimuth = rng.uniform(-np.pi, np.pi, len(beam))
    r = rng.uniform(5, 80, len(beam))
    xyz = (
        np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], 1)
        * r[:, None]
    )
    tilted = xyz @ Rotation.from_euler("x", 2.0, degrees=True).as_matrix().T
    assert beam_elevation_spread_rad(xyz, beam) < 1e-6
    assert beam_elevation_spread_rad(tilted, beam) > np.radians(0.5)


def test_unit_split_picks_the_cheaper_assignment():
    split = decide_unit_split({("low", "up"): 0.1, ("high", "down"): 0.1, ("low", "down"): 1.0, ("high", "up"): 1.0})
    assert (split.low_half_unit, split.high_half_unit) == ("up", "down")
    assert split.margin == pytest.approx(10.0)
    split = decide_unit_split({("low", "up"): 1.0, ("high", "down"): 2.0, ("low", "down"): 0.2, ("high", "up"): 0.1})
    assert (split.low_half_unit, split.high_half_unit) == ("down", "up")
    assert split.margin == pytest.approx(10.0)
