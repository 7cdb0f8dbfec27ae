"""Which lidar points a camera frame sees: projection into the frame, a depth buffer of the
projected points (which point of the picture may hide another) and the labelled boxes as solid
occluders. Lidar colours (:mod:`point_colours`) use it, and per-camera depth labels build on it.
Cameras are pinholes in the OpenCV frame (x right, y down, z forward), with NCore's pixel-corner
convention: pixel (i, j) covers [i, i+1) x [j, j+1).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.objects.boxes import box_corners, near_plane_crossings
from ncore_convert.transforms.objects.cores import CELL_M, VEHICLE, solid_entry, under_floor

CELL_RAD = np.radians(0.5)  #: depth-buffer cell, as an angle of view: its height; its width is half that
DEPTH_TOLERANCE = 0.05  #: a point this far behind (relative) its cell's nearest point is still visible ...
DEPTH_TOLERANCE_M = 0.3  #: ... plus this much
MIN_DEPTH_M = 0.3  #: points nearer the camera than this are not seen
VIEW_MARGIN = 0.5  #: a camera's nearby frames project only the points its middle frame sees, its image grown by this
#: A point whose lidar footprint (its spacing to the neighbouring returns, seen from the camera) is wider
#: than this many depth-buffer cell widths also hides what lies behind it in cells 2, 4, 8 or 16 times as
#: large, the smallest that its footprint fits in: a surface near the camera but far from the lidar
#: (a car just ahead of a bumper camera, the lidar on the roof behind it) has returns many pixels
#: apart, and what the lidar saw past it must not show through the gaps.
FOOTPRINT_CELLS = 1.0
MAX_LEVEL = 4
#: In those wider cells a surface may recede this much per metre sideways across the line of sight
#: (one seen 10 degrees off grazing): the points of one oblique surface do not hide each other.
GRAZING_SLOPE = 1.0 / np.tan(np.radians(10.0))
NOWHERE_M = 1e6  #: the depth of a point that hides nothing at a level (finite: the buffer's running minima add depths)


@dataclass(frozen=True)
class CameraView:
    """One camera frame, as the points it sees are decided.

    Attributes:
        camera_id: the camera; timestamp_us: the frame's time (µs).
        T_world_camera: float64 [4,4], maps fixed-frame (world) points into the camera frame at the
            frame's time.
        pinhole: the camera at the resolution its pixels are taken at.
        usable: bool [height,width], the pixels that show the world (False on the ego body); None: all.
        solids: the boxes of the labelled objects that have solid parts (vehicles, people, riders,
            posts) at the frame's time: box -> fixed frame ``T_box_world`` float64 [K,4,4] and half
            sizes float64 [K,3], m. A point behind one's solid parts (:func:`objects.cores.solid_entry`)
            is hidden even where the lidar saw none of the object's face the camera sees. None: no boxes.
        solids_slack_m: how far the boxes may be off their objects (annotation error), m: a box does
            not hide the points within this distance of it, which may be its object's own.
        solids_velocity_mps: each solid's velocity, fixed frame, m/s [K,3]: its own points from other
            times are moved to the frame's time by it (None: all still).
        solids_kind: the kind of solid each object is (:data:`objects.cores.SOLID_KINDS`), int [K]
            (None: every one a vehicle).
    """

    camera_id: str
    timestamp_us: int
    T_world_camera: np.ndarray
    pinhole: Pinhole
    usable: np.ndarray | None = None
    solids: tuple[np.ndarray, np.ndarray] | None = None
    solids_slack_m: float = 0.0
    solids_velocity_mps: np.ndarray | None = None
    solids_kind: np.ndarray | None = None


def nearest_in_front(
    cols: np.ndarray, lines: np.ndarray, depth: np.ndarray, cell_px: tuple[int, int], size_px: tuple[int, int]
) -> np.ndarray:
    """For each projected point (pixel ``cols``, ``lines``, int [V]; camera ``depth`` [V], m), the
    depth of the nearest point that may hide it in a buffer of cells of ``cell_px`` (width, height):
    at or above its row in its own cell and in the cells left and right of it (the pixels at a
    silhouette show the occluder up to a cell beyond its last points), and anywhere in the cell
    above (a nearer point below a point is the ground in front of it and does not hide it); inf
    where there is none, float64 [V]."""
    (w, h), (cell_w, cell_h) = size_px, cell_px
    n_cols = -(-w // cell_w) + 2  # a column either side
    cells = (lines // cell_h + 1) * n_cols + cols // cell_w + 1  # and a row above
    order = np.lexsort((lines, cells))
    o_cells, o_depth = cells[order], depth[order]
    key = o_cells * (h + 1) + lines[order]
    big = 2.0 * (float(o_depth.max()) + 1.0) if len(o_depth) else 1.0
    running = np.minimum.accumulate(o_depth - o_cells * big) + o_cells * big  # per cell, down to a row
    grid = np.full((-(-h // cell_h) + 1) * n_cols, np.inf)  # per cell, its nearest point: its last running value
    last = np.flatnonzero(np.r_[o_cells[1:] != o_cells[:-1], True]) if len(o_cells) else np.zeros(0, np.int64)
    grid[o_cells[last]] = running[last]

    def at_or_above(cell: np.ndarray) -> np.ndarray:
        i = np.searchsorted(key, cell * (h + 1) + lines, side="right") - 1
        found = (i >= 0) & (o_cells[np.maximum(i, 0)] == cell)
        return np.where(found, running[np.maximum(i, 0)], np.inf)

    return np.minimum.reduce([at_or_above(cells), at_or_above(cells - 1), at_or_above(cells + 1), grid[cells - n_cols]])


def _beside_cells(cols: np.ndarray, lines: np.ndarray, occupied_by: np.ndarray, cell_px: tuple[int, int]) -> np.ndarray:
    """The points (pixel ``cols``, ``lines``, int [V]) that a point of ``occupied_by`` (bool [V]) may
    hide in a buffer of cells of ``cell_px`` (:func:`nearest_in_front`: their own cell, the cells
    left and right of it, the cell above), bool [V]."""
    gx, gy = cols // cell_px[0] + 1, lines // cell_px[1] + 1  # a cell of padding on every side
    occupied = np.zeros((int(gy.max(initial=0)) + 2, int(gx.max(initial=0)) + 2), bool)
    occupied[gy[occupied_by], gx[occupied_by]] = True
    near = occupied.copy()
    near[:, 1:] |= occupied[:, :-1]
    near[:, :-1] |= occupied[:, 1:]
    near[1:, :] |= occupied[:-1, :]
    return near[gy, gx]


def in_view(frame: CameraView, xyz_world_m: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``xyz_world_m`` [N,3] in front of ``frame``'s camera that project into its image
    grown by ``margin`` of its size on every side, int [K], and those points in the camera frame [K,3]."""
    R, t = frame.T_world_camera[:3, :3], frame.T_world_camera[:3, 3]
    ahead = np.flatnonzero(xyz_world_m @ R[2] + t[2] > MIN_DEPTH_M)  # depth first: most points are not ahead
    xyz = xyz_world_m[ahead] @ R.T + t
    w, h = frame.pinhole.resolution_px
    u, v = frame.pinhole.project(xyz)
    inside = (u >= -margin * w) & (u < (1 + margin) * w) & (v >= -margin * h) & (v < (1 + margin) * h)
    return ahead[inside], xyz[inside]


