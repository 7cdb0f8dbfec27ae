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

import warnings
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ncore_convert.transforms.boxes import BOX_EDGES, CORNER_SIGNS
from ncore_convert.transforms.camera_models import Pinhole
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.visibility import nearest_in_front

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
        pinhole: the camera at the resolution of the image ``load_rgb`` returns.
        load_rgb: returns the image, uint8 [height,width,3]; called only if a point keeps its colour
            from this frame (decoding is slow), from up to ``DECODE_THREADS`` threads.
        usable: bool [height,width], the pixels that show the world (False on the ego body); None: all.
        solids: boxes known to be solid at the frame's time (labelled vehicles): box -> fixed frame
            ``T_box_world`` float64 [K,4,4] and half sizes float64 [K,3], m. A point behind one is hidden
            even where the lidar saw none of the box's face the camera sees. None: no boxes.
        solids_slack_m: how far the boxes may be off their objects (annotation error), m: a box does
            not hide the points within this distance of it, which may be its object's own.
    """

    camera_id: str
    timestamp_us: int
    T_world_camera: np.ndarray
    pinhole: Pinhole
    load_rgb: Callable[[], np.ndarray]
    usable: np.ndarray | None = None
    solids: tuple[np.ndarray, np.ndarray] | None = None
    solids_slack_m: float = 0.0


def _in_view(frame: ColourFrame, xyz_world_m: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``xyz_world_m`` [N,3] in front of ``frame``'s camera that project into its image
    grown by ``margin`` of its size on every side, int [K], and those points in the camera frame [K,3]."""
    xyz = xyz_world_m @ frame.T_world_camera[:3, :3].T + frame.T_world_camera[:3, 3]
    ahead = np.flatnonzero(xyz[:, 2] > MIN_DEPTH_M)
    w, h = frame.pinhole.resolution_px
    u, v = frame.pinhole.project(xyz[ahead])
    inside = (u >= -margin * w) & (u < (1 + margin) * w) & (v >= -margin * h) & (v < (1 + margin) * h)
    return ahead[inside], xyz[ahead[inside]]


