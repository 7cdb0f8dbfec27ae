"""Property-based tests (hypothesis) of the shared geometry: SE(3) composition and inversion,
quaternions and xyz-Euler angles, CARLA's left-handed frames and their right-handed mirrors, and
lidar decompensation followed by recompensation. References are scipy and plain matrix algebra."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from conftest import naive_compensate
from hypothesis import example, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from ncore_convert.transforms.carla import (
    boxes_world_right_handed,
    carla_pose_from_matrix,
    carla_pose_matrix,
    mirror_transform,
    points_right_handed,
    right_handed_pose,
)
from ncore_convert.transforms.geometry import (
    Trajectory,
    euler_xyz_from_rotation,
    invert_se3,
    quat_wxyz_from_se3,
    rotation_matrices_from_quats,
    se3_from_quat_wxyz,
    transform_points,
)
from ncore_convert.transforms.lidar.rays import decompensate

PROPERTY = settings(max_examples=300, deadline=None)

finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
#: quaternions away from zero norm (any sign, not normalised: the readers normalise)
quats = arrays(np.float64, 4, elements=finite).filter(lambda q: np.linalg.norm(q) > 0.1)
translations = arrays(np.float64, 3, elements=st.floats(-1000.0, 1000.0, allow_nan=False))
points = arrays(np.float64, (5, 3), elements=st.floats(-200.0, 200.0, allow_nan=False))
se3 = st.builds(se3_from_quat_wxyz, quats, translations)
angles_deg = st.floats(-360.0, 360.0, allow_nan=False)
carla_poses = st.tuples(*(st.floats(-500.0, 500.0, allow_nan=False),) * 3, angles_deg, angles_deg, angles_deg).map(
    np.array
)


def assert_proper_rigid(T: np.ndarray) -> None:
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert np.isclose(np.linalg.det(R), 1.0)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


@PROPERTY
@given(se3, se3, points)
def test_se3_composition_applies_right_to_left(A, B, p):
    assert_proper_rigid(A @ B)
    np.testing.assert_allclose(
        transform_points(A @ B, p), transform_points(A, transform_points(B, p)), atol=1e-8, rtol=1e-10
    )


@PROPERTY
@given(se3, se3, points)
def test_se3_inversion(A, B, p):
    np.testing.assert_allclose(invert_se3(A) @ A, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(invert_se3(A @ B), invert_se3(B) @ invert_se3(A), atol=1e-8)
    np.testing.assert_allclose(invert_se3(A), np.linalg.inv(A), atol=1e-8)
    np.testing.assert_allclose(transform_points(invert_se3(A), transform_points(A, p)), p, atol=1e-8)
    batch = np.stack([A, B])
    np.testing.assert_allclose(invert_se3(batch), [invert_se3(A), invert_se3(B)], atol=0)


@PROPERTY
@given(quats, translations)
def test_quaternion_to_se3_and_back(q, t):
    T = se3_from_quat_wxyz(q, t)
    assert_proper_rigid(T)
    np.testing.assert_array_equal(T[:3, 3], t)
    unit = q / np.linalg.norm(q)
    back = quat_wxyz_from_se3(T)
    np.testing.assert_allclose(back * np.sign(back @ unit), unit, atol=1e-9)  # q and -q are one rotation
    np.testing.assert_allclose(rotation_matrices_from_quats(unit[:, None])[..., 0], T[:3, :3], atol=1e-12)


@pytest.mark.filterwarnings("ignore:Gimbal lock detected")  # at pitch +-90 deg; the rotation is still exact
@PROPERTY
@given(quats)
def test_xyz_euler_round_trip_through_quaternions(q):
    """NCore's box ``rot`` (extrinsic x-y-z, R = Rz Ry Rx) rebuilds the rotation it came from."""
    R = se3_from_quat_wxyz(q, np.zeros(3))[:3, :3]
    rx, ry, rz = euler_xyz_from_rotation(R[None])[0]
    rebuilt = Rotation.from_euler("z", rz).as_matrix() @ Rotation.from_euler("y", ry).as_matrix()
    rebuilt = rebuilt @ Rotation.from_euler("x", rx).as_matrix()
    # at gimbal lock (pitch +-90 deg) the split between roll and yaw is ill-conditioned: hypothesis found
    # a rotation 1e-15 from it rebuilt to 6e-8, still far below any box's float32 storage
    np.testing.assert_allclose(rebuilt, R, atol=1e-9 if np.cos(ry) > 1e-3 else 1e-7)
    assert -np.pi / 2 - 1e-12 <= ry <= np.pi / 2 + 1e-12


@PROPERTY
@given(carla_poses, carla_poses, points)
def test_carla_mirroring_is_an_involution_and_a_homomorphism(pose_a, pose_b, p):
    """Left-handed -> right-handed twice is the identity; mirroring commutes with composition and
    inversion, so chains of CARLA transforms can be mirrored link by link."""
    A, B = carla_pose_matrix(pose_a), carla_pose_matrix(pose_b)
    np.testing.assert_allclose(mirror_transform(mirror_transform(A)), A, atol=1e-12)
    np.testing.assert_allclose(points_right_handed(points_right_handed(p)), p, atol=0)
    np.testing.assert_allclose(mirror_transform(A @ B), mirror_transform(A) @ mirror_transform(B), atol=1e-8)
    np.testing.assert_allclose(mirror_transform(np.linalg.inv(A)), invert_se3(mirror_transform(A)), atol=1e-8)
    assert_proper_rigid(right_handed_pose(pose_a))
    mirrored = transform_points(mirror_transform(A), points_right_handed(p))
    np.testing.assert_allclose(mirrored, points_right_handed(transform_points(A, p)), atol=1e-8)