@dataclass(frozen=True)
class BoxPictures:
    """Where boxes appear in a camera frame (:func:`box_pictures`).

    Attributes:
        origin_m: the camera's centre in each box's frame, float64 [K,3], m.
        rectangle_px: the bounding rectangle of each box's picture, whole pixels (first and last
            column, first and last row; NaN for a box wholly behind the camera), float64 [K] each.
        in_view: the boxes that may show in the image: the camera is outside them and their
            rectangle meets the image, bool [K].
    """

    origin_m: np.ndarray
    rectangle_px: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    in_view: np.ndarray


def box_pictures(frame: CameraView, T_box_world: np.ndarray, half_m: np.ndarray) -> BoxPictures:
    """Where boxes (box -> fixed frame ``T_box_world`` float64 [K,4,4], half sizes ``half_m`` [K,3],
    m) appear in ``frame``: the rectangle of each one's corners ahead of the camera and of where its
    edges cross the plane ``MIN_DEPTH_M`` ahead of it."""
    R_wc, t_wc = frame.T_world_camera[:3, :3], frame.T_world_camera[:3, 3]
    camera_m = invert_se3(frame.T_world_camera)[:3, 3]
    R_all, t_all = T_box_world[:, :3, :3], T_box_world[:, :3, 3]
    origin_all = np.einsum("kji,kj->ki", R_all, camera_m - t_all)
    corners = box_corners(R_all, t_all, half_m) @ R_wc.T + t_wc  # [K,8,3] in the camera frame
    on_plane, crosses = near_plane_crossings(corners, MIN_DEPTH_M)
    crossing = np.where(crosses[..., None], on_plane, np.nan)
    points = np.concatenate([np.where(corners[..., 2:] >= MIN_DEPTH_M, corners, np.nan), crossing], axis=1)
    w, h = frame.pinhole.resolution_px
    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a box wholly behind the camera: all NaN
        u, v = (c.reshape(points.shape[:-1]) for c in frame.pinhole.project(points.reshape(-1, 3)))
        u_lo, u_hi, v_lo, v_hi = (
            np.floor(np.nanmin(u, axis=1)),
            np.floor(np.nanmax(u, axis=1)),
            np.floor(np.nanmin(v, axis=1)),
            np.floor(np.nanmax(v, axis=1)),
        )
    camera_inside = np.all(np.abs(origin_all) <= half_m, axis=1)
    in_view = ~camera_inside & (u_hi >= 0) & (u_lo < w) & (v_hi >= 0) & (v_lo < h)  # NaN: False
    return BoxPictures(origin_all, (u_lo, u_hi, v_lo, v_hi), in_view)


