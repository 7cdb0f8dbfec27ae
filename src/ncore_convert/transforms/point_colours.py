"""Per-point lidar colours from camera images: the ``rgb`` that 3DGRUT seeds its Gaussians with.

Each point takes the colour of the camera pixel it projects to:

- per camera, in that camera's frame nearest to the point's own time, with the camera's pose at
  the frame's time (the point is where the lidar saw it; a static point is still there);
- only where the pixel shows the world (not the ``ego`` body: ``usable``);
- only if nothing nearer hides it: a depth buffer of the frame's projected points, kept per cell of
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
AV2 images are undistorted, CARLA's are ideal), in the OpenCV frame (x right, y down, z forward),
with NCore's pixel-corner convention: pixel (i, j) covers [i, i+1) x [j, j+1).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

FILL_RGB = (128, 128, 128)  #: the colour of a point no camera sees: neutral grey
DYNAMIC_DT_US = 5_000  #: a point on a moving object takes colour only from a frame this close in time
CELL_RAD = np.radians(1.0)  #: depth-buffer cell, as an angle of view: its height; its width is half that
DEPTH_TOLERANCE = 0.05  #: a point this far behind (relative) its cell's nearest point is still visible ...
DEPTH_TOLERANCE_M = 0.3  #: ... plus this much
MIN_DEPTH_M = 0.3  #: points nearer the camera than this are not coloured
VIEW_MARGIN = 0.5  #: a camera's frames project only the points its middle frame sees, its image grown by this


@dataclass(frozen=True)
class ColourFrame:
    """One camera image to take colours from.

    Attributes:
        camera_id: the camera; timestamp_us: the frame's time (µs).
        T_world_camera: float64 [4,4], maps world points into the camera frame at the frame's time.
        focal_px, centre_px: (fx, fy) and (cx, cy) of the pinhole at the image's resolution
            (pixel-corner convention).
        size_px: the image's (width, height).
        load_rgb: returns the image, uint8 [height,width,3]; called only if a point takes its colour
            from this frame (decoding is most of the cost).
        usable: bool [height,width], the pixels that show the world (False on the ego body); None: all.
    """

    camera_id: str
    timestamp_us: int
    T_world_camera: np.ndarray
    focal_px: tuple[float, float]
    centre_px: tuple[float, float]
    size_px: tuple[int, int]
    load_rgb: Callable[[], np.ndarray]
    usable: np.ndarray | None = None


def _in_view(frame: ColourFrame, xyz_world_m: np.ndarray, margin: float) -> np.ndarray:
    """The rows of ``xyz_world_m`` [N,3] in front of ``frame``'s camera that project into its image
    grown by ``margin`` of its size on every side, int [K]."""
    xyz = xyz_world_m @ frame.T_world_camera[:3, :3].T + frame.T_world_camera[:3, 3]
    z = xyz[:, 2]
    ahead = np.flatnonzero(z > MIN_DEPTH_M)
    (w, h), (fx, fy), (cx, cy) = frame.size_px, frame.focal_px, frame.centre_px
    u = fx * xyz[ahead, 0] / z[ahead] + cx
    v = fy * xyz[ahead, 1] / z[ahead] + cy
    return ahead[(u >= -margin * w) & (u < (1 + margin) * w) & (v >= -margin * h) & (v < (1 + margin) * h)]


def _visible_pixels(frame: ColourFrame, xyz_world_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points (rows of ``xyz_world_m`` [N,3], all that may be in view: each may hide another)
    that ``frame`` sees: their indices [V] and pixel (column, row) [V] each, int."""
    w, h = frame.size_px
    rows = _in_view(frame, xyz_world_m, 0.0)
    xyz = xyz_world_m[rows] @ frame.T_world_camera[:3, :3].T + frame.T_world_camera[:3, 3]
    depth = xyz[:, 2]
    cols = np.minimum((frame.focal_px[0] * xyz[:, 0] / depth + frame.centre_px[0]).astype(np.int64), w - 1)
    lines = np.minimum((frame.focal_px[1] * xyz[:, 1] / depth + frame.centre_px[1]).astype(np.int64), h - 1)
    if frame.usable is not None:
        ok = frame.usable[lines, cols]
        rows, cols, lines, depth = rows[ok], cols[ok], lines[ok], depth[ok]
    cell_h = max(1, int(round(CELL_RAD * frame.focal_px[1])))
    cell_w = max(1, int(round(CELL_RAD / 2 * frame.focal_px[0])))
    n_cols = -(-w // cell_w) + 2  # a column either side
    cell_r, cell_c = lines // cell_h + 1, cols // cell_w + 1  # and a row above
    cells = cell_r * n_cols + cell_c
    grid = np.full((-(-h // cell_h) + 1) * n_cols, np.inf)
    np.minimum.at(grid, cells, depth)
    # What can hide a point lies above it in the picture or level with it (a nearer point below it is
    # the ground in front of it): the nearest point at or above its row in its own cell and in the
    # cells left and right of it (the pixels at a silhouette show the occluder up to a cell beyond
    # its last points), and of the whole cell above
    order = np.lexsort((lines, cells))
    key = cells[order] * (h + 1) + lines[order]
    big = 2.0 * (float(depth.max()) + 1.0) if len(depth) else 1.0
    running = np.minimum.accumulate(depth[order] - cells[order] * big) + cells[order] * big  # per cell, down to a row

    def at_or_above(cell: np.ndarray) -> np.ndarray:
        i = np.searchsorted(key, cell * (h + 1) + lines, side="right") - 1
        found = (i >= 0) & (cells[order][np.maximum(i, 0)] == cell)
        return np.where(found, running[np.maximum(i, 0)], np.inf)

    nearest = np.minimum.reduce([at_or_above(cells), at_or_above(cells - 1), at_or_above(cells + 1), grid[cells - n_cols]])
    seen = depth <= nearest * (1.0 + DEPTH_TOLERANCE) + DEPTH_TOLERANCE_M
    return rows[seen], cols[seen], lines[seen]


def point_colours(
    xyz_world_m: np.ndarray, timestamps_us: np.ndarray, dynamic: np.ndarray, frames: list[ColourFrame]
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's colour (see the module docstring).

    Args:
        xyz_world_m: the points in a fixed frame, where the lidar saw them, float64 [N,3].
        timestamps_us: each point's own time, int64 [N].
        dynamic: the points on moving objects (``dynamic_flag``), bool [N].
        frames: the camera frames to take colours from, in the same fixed frame.

    Returns:
        rgb: uint8 [N,3], ``FILL_RGB`` where no camera sees the point; coloured: bool [N].
    """
    n = len(xyz_world_m)
    rgb = np.tile(np.array(FILL_RGB, dtype=np.uint8), (n, 1))
    best_dt = np.full(n, np.inf)
    t_us = np.asarray(timestamps_us, dtype=np.int64)
    for camera_id in sorted({f.camera_id for f in frames}):
        own = sorted((f for f in frames if f.camera_id == camera_id), key=lambda f: f.timestamp_us)
        times = np.array([f.timestamp_us for f in own], dtype=np.int64)
        after = np.clip(np.searchsorted(times, t_us), 1, max(1, len(times) - 1))
        nearest = after - 1 if len(times) == 1 else np.where(t_us - times[after - 1] <= times[after] - t_us, after - 1, after)
        near = _in_view(own[len(own) // 2], xyz_world_m, VIEW_MARGIN)  # once per camera: the frames are close
        for k, frame in enumerate(own):
            rows, cols, lines = _visible_pixels(frame, xyz_world_m[near])
            rows = near[rows]
            dt = np.abs(t_us[rows] - frame.timestamp_us).astype(np.float64)
            take = (nearest[rows] == k) & (dt < best_dt[rows]) & (~dynamic[rows] | (dt <= DYNAMIC_DT_US))
            if take.any():
                rgb[rows[take]] = frame.load_rgb()[lines[take], cols[take]]
                best_dt[rows[take]] = dt[take]
    return rgb, np.isfinite(best_dt)
