"""The synthetic ego body in the AV2 / TbV cameras that see it, and camera pictures around it.

Three ring cameras see the ego vehicle, as on the real car: ``ring_front_center`` the hood along
the bottom of its portrait image, ``ring_rear_left`` / ``ring_rear_right`` the rear corner of the
body (trunk lid and flank). The body is an outline in the ego frame (metres, x forward, y left,
z up from the rear-axle origin), projected with each camera's own calibration; the true mask is
every pixel below the projected outline, so it follows the mounting exactly.

Pictures: the world is a road-like gradient with large random blobs that change from picture to
picture (the world moving past); the body keeps its paint texture and only its lighting changes a
little between pictures, as real paint does under changing light.
"""

from __future__ import annotations

import io

import numpy as np
import PIL.Image
import PIL.ImageDraw

#: The cameras that see the ego body.
EGO_CAMERAS = ("ring_front_center", "ring_rear_left", "ring_rear_right")
#: Pictures per camera that the frames cycle through at random (each a different "world").
N_PICTURES = 6
#: Paint brightness of the body varies by this factor between pictures (lighting).
LIGHTING = (0.95, 1.05)


def body_outline_m(camera: str) -> np.ndarray:
    """The visible top outline of the ego body for ``camera``, ego frame, metres [K,3], ordered so
    that the region below it in the image is the body."""
    s = np.linspace(-1.0, 1.0, 41)
    if camera == "ring_front_center":  # hood: sides from near the windscreen, front edge bulging up
        front = np.stack([2.25 - 0.25 * s**2, -0.95 * s, 1.12 - 0.08 * s**2], axis=1)
        left = np.stack([np.linspace(1.85, 2.0, 8), np.full(8, 0.95), np.linspace(1.0, 1.04, 8)], axis=1)
        return np.concatenate([left, front, left[::-1] * [1, -1, 1]])
    side = 1.0 if camera == "ring_rear_left" else -1.0
    flank = np.stack([np.linspace(1.0, -0.9, 30), np.full(30, 0.98 * side), np.full(30, 0.75)], axis=1)
    rear = np.stack([np.full(41, -0.9), 0.98 * side * -s, np.full(41, 0.75)], axis=1)
    return np.concatenate([flank, rear])


def true_mask(camera: str, T_camera_ego: np.ndarray, focal_px: float, cx_px: float, cy_px: float,
              width: int, height: int) -> np.ndarray:  # fmt: skip
    """The ego pixels of ``camera`` (bool [H,W]): below the projected body outline. ``T_camera_ego``
    maps camera points (OpenCV axes) to the ego frame; the principal point is av2's (pixel centres
    at integers)."""
    mask = PIL.Image.new("L", (width, height), 0)
    if camera not in EGO_CAMERAS:
        return np.zeros((height, width), dtype=bool)
    T_ego_camera = np.linalg.inv(T_camera_ego)
    xyz = body_outline_m(camera) @ T_ego_camera[:3, :3].T + T_ego_camera[:3, 3]
    xyz = xyz[xyz[:, 2] > 0.05]
    u = np.clip(focal_px * xyz[:, 0] / xyz[:, 2] + cx_px, -4 * width, 5 * width)
    v = np.clip(focal_px * xyz[:, 1] / xyz[:, 2] + cy_px, -4 * height, 5 * height)
    polygon = [(float(a), float(b)) for a, b in zip(u, v, strict=True)]
    polygon += [(float(u[-1]), 2.0 * height), (float(u[0]), 2.0 * height)]
    PIL.ImageDraw.Draw(mask).polygon(polygon, fill=255)  # PIL and av2 both put pixel centres at integers
    return np.asarray(mask) > 0


def _smooth_field(rng: np.random.Generator, width: int, height: int, cell_px: int) -> np.ndarray:
    """A random field in [-1, 1] that varies over about ``cell_px`` pixels, float32 [H,W]."""
    coarse = rng.uniform(-1, 1, (height // cell_px + 2, width // cell_px + 2)).astype(np.float32)
    image = PIL.Image.fromarray(coarse, mode="F").resize((width, height), PIL.Image.BILINEAR)
    return np.clip(np.asarray(image), -1, 1)


def pictures(rng: np.random.Generator, width: int, height: int, mask: np.ndarray | None, parked: bool) -> list[bytes]:
    """``N_PICTURES`` JPEGs of one camera (~0.45 MB at AV2 resolutions): a different world in each
    (the same one when ``parked``), the body (``mask``, or none) painted with a fixed texture under
    slightly different light."""
    v = np.linspace(0, 1, height, dtype=np.float32)[:, None]
    road = np.where(v < 0.45, 150 + 80 * v, 90 - 40 * (v - 0.45))
    world_seed = int(rng.integers(2**62))
    if mask is not None:
        paint = 70 + 25 * _smooth_field(rng, width, height, 64) + 40 * np.clip(1.2 - v, 0, 1)
    out = []
    for _ in range(N_PICTURES):
        world_rng = np.random.default_rng(world_seed) if parked else rng  # parked: the same world each time
        blobs = 45 * _smooth_field(world_rng, width, height, 48) + 20 * _smooth_field(world_rng, width, height, 9)
        noise = rng.standard_normal((height, width), dtype=np.float32)
        grey = road + blobs + 5 * noise
        if mask is not None:
            light = rng.uniform(*LIGHTING)
            grey = np.where(mask, paint * light + 2 * noise, grey)
        rgb = np.clip(grey[..., None] + np.array([0, 5, 12], dtype=np.float32) * v[..., None], 0, 255)
        buf = io.BytesIO()
        PIL.Image.fromarray(rgb.astype(np.uint8)).save(buf, format="JPEG", quality=80)
        out.append(buf.getvalue())
    return out
