"""CARLA (OPV2V, V2XSet) frames to NCore's right-handed frames: pure, vectorised numpy.

CARLA's world and sensor frames are left-handed: x forward, y right, z up, with poses written as
``[x, y, z, roll, yaw, pitch]`` in metres and degrees. Mirroring y, ``S = diag(1, -1, 1)``, turns
them into right-handed frames (x forward, y left, z up), which is what NCore's ``rig``, ``world``
and sensor frames are:
- a pose (a left-handed ``T_x_world``, frame x -> world) becomes ``S · T · S``;
- a point or direction becomes ``S · p`` (``(x, -y, z)``);
- a camera's UE4 axes (x along the optical axis, y right, z up) relate to OpenCV axes (x right,
  y down, z along the optical axis) by ``p_ue4 = M_UE4_FROM_CV · p_cv``, so the right-handed
  world pose of a camera in OpenCV axes is ``S · T_cam · M_UE4_FROM_CV``.
"""

from __future__ import annotations

import numpy as np

#: The y mirror between CARLA's left-handed frames and right-handed ones, [4,4].
S = np.diag([1.0, -1.0, 1.0, 1.0])
#: OpenCV camera axes expressed in UE4 camera axes: x_ue = z_cv, y_ue = x_cv, z_ue = -y_cv, [4,4].
M_UE4_FROM_CV = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def carla_pose_matrix(pose: np.ndarray) -> np.ndarray:
    """CARLA ``Transform.get_matrix()`` (OpenCOOD ``x_to_world``): the left-handed ``T_x_world``.

    Args:
        pose: ``[x, y, z, roll, yaw, pitch]`` in metres and degrees, [6] or [N,6].

    Returns:
        [4,4] or [N,4,4] float64, maps points of the posed (left-handed) frame to the CARLA world.
    """
    pose = np.asarray(pose, dtype=np.float64)
    single = pose.ndim == 1
    pose = np.atleast_2d(pose)
    roll, yaw, pitch = np.radians(pose[:, 3]), np.radians(pose[:, 4]), np.radians(pose[:, 5])
    cr, sr, cy, sy, cp, sp = np.cos(roll), np.sin(roll), np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    T = np.tile(np.eye(4), (len(pose), 1, 1))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 2] = cp * cy, cy * sp * sr - sy * cr, -cy * sp * cr - sy * sr
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, -sy * sp * cr + cy * sr
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2] = sp, -cp * sr, cp * cr
    T[:, :3, 3] = pose[:, :3]
    return T[0] if single else T


def carla_pose_from_matrix(T: np.ndarray) -> np.ndarray:
    """The CARLA pose ``[x, y, z, roll, yaw, pitch]`` (metres, degrees; [6] or [N,6]) of a
    left-handed ``T_x_world`` ([4,4] or [N,4,4]): the inverse of :func:`carla_pose_matrix`, with
    pitch in [-90, 90] and roll and yaw in (-180, 180]."""
    T = np.asarray(T, dtype=np.float64)
    single = T.ndim == 2
    T = T.reshape(-1, 4, 4)
    pitch = np.degrees(np.arcsin(np.clip(T[:, 2, 0], -1.0, 1.0)))
    yaw = np.degrees(np.arctan2(T[:, 1, 0], T[:, 0, 0]))
    roll = np.degrees(np.arctan2(-T[:, 2, 1], T[:, 2, 2]))
    pose = np.concatenate([T[:, :3, 3], np.stack([roll, yaw, pitch], axis=1)], axis=1)
    return pose[0] if single else pose


def mirror_transform(T_carla: np.ndarray) -> np.ndarray:
    """A left-handed CARLA transform ([...,4,4]) as the right-handed one: ``S · T · S``."""
    return S @ T_carla @ S


def right_handed_pose(pose: np.ndarray) -> np.ndarray:
    """The right-handed ``T_x_world`` of a CARLA pose ``[x, y, z, roll, yaw, pitch]`` ([6] or [N,6])."""
    return mirror_transform(carla_pose_matrix(pose))


def opencv_camera_pose(cords: np.ndarray) -> np.ndarray:
    """The right-handed ``T_camera_world`` of a CARLA camera in OpenCV axes, from its ``cords`` pose
    ([6] or [N,6])."""
    return S @ carla_pose_matrix(cords) @ M_UE4_FROM_CV


def points_right_handed(xyz_carla: np.ndarray) -> np.ndarray:
    """Points or directions [N,3] from a CARLA (left-handed) frame to its right-handed mirror."""
    out = np.array(xyz_carla, copy=True)
    out[..., 1] = -out[..., 1]
    return out


def boxes_world_right_handed(
    location: np.ndarray, angle: np.ndarray, center: np.ndarray, extent: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """CARLA actor bounding boxes as right-handed world poses of the box centres, and full sizes.

    Args:
        location: actor origins [M,3]; angle: actor (roll, yaw, pitch) [M,3], degrees; center: the
            box-centre offset in the actor frame [M,3]; extent: half length, width, height [M,3].
            All in the CARLA (left-handed) world, metres.

    Returns:
        T_box_world [M,4,4] (right-handed; box x forward, y left, z up) and (length, width,
        height) [M,3] = 2 * extent. The centre is ``location + R(angle) · center``.
    """
    T = carla_pose_matrix(np.concatenate([location, angle], axis=1))
    T[:, :3, 3] += np.einsum("mij,mj->mi", T[:, :3, :3], center)
    return mirror_transform(T), 2.0 * np.asarray(extent, dtype=np.float64)
