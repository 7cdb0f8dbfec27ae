"""The ego vehicle's pixels in a camera, estimated from the camera's own images.

The body is rigidly fixed in a camera's image while the world moves through it, so over frames
sampled across a log its pixels barely change (lighting only) while the world's change a lot. On
greyscale frames decoded at reduced resolution:

1. **Motion**: the world must have moved. The median temporal standard deviation of the pixels
   above the horizon must reach ``MIN_WORLD_STD``; otherwise (a parked log, a static scene) the
   camera gets no mask and a warning, because still pixels then say nothing about the body.
2. **Still pixels**: temporal standard deviation below a threshold set from the world's own
   variation (``STILL_FRACTION`` of the median above the horizon, clamped to ``STILL_STD_RANGE``).
3. **Where the body can be** (the calibration): below the horizon by at least ``HORIZON_MARGIN_DEG``
   (the body is below the camera), and connected to the bottom image border (the border that faces
   the car for these level-mounted cameras).
4. **Clean-up**: closing, hole filling and opening; components smaller than ``MIN_FRACTION`` of the
   image are dropped. A camera left with no component does not see the ego: **no** mask, rather than
   speckle.
5. **Plausibility**: a mask covering more than ``MAX_FRACTION`` of the image is rejected (no mask,
   a warning): the body of a car covers at most about a quarter of a ring camera's image (AV2's
   hood about a tenth), so more means the "still" pixels are the scene.
6. The mask is upsampled to the camera's resolution (bilinear, then a threshold at one half).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import PIL.Image
from scipy import ndimage

MIN_WORLD_STD = 4.0  #: grey levels: below this, the world did not move enough to tell the body from it
STILL_FRACTION = 0.3
STILL_STD_RANGE = (4.0, 12.0)  #: grey levels
HORIZON_MARGIN_DEG = 2.0
MIN_FRACTION = 0.005  #: of the image: smaller still regions are speckle, not a body
MAX_FRACTION = 0.30  #: of the image: a larger "body" is the scene standing still
MIN_SAMPLES = 6  #: fewer sampled images than this cannot tell still from moving


@dataclass(frozen=True)
class EgoMaskEstimate:
    """The estimate for one camera.

    Attributes:
        mask: ego pixels at the reduced resolution, bool [h,w]; None when no mask is written.
        decision: ``"mask"``, ``"not seen"`` (no body), or a fallback: ``"too few images"``,
            ``"too little motion"``, ``"implausible coverage"``.
        covered_fraction: the share of the image the mask covers (0 without one).
        still_threshold: the temporal standard deviation below which pixels counted as still.
        world_std: the median temporal standard deviation above the horizon (grey levels).
    """

    mask: np.ndarray | None
    decision: str
    covered_fraction: float
    still_threshold: float
    world_std: float


def below_horizon(
    shape: tuple[int, int], focal_px: tuple[float, float], centre_px: tuple[float, float], R_camera_ego: np.ndarray
) -> np.ndarray:
    """Pixels whose ray points down in the ego frame by more than HORIZON_MARGIN_DEG, bool [h,w].

    Args:
        shape: (h, w) of the reduced image; focal_px, centre_px: its (fx, fy) and principal point
            (pixel-corner convention); R_camera_ego: camera (OpenCV) -> ego rotation [3,3].
    """
    h, w = shape
    u = (np.arange(w) + 0.5 - centre_px[0]) / focal_px[0]
    v = (np.arange(h) + 0.5 - centre_px[1]) / focal_px[1]
    up = R_camera_ego[2]  # the ego z component of a camera-frame direction
    z = up[0] * u[None, :] + up[1] * v[:, None] + up[2]
    norm = np.sqrt(u[None, :] ** 2 + v[:, None] ** 2 + 1.0)
    return z / norm < -np.sin(np.radians(HORIZON_MARGIN_DEG))


def estimate(frames: np.ndarray, allowed: np.ndarray) -> EgoMaskEstimate:
    """Estimate the ego pixels from greyscale frames sampled across a log.

    Args:
        frames: float32 [N,h,w], grey levels 0..255, at reduced resolution.
        allowed: where the body can be (:func:`below_horizon`), bool [h,w].
    """
    if len(frames) < MIN_SAMPLES:
        return EgoMaskEstimate(None, "too few images", 0.0, 0.0, 0.0)
    std = frames.std(axis=0)
    world = ~allowed
    world_std = float(np.median(std[world])) if world.any() else float(np.median(std))
    threshold = float(np.clip(STILL_FRACTION * world_std, *STILL_STD_RANGE))
    if world_std < MIN_WORLD_STD:
        return EgoMaskEstimate(None, "too little motion", 0.0, threshold, world_std)
    candidate = (std < threshold) & allowed
    labels, _ = ndimage.label(candidate)
    touching = np.unique(labels[-1][labels[-1] > 0])
    mask = np.isin(labels, touching)
    mask = ndimage.binary_closing(mask, structure=np.ones((3, 3)), iterations=2, border_value=1)
    mask = ndimage.binary_fill_holes(mask)
    mask = ndimage.binary_opening(mask, structure=np.ones((3, 3)), iterations=1) & allowed
    labels, n = ndimage.label(mask)
    if n:
        sizes = ndimage.sum(mask, labels, index=np.arange(1, n + 1))
        keep = np.flatnonzero(sizes >= MIN_FRACTION * mask.size) + 1
        touching = np.intersect1d(keep, np.unique(labels[-1]))
        mask = np.isin(labels, touching)
    covered = float(mask.mean())
    if covered == 0.0:
        return EgoMaskEstimate(None, "not seen", 0.0, threshold, world_std)
    if covered > MAX_FRACTION:
        return EgoMaskEstimate(None, "implausible coverage", covered, threshold, world_std)
    return EgoMaskEstimate(mask, "mask", covered, threshold, world_std)


def upsample(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """A reduced-resolution mask at the camera's resolution, bool [height,width] (bilinear, then > 1/2)."""
    image = PIL.Image.fromarray(mask.astype(np.uint8) * 255).resize((width, height), PIL.Image.BILINEAR)
    return np.asarray(image) >= 128
