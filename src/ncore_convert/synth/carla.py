"""CARLA's conventions as the synthetic OPV2V/V2XSet generator (:mod:`.opencood`) writes them: its
left-handed poses (``[x, y, z, roll, yaw, pitch]``, degrees), its 800x600 cameras in UE4 axes, and
their pictures rendered from the scene (:func:`synth.raycast.render`)."""

from __future__ import annotations

import io

import numpy as np
import PIL.Image
from scipy.spatial.transform import Rotation

from ncore_convert.synth.raycast import render
from ncore_convert.synth.scene import Scene
from ncore_convert.transforms.camera.models import Pinhole

WIDTH, HEIGHT, FOV_DEG = 800, 600, 100.0
FOCAL_PX = float(WIDTH / (2.0 * np.tan(np.radians(FOV_DEG / 2))))
PINHOLE = Pinhole((FOCAL_PX, FOCAL_PX), (WIDTH / 2, HEIGHT / 2), (WIDTH, HEIGHT))  #: CARLA's: centred, square pixels
PILLAR_DIMS_M = (0.8, 0.8, 4.0)
PILLAR_RGB = (255, 0, 0)  #: the pillars' colour: where one's centre projects, its face is the marker
RENDER_STEP = 2  #: cameras are ray-cast at half their resolution, each ray's colour repeated over 2x2 pixels
#: UE4 camera axes (x forward, y right, z up) of the OpenCV ones (x right, y down, z forward)
T_UE4_OPENCV = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
RENDER_RANGE_M = 300.0


def carla_rotation(angles_deg: np.ndarray) -> np.ndarray:
    """CARLA rotation matrices of (roll, yaw, pitch) degrees [...,3]: Rz(yaw)·Ry(-pitch)·Rx(-roll)."""
    a = np.asarray(angles_deg, dtype=np.float64)
    return Rotation.from_euler("ZYX", np.stack([a[..., 1], -a[..., 2], -a[..., 0]], axis=-1), degrees=True).as_matrix()


def carla_pose_matrix(pose: np.ndarray) -> np.ndarray:
    """[x, y, z, roll, yaw, pitch] -> 4x4 T_x_world in CARLA's (left-handed) world."""
    T = np.eye(4)
    T[:3, :3] = carla_rotation(np.asarray(pose[3:6]))
    T[:3, 3] = pose[:3]
    return T


def carla_pose_list(T: np.ndarray) -> list[float]:
    """4x4 CARLA T_x_world -> [x, y, z, roll, yaw, pitch] (degrees)."""
    yaw, neg_pitch, neg_roll = Rotation.from_matrix(T[:3, :3]).as_euler("ZYX", degrees=True)
    return [float(v) for v in (*T[:3, 3], -neg_roll, yaw, -neg_pitch)]


def project_ue4(T_cam_world: np.ndarray, xyz_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CARLA camera projection of world points [M,3]: pixel (u, v) [M,2] (pixel-corner convention,
    principal point at the image centre) and whether each is in front of the camera [M]."""
    p = (xyz_world - T_cam_world[:3, 3]) @ T_cam_world[:3, :3]  # UE4 camera axes
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack(PINHOLE.project(np.stack([p[:, 1], -p[:, 2], p[:, 0]], axis=1)), axis=1)  # OpenCV axes
    return uv, p[:, 0] > 0.5


def render_png(
    scene: Scene, box_rgb: np.ndarray, T_cam_world: np.ndarray, step: int = RENDER_STEP
) -> tuple[bytes, np.ndarray]:
    """An 800x600 PNG of ``scene`` from the CARLA camera ``T_cam_world`` (UE4 axes), flat-shaded with
    the boxes' colours ``box_rgb`` (:func:`synth.raycast.render`, one ray per ``step`` x ``step``
    pixels), and what each pixel shows, int [600,800] (a scene box index, -1 ground, ``SKY``)."""
    image, shows = render(
        scene,
        box_rgb,
        T_cam_world @ T_UE4_OPENCV,
        PINHOLE,
        step,
        max_range_m=RENDER_RANGE_M,
        ground_z_m=0.0,
    )
    out = io.BytesIO()
    PIL.Image.fromarray(image).save(out, format="PNG", compress_level=1)
    return out.getvalue(), shows


def shows_around(shows: np.ndarray, uv_px: np.ndarray, box: int) -> bool:
    """Whether the pixel at ``uv_px`` (u, v) and the 8 around it show scene box ``box`` (``shows``:
    a picture's box index per pixel)."""
    c, r = int(np.floor(uv_px[0])), int(np.floor(uv_px[1]))
    return bool(np.all(shows[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2] == box))