@PROPERTY
@given(
    carla_poses,
    arrays(np.float64, 3, elements=st.floats(-2.0, 2.0)),
    arrays(np.float64, 3, elements=st.floats(0.1, 5.0)),
)
def test_carla_box_corners_mirror_onto_the_right_handed_box(pose, center, extent):
    """Each corner of a CARLA box, mirrored, is a corner of the converted right-handed box."""
    world_SE3_box, dims = boxes_world_right_handed(pose[None, :3], pose[None, 3:], center[None], extent[None])
    signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
    corners_carla = transform_points(carla_pose_matrix(pose), center + signs * extent)
    corners_rh = transform_points(world_SE3_box[0], signs * dims[0] / 2)
    np.testing.assert_allclose(
        np.sort(points_right_handed(corners_carla), axis=0), np.sort(corners_rh, axis=0), atol=1e-8
    )


@st.composite
def trajectories(draw) -> Trajectory:
    n = draw(st.integers(2, 6))
    steps_us = draw(arrays(np.int64, n - 1, elements=st.integers(1_000, 200_000)))
    T = np.stack([draw(se3) for _ in range(n)])
    return Trajectory(np.concatenate([[0], np.cumsum(steps_us)]) + 1_000_000, T)


@PROPERTY
@given(trajectories(), se3, points, st.lists(st.floats(0.0, 1.0), min_size=5, max_size=5), st.floats(0.0, 1.0))
def test_decompensation_then_recompensation_is_the_identity(traj, T_sensor_rig, xyz, fractions, ref_fraction):
    span_ns = (traj.end_us - traj.start_us) * 1000
    times_ns = traj.start_us * 1000 + (np.array(fractions) * span_ns).astype(np.int64)
    ref_ns = traj.start_us * 1000 + int(ref_fraction * span_ns)
    sensor = decompensate(xyz, times_ns, ref_ns, traj, T_sensor_rig)
    np.testing.assert_allclose(naive_compensate(sensor, times_ns, ref_ns, traj, T_sensor_rig), xyz, atol=1e-7)
    # a point fired at the reference time only changes frame: rig -> sensor
    at_ref = decompensate(xyz, np.full(len(xyz), ref_ns), ref_ns, traj, T_sensor_rig)
    np.testing.assert_allclose(at_ref, transform_points(invert_se3(T_sensor_rig), xyz), atol=1e-7)


@PROPERTY
@given(carla_poses)
def test_a_carla_pose_is_recovered_from_its_matrix(pose):
    """``carla_pose_from_matrix`` inverts ``carla_pose_matrix``: the same matrix back, and away from
    gimbal lock the same angles (roll and yaw up to whole turns)."""
    recovered = carla_pose_from_matrix(carla_pose_matrix(pose))
    np.testing.assert_allclose(carla_pose_matrix(recovered), carla_pose_matrix(pose), atol=1e-9)
    np.testing.assert_allclose(recovered[:3], pose[:3], rtol=0, atol=0)
    assert -90.0 <= recovered[5] <= 90.0 and np.all(np.abs(recovered[3:5]) <= 180.0)
    if abs(pose[5]) < 89.0:  # else the same rotation may take other angles
        turns = (recovered[3:5] - pose[3:5]) / 360.0
        np.testing.assert_allclose(turns, np.round(turns), atol=1e-9)
        np.testing.assert_allclose(recovered[5], pose[5], atol=1e-9)


#: point clouds as the box tests see them: clustered, spread over hundreds of metres, with a few
#: non-finite or far outlying points (a stray return, a NaN that slipped through)
cloud_coords = st.one_of(
    st.floats(-60.0, 60.0, allow_nan=False),
    st.floats(-1e5, 1e5, allow_nan=False),
    st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 2.0, -2.0]),
)


@PROPERTY
@given(
    arrays(np.float64, st.tuples(st.integers(0, 300), st.just(3)), elements=cloud_coords),
    arrays(np.float64, 3, elements=st.floats(-80.0, 80.0, allow_nan=False)),
    st.floats(0.0, 40.0),
    st.integers(0, 2**32 - 1),
)
# found by CI: centre + reach rounds to 0.0 below the point, |point - centre| rounds to the reach
@example(np.full((1, 3), 3.77431513e-203), np.array([-1 / 3, 0.0, 0.0]), 1 / 3, 0)
def test_the_point_grid_finds_exactly_the_points_within_reach(xyz, centre, reach, seed):
    """``PointGrid.near`` returns every row within ``reach`` of the centre on all three axes and no
    other: the brute-force test over all points (a few centres on points of the cloud itself)."""
    from ncore_convert.transforms.objects.boxes import PointGrid

    grid = PointGrid(xyz)
    rng = np.random.default_rng(seed)
    picked = rng.integers(0, len(xyz), 3) if len(xyz) else []
    centres = [centre, np.array([np.nan, *centre[1:]])]  # a NaN centre (a corrupt box) holds nothing
    centres += [xyz[i] for i in picked if np.isfinite(xyz[i]).all()]
    for c in centres:
        with np.errstate(invalid="ignore"):  # NaN coordinates compare false: the truth's own rule
            truth = np.flatnonzero(np.all(np.abs(xyz - c) <= reach, axis=1))
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no NaN cast into a column index, no overflowing index
            assert sorted(grid.near(c, reach).tolist()) == truth.tolist()