def _behind_solids(
    frame: CameraView,
    xyz_world_m: np.ndarray,
    cols: np.ndarray,
    lines: np.ndarray,
    spacing_m: np.ndarray | None,
    candidates: np.ndarray,
) -> np.ndarray:
    """The points (float64 [V,3], fixed frame, all those in view; their pixel ``cols``, ``lines``,
    int [V]; the lidar's spacing at each, ``spacing_m`` [V,2] or None) whose line of sight from
    ``frame``'s camera enters the solid part of one of its ``solids``
    (:func:`objects.cores.solid_entry`, from the box's own points among these) more than the depth
    tolerance before reaching the point, bool [V]. A box the camera is inside hides nothing, nor does
    a box hide the points within ``frame.solids_slack_m`` of it (its object's own: the depth buffer
    decides those), but for the street under a vehicle's floor. Only the ``candidates`` (bool [V],
    those still seen) are tested; every point is evidence of its box's solid parts. Each box in view
    looks only at the points in its picture's bounding rectangle."""
    hidden = np.zeros(len(xyz_world_m), bool)
    if frame.solids is None or not len(xyz_world_m):
        return hidden
    camera_m = invert_se3(frame.T_world_camera)[:3, 3]  # the camera's centre in the fixed frame
    by_col = np.argsort(cols, kind="stable")
    cols_sorted = cols[by_col]
    T_box_world, half_all = frame.solids
    pictures = box_pictures(frame, T_box_world, half_all)
    R_all, t_all, origin_all = T_box_world[:, :3, :3], T_box_world[:, :3, 3], pictures.origin_m
    u_lo, u_hi, v_lo, v_hi = pictures.rectangle_px
    for k in np.flatnonzero(pictures.in_view):
        R, t, half_m, origin = R_all[k], t_all[k], half_all[k], origin_all[k]
        near = by_col[np.searchsorted(cols_sorted, u_lo[k]) : np.searchsorted(cols_sorted, u_hi[k], side="right")]
        near = near[(lines[near] >= v_lo[k]) & (lines[near] <= v_hi[k])]
        if not len(near):
            continue
        local = (xyz_world_m[near] - t) @ R
        own = np.all(np.abs(local) <= half_m + frame.solids_slack_m, axis=1)  # may be its object's own
        kind = VEHICLE if frame.solids_kind is None else int(frame.solids_kind[k])
        gaps_m = CELL_M if spacing_m is None or not own.any() else float(np.median(spacing_m[near[own]].max(axis=1)))
        own_m = local[own]
        own &= ~under_floor(kind, half_m, local)
        test = ~own & candidates[near] & ~hidden[near]  # a point another box hides needs no more tests
        near, local = near[test], local[test]
        if not len(near):
            continue
        entry = solid_entry(kind, half_m, own_m, gaps_m, origin, local - origin)
        distance_m = np.linalg.norm(xyz_world_m[near] - camera_m, axis=1)
        allowed_m = distance_m * (1.0 - DEPTH_TOLERANCE) - DEPTH_TOLERANCE_M  # an entry nearer than this hides
        hidden[near[entry * distance_m < allowed_m]] = True
    return hidden


def footprint_levels(spacing_m: np.ndarray | None, depth_m: np.ndarray) -> np.ndarray:
    """The depth-buffer level of each point across and along the image's rows (0: the base cells;
    L: cells 2^L as wide, or as tall): the smallest whose cells its footprint fits in, where the
    footprint (``spacing_m`` [V,2], the lidar's spacing between neighbouring returns at the point
    across and along its rows, m, seen at camera depth ``depth_m`` [V]) is wider, or taller, than
    ``FOOTPRINT_CELLS`` base cells; else 0. None: all 0. int [V,2]."""
    if spacing_m is None:
        return np.zeros((len(depth_m), 2), np.int64)
    cells = spacing_m / (depth_m[:, None] * np.array([CELL_RAD / 2, CELL_RAD]))  # in base cell widths, heights
    level = np.ceil(np.log2(np.maximum(cells, 1.0)))
    return np.where(cells > FOOTPRINT_CELLS, np.minimum(level, MAX_LEVEL), 0).astype(np.int64)


