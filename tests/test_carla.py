"""CARLA frames to right-handed NCore frames, against independent statements of the conventions
and the OpenCOOD documentation sample."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from ncore_convert.transforms.carla import (
    M_UE4_FROM_CV,
    carla_pose_matrix,
    opencv_camera_pose,
    points_right_handed,
    right_handed_pose,
)

angles = st.floats(-360.0, 360.0, allow_nan=False)
coords = st.floats(-500.0, 500.0, allow_nan=False)
poses = st.tuples(coords, coords, coords, angles, angles, angles).map(np.array)


def rot(axis: str, degrees: float) -> np.ndarray:
    return Rotation.from_euler(axis, degrees, degrees=True).as_matrix()


@settings(max_examples=200, deadline=None)
@given(poses)
def test_carla_matrix_is_yaw_then_negated_pitch_and_roll(pose):
    """CARLA's rotation, written in standard form for its left-handed axes: Rz(yaw) Ry(-pitch) Rx(-roll)."""
    x, y, z, roll, yaw, pitch = pose
    expected = rot("z", yaw) @ rot("y", -pitch) @ rot("x", -roll)
    T = carla_pose_matrix(pose)
    np.testing.assert_allclose(T[:3, :3], expected, atol=1e-12)
    np.testing.assert_allclose(T[:3, 3], [x, y, z])


@settings(max_examples=200, deadline=None)
@given(poses, st.tuples(coords, coords, coords).map(np.array))
def test_mirrored_pose_maps_mirrored_points(pose, p_local):
    """Right-handed poses are proper rotations and move mirrored points where CARLA moves the originals."""
    T_rh = right_handed_pose(pose)
    assert np.isclose(np.linalg.det(T_rh[:3, :3]), 1.0)
    np.testing.assert_allclose(T_rh[:3, :3] @ T_rh[:3, :3].T, np.eye(3), atol=1e-12)
    p_world_carla = carla_pose_matrix(pose) @ np.r_[p_local, 1.0]
    p_world_rh = T_rh @ np.r_[points_right_handed(p_local[None])[0], 1.0]
    np.testing.assert_allclose(p_world_rh[:3], points_right_handed(p_world_carla[None, :3])[0], atol=1e-9)


def test_yaw_turns_clockwise_from_above():
    """CARLA yaw +90 deg points forward along +y_carla, which is to the right: -y when right-handed."""
    forward = right_handed_pose(np.array([0, 0, 0, 0, 90.0, 0]))[:3, 0]
    np.testing.assert_allclose(forward, [0, -1, 0], atol=1e-12)


def test_opencv_camera_axes():
    """Camera frames are proper and look where their yaw says: front along +x, camera1 (yaw +100) to the right."""
    front = opencv_camera_pose(np.array([2.5, 0, 1.0, 0, 0, 0]))
    right = opencv_camera_pose(np.array([0, 0.3, 1.8, 0, 100.0, 0]))
    for T in (front, right):
        assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    np.testing.assert_allclose(front[:3, 2], [1, 0, 0], atol=1e-12)  # OpenCV z = optical axis
    np.testing.assert_allclose(front[:3, 1], [0, 0, -1], atol=1e-12)  # OpenCV y = image down
    assert right[1, 2] < -0.9  # looks to the right of a vehicle at yaw 0
    np.testing.assert_allclose(M_UE4_FROM_CV[:3, :3] @ [0, 0, 1], [1, 0, 0])


def test_documented_sample_lidar_to_camera_translation():
    """OpenCOOD's sample YAML: recomputing T_cam<-lidar from lidar_pose and camera0 cords gives the
    documented (-2.991, -0.007, 0.900) m."""
    lidar_pose = np.array([144.33, -388.94, 1.93, 0.078, 174.18, 0.21])
    cords = np.array([141.35, -388.64, 1.04, 0.076, 174.18, 0.207])
    T = np.linalg.inv(carla_pose_matrix(cords)) @ carla_pose_matrix(lidar_pose)
    np.testing.assert_allclose(T[:3, 3], [-2.991, -0.007, 0.900], atol=0.005)
