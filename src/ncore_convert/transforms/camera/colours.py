"""Per-point lidar colours from camera images: the ``rgb`` that 3DGRUT seeds its Gaussians with.

Each point takes the colour of the camera pixel it projects to:

- per camera, in that camera's frame nearest to the point's own time, with the camera's pose at
  the frame's time (the point is where the lidar saw it; a static point is still there);
- only where the pixel shows the world (not the ``ego`` body: ``usable``);
- only if nothing nearer hides it (:mod:`visibility`): a depth buffer of the frame's projected points, kept per cell of
  ``CELL_RAD`` of view angle high and half that wide (more than a lidar's spacing between scan
  lines and between its columns, so an occluder's points fall in every cell it hides), where a point
  is visible when it is at most ``DEPTH_TOLERANCE`` (relative, plus ``DEPTH_TOLERANCE_M``) behind
  the nearest point at or above its row in its cell and the cells left and right of it (the pixels
  at a silhouette show the occluder up to a cell beyond its last points) and in the whole cell
  above (the ground in front of a point lies below it in the picture and does not hide it);
- for points on dynamic objects (``dynamic``), only from a frame within ``DYNAMIC_DT_US`` of the
  point: the object moves, the pixel shows where it was then;
- of the cameras that see a point, the one whose frame is nearest in time.

Points no camera colours get ``FILL_RGB``. Cameras are pinholes (every camera of our datasets is:
AV2 images are undistorted, CARLA's are ideal), as in :mod:`visibility`.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, fields

import numpy as np

from ncore_convert.transforms.camera.visibility import VIEW_MARGIN, CameraView, in_view, visible_pixels

FILL_RGB = (128, 128, 128)  #: the colour of a point no camera sees: neutral grey
DYNAMIC_DT_US = 5_000  #: a point on a moving object takes colour only from a frame this close in time
DECODE_THREADS = 4  #: images are decoded this many at a time


@dataclass(frozen=True)
class ColourFrame(CameraView):
    """One camera image to take colours from: a :class:`CameraView` and its picture.

    Attributes:
        load_rgb: returns the image, uint8 [height,width,3] (at the view's pinhole resolution);
            called only if a point keeps its colour from this frame (decoding is slow), from up to
            ``DECODE_THREADS`` threads.
    """

    load_rgb: Callable[[], np.ndarray] = field(kw_only=True)

    @classmethod
    def of(cls, view: CameraView, load_rgb: Callable[[], np.ndarray]) -> ColourFrame:
        """``view`` with its picture's loader."""
        return cls(**{f.name: getattr(view, f.name) for f in fields(view)}, load_rgb=load_rgb)


def point_colours(
    xyz_world_m: np.ndarray,
    timestamps_us: np.ndarray,
    dynamic: np.ndarray,
    frames: list[ColourFrame],
    spacing_m: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's colour (see the module docstring).

    Args:
        xyz_world_m: the points in a fixed frame, where the lidar saw them, float64 [N,3].
        timestamps_us: each point's own time, int64 [N].
        dynamic: the points on moving objects (``dynamic_flag``), bool [N].
        frames: the camera frames to take colours from, in the same fixed frame.
        spacing_m: the lidar's spacing between neighbouring returns at each point, across and along its
            rows, m [N,2] (None: not known; see :func:`visibility.visible_pixels`).

    Returns:
        rgb: uint8 [N,3], ``FILL_RGB`` where no camera sees the point; coloured: bool [N].
    """
    n = len(xyz_world_m)
    best_dt = np.full(n, np.inf)
    t_us = np.asarray(timestamps_us, dtype=np.int64)
    taken: list[ColourFrame] = []  # the frames some point took, in order: a later one may take a point over
    owner = np.full(n, -1, dtype=np.int64)  # each point's frame in ``taken``
    pixel = np.zeros((n, 2), dtype=np.int64)  # and its (row, column) there
    for camera_id in sorted({f.camera_id for f in frames}):
        own = sorted((f for f in frames if f.camera_id == camera_id), key=lambda f: f.timestamp_us)
        times = np.array([f.timestamp_us for f in own], dtype=np.int64)
        after = np.clip(np.searchsorted(times, t_us), 1, max(1, len(times) - 1))
        nearest = (
            after - 1 if len(times) == 1 else np.where(t_us - times[after - 1] <= times[after] - t_us, after - 1, after)
        )
        near, _ = in_view(own[len(own) // 2], xyz_world_m, VIEW_MARGIN)  # once per camera: the frames are close
        for k, frame in enumerate(own):
            rows, cols, lines = visible_pixels(frame, xyz_world_m[near], None if spacing_m is None else spacing_m[near])
            rows = near[rows]
            dt = np.abs(t_us[rows] - frame.timestamp_us).astype(np.float64)
            take = (nearest[rows] == k) & (dt < best_dt[rows]) & (~dynamic[rows] | (dt <= DYNAMIC_DT_US))
            if take.any():
                owner[rows[take]] = len(taken)
                pixel[rows[take]] = np.stack([lines[take], cols[take]], axis=1)
                best_dt[rows[take]] = dt[take]
                taken.append(frame)
    rgb = np.tile(np.array(FILL_RGB, dtype=np.uint8), (n, 1))
    by_frame = np.argsort(owner, kind="stable")
    bounds = np.searchsorted(owner[by_frame], np.arange(len(taken) + 1))
    needed = [i for i in range(len(taken)) if bounds[i + 1] > bounds[i]]  # frames that kept a point
    with ThreadPoolExecutor(max_workers=max(1, min(DECODE_THREADS, len(needed)))) as pool:  # decoders release the GIL
        for i, image in zip(needed, pool.map(lambda i: taken[i].load_rgb(), needed), strict=True):
            points = by_frame[bounds[i] : bounds[i + 1]]
            rgb[points] = image[pixel[points, 0], pixel[points, 1]]
    return rgb, np.isfinite(best_dt)