def moving_shift(frame: CameraView, evidence_m: np.ndarray, evidence_dt_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which points of ``evidence_m`` ([E,3], fixed frame, taken ``evidence_dt_s`` [E] seconds before
    the frame) lie in a moving solid's box (grown by ``frame.solids_slack_m``) once moved with its
    velocity to the frame's time, bool [E], and that move, float64 [E,3] (m; 0 for the others). A
    still box claims none: a mover's points from other times near it are not its."""
    keep = np.zeros(len(evidence_m), bool)
    shift = np.zeros((len(evidence_m), 3))
    if frame.solids is not None and frame.solids_velocity_mps is not None and len(evidence_m):
        T_box_world, half_all = frame.solids
        for k in np.flatnonzero(np.any(frame.solids_velocity_mps != 0, axis=1)):
            move = np.multiply.outer(evidence_dt_s, frame.solids_velocity_mps[k])
            local = (evidence_m + move - T_box_world[k, :3, 3]) @ T_box_world[k, :3, :3]
            inside = ~keep & np.all(np.abs(local) <= half_all[k] + frame.solids_slack_m, axis=1)
            shift[inside], keep[inside] = move[inside], True
    return keep, shift


def moved_evidence(
    frame: CameraView, evidence_m: np.ndarray, evidence_dt_s: np.ndarray, spacing_m: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """The points of ``evidence_m`` that a moving solid claims (:func:`moving_shift`), moved with it to
    the frame's time [M,3], and their ``spacing_m`` rows ([M,2], None without)."""
    keep, shift = moving_shift(frame, evidence_m, evidence_dt_s)
    return (evidence_m + shift)[keep], None if spacing_m is None else spacing_m[keep]


def visible_pixels(
    frame: CameraView,
    xyz_world_m: np.ndarray,
    spacing_m: np.ndarray | None = None,
    evidence_m: np.ndarray | None = None,
    evidence_dt_s: np.ndarray | None = None,
    evidence_spacing_m: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points (rows of ``xyz_world_m`` [N,3], all that may be in view: each may hide another)
    that ``frame`` sees: their indices [V] and pixel (column, row) [V] each, int. ``spacing_m``
    [N,2]: the lidar's spacing between neighbouring returns at each point, across and along its
    rows, m (None: not known; the base cells only, see ``FOOTPRINT_CELLS``). ``evidence_m`` [E,3]:
    more points of the same sweep that are not to be labelled (a mover's, from other times), fixed
    frame, taken ``evidence_dt_s`` [E] seconds before the frame (``evidence_spacing_m`` [E,2] as
    ``spacing_m``): those in a moving solid's box, moved with it to the frame's time
    (:func:`moved_evidence`), hide what lies behind them and show where its object is
    (:func:`objects.cores.solid_entry`)."""
    n = len(xyz_world_m)
    if evidence_m is not None and len(evidence_m):
        dt_s = np.zeros(len(evidence_m)) if evidence_dt_s is None else evidence_dt_s
        moved, moved_spacing = moved_evidence(frame, evidence_m, dt_s, evidence_spacing_m)
        xyz_world_m = np.concatenate([xyz_world_m, moved])
        if spacing_m is not None:
            spacing_m = np.concatenate(
                [spacing_m, moved_spacing if moved_spacing is not None else np.zeros((len(moved), 2))]
            )
    w, h = frame.pinhole.resolution_px
    rows, xyz = in_view(frame, xyz_world_m, 0.0)
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
    in_view_spacing_m = None if spacing_m is None else spacing_m[rows]
    levels = footprint_levels(in_view_spacing_m, depth)
    for wide, tall in np.unique(levels[np.any(levels > 0, axis=1)], axis=0):
        # the points whose footprints need cells this wide and tall hide what lies behind them in those
        near_scale = (
            (levels[:, 0] >= wide) & (levels[:, 0] <= wide + 1) & (levels[:, 1] >= tall) & (levels[:, 1] <= tall + 1)
        )
        cell = (cell_px[0] * 2**wide, cell_px[1] * 2**tall)
        sub = near_scale | (seen & _beside_cells(cols, lines, near_scale, cell))  # the others are not near one
        occluder = np.where(near_scale[sub], depth[sub], NOWHERE_M)
        nearest = nearest_in_front(cols[sub], lines[sub], occluder, cell, (w, h))
        # a surface receding across the cell: sideways (a car's flank); upwards, the ground recedes, but
        # a point only hides those below it (``nearest_in_front``)
        slope = GRAZING_SLOPE * CELL_RAD / 2 * 2.0**wide
        seen[sub] &= depth[sub] <= nearest * (1.0 + DEPTH_TOLERANCE + slope) + DEPTH_TOLERANCE_M
    seen &= rows < n  # the moved evidence only hides
    seen &= ~_behind_solids(frame, xyz_world_m[rows], cols, lines, in_view_spacing_m, seen)
    return rows[seen], cols[seen], lines[seen]