def _behind_solids(frame: ColourFrame, xyz_world_m: np.ndarray, cols: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """The points (float64 [V,3], fixed frame; their pixel ``cols``, ``lines``, int [V]) whose line of
    sight from ``frame``'s camera enters one of its ``solids`` more than the depth tolerance before
    reaching the point, bool [V]. A box the camera is inside hides nothing, nor does a box hide the
    points within ``frame.solids_slack_m`` of it (its object's own: the depth buffer decides those).
    Each box in view tests only the points in its picture's bounding rectangle."""
    hidden = np.zeros(len(xyz_world_m), bool)
    if frame.solids is None or not len(xyz_world_m):
        return hidden
    R_wc, t_wc = frame.T_world_camera[:3, :3], frame.T_world_camera[:3, 3]
    camera_m = invert_se3(frame.T_world_camera)[:3, 3]  # the camera's centre in the fixed frame
    w, h = frame.pinhole.resolution_px
    by_col = np.argsort(cols, kind="stable")
    cols_sorted = cols[by_col]
    T_box_world, half_all = frame.solids
    R_all, t_all = T_box_world[:, :3, :3], T_box_world[:, :3, 3]
    origin_all = np.einsum("kji,kj->ki", R_all, camera_m - t_all)  # the camera in each box's frame
    corners = np.einsum("kij,kcj->kci", R_all, CORNER_SIGNS[None] * half_all[:, None]) + t_all[:, None]
    corners = corners @ R_wc.T + t_wc  # [K,8,3] in the camera frame
    # the bounding rectangle of each box's picture: its corners ahead of the camera, and where its
    # edges cross the plane MIN_DEPTH_M ahead of it
    start, end = corners[:, BOX_EDGES[:, 0]], corners[:, BOX_EDGES[:, 1]]  # [K,12,3]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = (MIN_DEPTH_M - start[..., 2]) / (end[..., 2] - start[..., 2])
        crossing = np.where(((f > 0) & (f < 1))[..., None], start + f[..., None] * (end - start), np.nan)
    points = np.concatenate([np.where(corners[..., 2:] >= MIN_DEPTH_M, corners, np.nan), crossing], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a box wholly behind the camera: all NaN
        u, v = (c.reshape(points.shape[:-1]) for c in frame.pinhole.project(points.reshape(-1, 3)))
        u_lo, u_hi, v_lo, v_hi = (
            np.floor(np.nanmin(u, axis=1)),
            np.floor(np.nanmax(u, axis=1)),
            np.floor(np.nanmin(v, axis=1)),
            np.floor(np.nanmax(v, axis=1)),
        )
    camera_inside = np.all(np.abs(origin_all) <= half_all, axis=1)
    candidates = ~camera_inside & (u_hi >= 0) & (u_lo < w) & (v_hi >= 0) & (v_lo < h)  # NaN: False
    for k in np.flatnonzero(candidates):
        R, t, half_m, origin = R_all[k], t_all[k], half_all[k], origin_all[k]
        near = by_col[np.searchsorted(cols_sorted, u_lo[k]) : np.searchsorted(cols_sorted, u_hi[k], side="right")]
        near = near[(lines[near] >= v_lo[k]) & (lines[near] <= v_hi[k])]
        if not len(near):
            continue
        local = (xyz_world_m[near] - t) @ R
        if frame.solids_slack_m > 0:  # a point this close to a loose box may be its object's own
            away = np.any(np.abs(local) > half_m + frame.solids_slack_m, axis=1)
            near, local = near[away], local[away]
        distance_m = np.linalg.norm(xyz_world_m[near] - camera_m, axis=1)
        step = local - origin  # the line of sight in the box frame, as a fraction of its length
        with np.errstate(divide="ignore", invalid="ignore"):
            low, high = (-half_m - origin) / step, (half_m - origin) / step
        enter = np.nanmax(np.fmin(low, high), axis=1)
        leave = np.nanmin(np.fmax(low, high), axis=1)
        allowed_m = distance_m * (1.0 - DEPTH_TOLERANCE) - DEPTH_TOLERANCE_M  # an entry nearer than this hides
        hidden[near[(enter <= leave) & (enter > 0) & (enter * distance_m < allowed_m)]] = True
    return hidden


def _visible_pixels(frame: ColourFrame, xyz_world_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points (rows of ``xyz_world_m`` [N,3], all that may be in view: each may hide another)
    that ``frame`` sees: their indices [V] and pixel (column, row) [V] each, int."""
    w, h = frame.pinhole.resolution_px
    rows, xyz = _in_view(frame, xyz_world_m, 0.0)
    depth = xyz[:, 2]
    u, v = frame.pinhole.project(xyz)
    cols, lines = np.minimum(u.astype(np.int64), w - 1), np.minimum(v.astype(np.int64), h - 1)
    if frame.usable is not None:
        ok = frame.usable[lines, cols]
        rows, cols, lines, depth = rows[ok], cols[ok], lines[ok], depth[ok]
    fx, fy = frame.pinhole.focal_length_px
    cell_px = (max(1, int(round(CELL_RAD / 2 * fx))), max(1, int(round(CELL_RAD * fy))))
    nearest = nearest_in_front(cols, lines, depth, cell_px, (w, h))
    seen = depth <= nearest * (1.0 + DEPTH_TOLERANCE) + DEPTH_TOLERANCE_M
    seen[seen] = ~_behind_solids(frame, xyz_world_m[rows[seen]], cols[seen], lines[seen])
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
        nearest = (
            after - 1 if len(times) == 1 else np.where(t_us - times[after - 1] <= times[after] - t_us, after - 1, after)
        )
        near, _ = _in_view(own[len(own) // 2], xyz_world_m, VIEW_MARGIN)  # once per camera: the frames are close
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
