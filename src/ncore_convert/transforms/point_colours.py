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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

FILL_RGB = (128, 128, 128)  #: the colour of a point no camera sees: neutral grey
DYNAMIC_DT_US = 5_000  #: a point on a moving object takes colour only from a frame this close in time
CELL_RAD = np.radians(1.0)  #: depth-buffer cell, as an angle of view: its height; its width is half that
DEPTH_TOLERANCE = 0.05  #: a point this far behind (relative) its cell's nearest point is still visible ...
DEPTH_TOLERANCE_M = 0.3  #: ... plus this much
MIN_DEPTH_M = 0.3  #: points nearer the camera than this are not coloured
DECODE_THREADS = 4  #: images are decoded this many at a time
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
        load_rgb: returns the image, uint8 [height,width,3]; called only if a point keeps its colour
            from this frame (decoding is slow), from up to ``DECODE_THREADS`` threads.
        usable: bool [height,width], the pixels that show the world (False on the ego body); None: all.
        solids: boxes known to be solid at the frame's time (labelled vehicles): box -> fixed frame
            ``T_box_world`` float64 [K,4,4] and half sizes float64 [K,3], m. A point behind one is hidden
            even where the lidar saw none of the box's face the camera sees. None: no boxes.
    """

    camera_id: str
    timestamp_us: int
    T_world_camera: np.ndarray
    focal_px: tuple[float, float]
    centre_px: tuple[float, float]
    size_px: tuple[int, int]
    load_rgb: Callable[[], np.ndarray]
    usable: np.ndarray | None = None
    solids: tuple[np.ndarray, np.ndarray] | None = None


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


def _nearest_in_front(cols: np.ndarray, lines: np.ndarray, depth: np.ndarray, occluder: np.ndarray,
                      cell_px: tuple[int, int], size_px: tuple[int, int]) -> np.ndarray:  # fmt: skip
    """For each projected point (pixel ``cols``, ``lines``, int [V]; camera ``depth`` [V], m), the
    depth of the nearest ``occluder`` (bool [V]) that may hide it in a buffer of cells of
    ``cell_px`` (width, height): at or above its row in its own cell and in the cells left and right
    of it (the pixels at a silhouette show the occluder up to a cell beyond its last points), and
    anywhere in the cell above (a nearer point below a point is the ground in front of it and does
    not hide it); inf where there is none, float64 [V]."""
    (w, h), (cell_w, cell_h) = size_px, cell_px
    n_cols = -(-w // cell_w) + 2  # a column either side
    cells = (lines // cell_h + 1) * n_cols + cols // cell_w + 1  # and a row above
    grid = np.full((-(-h // cell_h) + 1) * n_cols, np.inf)
    np.minimum.at(grid, cells[occluder], depth[occluder])
    o_cells, o_lines, o_depth = cells[occluder], lines[occluder], depth[occluder]
    order = np.lexsort((o_lines, o_cells))
    o_cells, o_lines, o_depth = o_cells[order], o_lines[order], o_depth[order]
    key = o_cells * (h + 1) + o_lines
    big = 2.0 * (float(o_depth.max()) + 1.0) if len(o_depth) else 1.0
    running = np.minimum.accumulate(o_depth - o_cells * big) + o_cells * big  # per cell, down to a row

    def at_or_above(cell: np.ndarray) -> np.ndarray:
        i = np.searchsorted(key, cell * (h + 1) + lines, side="right") - 1
        found = (i >= 0) & (o_cells[np.maximum(i, 0)] == cell)
        return np.where(found, running[np.maximum(i, 0)], np.inf)

    return np.minimum.reduce([at_or_above(cells), at_or_above(cells - 1), at_or_above(cells + 1), grid[cells - n_cols]])


def _behind_solids(frame: ColourFrame, xyz_world_m: np.ndarray) -> np.ndarray:
    """The points (float64 [V,3], fixed frame) whose line of sight from ``frame``'s camera enters one
    of its ``solids`` more than the depth tolerance before reaching the point, bool [V]. A box the
    camera is inside hides nothing."""
    hidden = np.zeros(len(xyz_world_m), bool)
    if frame.solids is None or not len(xyz_world_m):
        return hidden
    R_wc, t_wc = frame.T_world_camera[:3, :3], frame.T_world_camera[:3, 3]
    camera_m = -R_wc.T @ t_wc  # the camera's centre in the fixed frame
    distance_m = np.linalg.norm(xyz_world_m - camera_m, axis=1)
    allowed_m = distance_m * (1.0 - DEPTH_TOLERANCE) - DEPTH_TOLERANCE_M  # an entry nearer than this hides
    for T_box_world, half_m in zip(*frame.solids, strict=True):
        R, t = T_box_world[:3, :3], T_box_world[:3, 3]
        origin = (camera_m - t) @ R
        if np.all(np.abs(origin) <= half_m):
            continue
        step = (xyz_world_m - t) @ R - origin  # the line of sight in the box frame, as a fraction of its length
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = (-half_m - origin) / step, (half_m - origin) / step
        enter = np.nanmax(np.fmin(a, b), axis=1)
        leave = np.nanmin(np.fmax(a, b), axis=1)
        hidden |= (enter <= leave) & (enter > 0) & (enter * distance_m < allowed_m)
    return hidden


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
    cell_px = (max(1, int(round(CELL_RAD / 2 * frame.focal_px[0]))), max(1, int(round(CELL_RAD * frame.focal_px[1]))))
    nearest = _nearest_in_front(cols, lines, depth, np.ones(len(rows), bool), cell_px, (w, h))
    seen = depth <= nearest * (1.0 + DEPTH_TOLERANCE) + DEPTH_TOLERANCE_M
    seen[seen] = ~_behind_solids(frame, xyz_world_m[rows[seen]])
    return rows[seen], cols[seen], lines[seen]


def point_colours(
    xyz_world_m: np.ndarray,
    timestamps_us: np.ndarray,
    dynamic: np.ndarray,
    frames: list[ColourFrame],
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
    best_dt = np.full(n, np.inf)
    t_us = np.asarray(timestamps_us, dtype=np.int64)
    taken: list[ColourFrame] = []  # the frames some point took, in order: a later one may take a point over
    owner = np.full(n, -1, dtype=np.int64)  # each point's frame in ``taken``
    pixel = np.zeros((n, 2), dtype=np.int64)  # and its (row, column) there
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
