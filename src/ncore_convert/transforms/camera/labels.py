"""Image-aligned labels of camera frames, for NCore's camera-labels component: sparse z-depth from
lidar points (``depth.z``), and which labelled object each pixel shows (``mask.dynamic`` and
``segmentation.instance`` are made from :func:`box_index`: each object's box cut to where the
lidar's points show it).

A depth label holds, per pixel, the camera-frame z (metres, OpenCV frame: z forward) of the nearest
lidar point that the camera sees there, 0 where no point does. The points are the lidar's, where
it saw them, in the fixed (world) frame:

- a static point is still there at the camera's time, so it is taken from whichever sweep is at
  hand and projected with the camera's pose at the frame's time;
- a point on a moving object (``dynamic``) only from within ``DYNAMIC_DT_US`` of the frame: the
  object moves, and elsewhere its points would label pixels it no longer covers;
- only the points the camera sees (:func:`visibility.visible_pixels`: in front of the camera, not on
  the ego body, not behind a nearer point of the picture or a labelled box at the frame's time),
  so a pixel never shows a surface the lidar saw through a foreground object from its own viewpoint.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np

from ncore_convert.transforms.camera.visibility import (
    MIN_DEPTH_M,
    CameraView,
    box_pictures,
    moving_shift,
    visible_pixels,
)
from ncore_convert.transforms.objects.boxes import box_corners, first_seen, slab_span
from ncore_convert.transforms.objects.cores import CELL_M, OWN_MARGIN_M, VEHICLE, cover_columns, cover_map

#: A point on a moving object labels only a frame this close to its own time (µs): at 15 m/s the
#: object moves 7.5 cm in that time.
DYNAMIC_DT_US = 5_000


def depth_z(
    view: CameraView,
    xyz_world_m: np.ndarray,
    timestamps_us: np.ndarray,
    dynamic: np.ndarray,
    spacing_m: np.ndarray | None = None,
    hiding: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """The depth label of ``view`` (see the module docstring).

    Args:
        view: the camera frame; its pinhole's resolution is the label's.
        xyz_world_m: lidar points where the lidar saw them, fixed frame, float64 [N,3].
        timestamps_us: each point's own time, int [N].
        dynamic: the points on moving objects (``dynamic_flag``), bool [N].
        spacing_m: the lidar's spacing between neighbouring returns at each point, across and along its
            rows, m [N,2] (None: not known; see :func:`visibility.visible_pixels`).
        hiding: more points that hide what lies behind them but label nothing, fixed frame, float64
            [H,3], and their spacing, m [H,2] (without boxes: the movers' points drawn by
            :func:`mover_mask`, where the sweeps around the frame saw them). None: none.

    Returns:
        float32 [height,width]: z in metres of the nearest visible point per pixel, 0 where none.
    """
    width, height = view.pinhole.resolution_px
    image = np.zeros((height, width), dtype=np.float32)
    dt_us = np.abs(np.asarray(timestamps_us, dtype=np.int64) - int(view.timestamp_us))
    usable = np.flatnonzero(~np.asarray(dynamic, dtype=bool) | (dt_us <= DYNAMIC_DT_US))
    if not len(usable):
        return image
    stale = np.ones(len(xyz_world_m), bool)
    stale[usable] = False  # a mover's points from other times: where its object is, not what a pixel shows
    spacing = None if spacing_m is None else spacing_m[usable]
    dt_s = (view.timestamp_us - np.asarray(timestamps_us, dtype=np.int64)[stale]) * 1e-6
    stale_spacing = None if spacing_m is None else spacing_m[stale]
    labelled_m = xyz_world_m[usable]
    if hiding is not None and spacing is not None:
        labelled_m, spacing = np.concatenate([labelled_m, hiding[0]]), np.concatenate([spacing, hiding[1]])
    rows, cols, lines = visible_pixels(view, labelled_m, spacing, xyz_world_m[stale], dt_s, stale_spacing)
    labels = rows < len(usable)  # the hiding points label nothing
    rows, cols, lines = rows[labels], cols[labels], lines[labels]
    T = view.T_world_camera
    z_m = xyz_world_m[usable[rows]] @ T[2, :3] + T[2, 3]
    pixel = lines * width + cols
    order = np.lexsort((z_m, pixel))  # by pixel, nearest first
    first = order[np.r_[True, pixel[order][1:] != pixel[order][:-1]]] if len(order) else order
    image.reshape(-1)[pixel[first]] = z_m[first]
    return image


def points_at_frame(
    view: CameraView,
    xyz_world_m: np.ndarray,
    timestamps_us: np.ndarray,
    dynamic: np.ndarray,
    spacing_m: np.ndarray | None = None,
    origins_m: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A sweep's points where their objects are at ``view``'s time, the evidence of the objects'
    shapes in its masks (:func:`box_index`): a static point, and a moving one within ``DYNAMIC_DT_US``,
    where the lidar saw it; a moving one from further off moved with its moving box
    (:func:`visibility.moving_shift`), or left out. Arguments as :func:`depth_z`'s, and ``origins_m``:
    where the lidar was as it measured each point, fixed frame, [N,3] or [3] (None: not known), moved
    with its point. Returns the points [M,3], their spacing [M,2] and origins [M,3] (None where not
    given)."""
    dt_us = np.asarray(timestamps_us, dtype=np.int64) - int(view.timestamp_us)
    near = ~np.asarray(dynamic, dtype=bool) | (np.abs(dt_us) <= DYNAMIC_DT_US)
    far = np.flatnonzero(~near)
    keep, shift = moving_shift(view, xyz_world_m[far], -dt_us[far] * 1e-6)
    rows = np.r_[np.flatnonzero(near), far[keep]]
    moved = np.zeros((len(rows), 3))
    moved[int(near.sum()) :] = shift[keep]
    origins = None
    if origins_m is not None:
        origins_m = np.asarray(origins_m, np.float64)
        origins = (origins_m[rows] if origins_m.ndim == 2 else origins_m) + moved
    return xyz_world_m[rows] + moved, None if spacing_m is None else spacing_m[rows], origins


@dataclass(frozen=True)
class BoxPicture:
    """Which box each pixel of a camera frame shows (:func:`box_index`).

    Attributes:
        index: int32 [height,width], an index into the boxes, or -1.
        shown: the boxes that hold a pixel, sorted, int [S].
        rectangles: each shown box's pixels lie in rows ``r0:r1`` and columns ``c0:c1`` of it,
            int [S,4] (r0, r1, c0, c1).
    """

    index: np.ndarray
    shown: np.ndarray
    rectangles: np.ndarray


#: How masks (``mask.dynamic``, ``segmentation.instance``) are made, as their metadata says it.
MASKS_MADE = (
    "each labelled object's box cut where the lidar shows it empty: a vehicle to a height map of its own points"
    " (6 cm cells; its far side mirrored, unseen cells a generous car shape no higher than the lidar's lines of"
    " sight through them; the street under its body between the wheels left out; vans, trucks and buses taller"
    " than 2 m at full height), any other object to its own points' footprints; a box without own points whole."
    " A vehicle's map is made from the points and lines of sight of every sweep of its track"
    " (objects.track_shapes): a static track's at its median box, a simulator's exact boxes as they are, an"
    " annotated moving track's sweeps registered to each other first (only those that agree); near a sweep"
    " that does not agree, from the frame's own sweep"
)


def box_index(
    view: CameraView,
    T_box_world: np.ndarray,
    half_m: np.ndarray,
    kinds: np.ndarray | None = None,
    points_m: np.ndarray | None = None,
    spacing_m: np.ndarray | None = None,
    origins_m: np.ndarray | None = None,
    covers: dict | None = None,
    keys: list | None = None,
    sight=None,
    shapes=None,
) -> BoxPicture:
    """Which object each pixel of ``view`` shows: the object whose picture holds the pixel, where
    pictures overlap the one whose box is in front (:func:`objects.boxes.first_seen`; of boxes that
    overlap in space, the one each pixel's ray enters first), -1 where none does or the pixel is not
    usable (the ego body). Objects hide each other; nothing else does
    (the labels know no other surface). A box the camera is inside is left out.

    With the lidar's points, a box's object is where its own points do not show the box empty
    (:func:`objects.cores.cover_map`: the box cut to the tops its points show, and for a vehicle
    to its body and wheels); without them, it is its whole box.

    Args:
        view: the camera frame; its pinhole's resolution is the result's.
        T_box_world: box -> fixed frame, float64 [K,4,4]; half_m: half sizes, float64 [K,3], m.
        kinds: each box's kind of solid (:data:`objects.cores.SOLID_KINDS`, -1 none), int [K]
            (None: every one a vehicle).
        points_m: the lidar's points at the frame's time, fixed frame, float64 [N,3] (None: boxes only).
        spacing_m: the lidar's spacing between neighbouring returns at each point, across and along
            its rows, m [N,2] (None: not known, ``CELL_M``).
        origins_m: where the lidar was as it measured each point, fixed frame, float64 [N,3] or [3]
            (None: not known).
        covers, keys: each vehicle's :func:`objects.cores.cover_map` is kept in ``covers`` under its
            box's key (``keys`` [K], hashable) and taken from there when it is already in: the frames
            of one sweep share the maps (the caller empties it for the next sweep).
        sight: where the sweep's lines of sight passed (``sight.passed(places [M,3], fixed frame) ->
            bool [M]``: ``lidar.range_image.RangeImage``); None: nowhere known (no free space cuts).
        shapes: the vehicles' shapes from every sweep of their tracks
            (:class:`objects.track_shapes.TrackShapes`, by ``keys``): a box whose track it holds takes
            its whole-track cover map instead of this sweep's. None: this sweep's only.
    """
    width, height = view.pinhole.resolution_px
    index = np.full((height, width), -1, dtype=np.int32)
    pictures = box_pictures(view, T_box_world, half_m)
    u_lo, u_hi, v_lo, v_hi = pictures.rectangle_px
    candidates = np.flatnonzero(pictures.in_view)
    rectangles = np.zeros((len(candidates), 4), dtype=np.int64)
    rectangles[:, 0], rectangles[:, 1] = np.maximum(v_lo[candidates], 0), np.minimum(v_hi[candidates], height - 1) + 1
    rectangles[:, 2], rectangles[:, 3] = np.maximum(u_lo[candidates], 0), np.minimum(u_hi[candidates], width - 1) + 1
    (fx, fy), (cx, cy) = view.pinhole.focal_length_px, view.pinhole.principal_point_px
    R_camera_world = view.T_world_camera[:3, :3].T  # camera axes in the fixed frame
    eye_m = -R_camera_world @ view.T_world_camera[:3, 3]  # the camera's centre, fixed frame
    owner = _OwnPoints(view, points_m, spacing_m, origins_m, pictures, sight) if points_m is not None else None

    def entry(k: int, lines: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Where the rays through pixels (``lines``, ``cols``, int [P]) enter box ``k``: z-depth, [P]."""
        M = (T_box_world[k, :3, :3].T @ R_camera_world).astype(np.float32)  # camera axes -> box axes
        x = ((cols + (0.5 - cx)) * (1.0 / fx)).astype(np.float32)
        y = ((lines + (0.5 - cy)) * (1.0 / fy)).astype(np.float32)
        rays = [M[a, 0] * x + M[a, 1] * y + M[a, 2] for a in range(3)]  # box axes
        return slab_span(pictures.origin_m[k], rays, -half_m[k], half_m[k], 0.0, np.float32, leave=False)[0]

    for i, k in enumerate(candidates):
        r0, r1, c0, c1 = rectangles[i].tolist()
        if owner is not None and (kinds is None or kinds[k] == VEHICLE):
            key = None if covers is None or keys is None else keys[k]
            T_map_world = T_box_world[k]  # where the cover map lies
            pooled = None if shapes is None or keys is None else shapes.cover(keys[k], half_m[k], view.timestamp_us)
            if pooled is not None:  # the whole track's, where the frame's box holds it
                top, bottom, offset_m = pooled
                T_map_world = T_box_world[k].copy()
                T_map_world[:3, 3] -= T_box_world[k, :3, :3] @ offset_m
            else:
                made = None if key is None else covers.get(key)
                if made is None:  # this sweep's evidence alone
                    own = owner.of_box(k, T_box_world[k], half_m[k])
                    passed = None if sight is None else partial(owner.passed, T_box_world[k])
                    made = cover_map(half_m[k], own.local_m, own.spacing_m, own.origins_m, passed)
                    if key is not None:
                        covers[key] = made
                top, bottom = made
            hit = cover_picture(view, T_map_world, half_m[k], top, bottom, (r0, r1, c0, c1))
        else:
            # the ray through pixel (col, row) is x(col) X + y(row) Y + Z in camera axes; in the box's
            # axes each coordinate is a sum of a column term and a row term
            M = T_box_world[k, :3, :3].T @ R_camera_world  # camera axes -> box axes
            x = ((np.arange(c0, c1) + 0.5 - cx) / fx).astype(np.float32)
            y = ((np.arange(r0, r1) + 0.5 - cy) / fy).astype(np.float32)
            steps = [(M[a, 2] + M[a, 0] * x)[None, :] + (M[a, 1] * y)[:, None] for a in range(3)]  # [rows,cols]
            enter, leave = slab_span(pictures.origin_m[k], steps, -half_m[k], half_m[k], 0.0, np.float32)
            hit = enter <= leave
            if owner is not None and len((own := owner.of_box(k, T_box_world[k], half_m[k])).local_m):
                # a person, a rider, a post, a sign: where its own points are
                size_px = own.spacing_m / own.depth_m[:, None] * np.array([fx, fy])
                hit &= footprints(own.u_px - c0, own.v_px - r0, size_px, (r1 - r0, c1 - c0))
        window = index[r0:r1, c0:c1]
        shared = hit & (window >= 0)  # pixels another object's picture holds already
        if shared.any():  # the object in front holds them
            for other in np.flatnonzero(np.bincount(window[shared])).tolist():
                front = first_seen(eye_m, T_box_world[k], half_m[k], T_box_world[other], half_m[other])
                if front == 0:
                    continue
                theirs = shared & (window == other)
                if front is None:  # boxes that overlap (annotation error): the one each ray enters first
                    lines, cols = np.nonzero(theirs)
                    theirs[lines, cols] = entry(k, lines + r0, cols + c0) >= entry(other, lines + r0, cols + c0)
                hit &= ~theirs
        window[hit] = k
    if view.usable is not None:
        index[~view.usable] = -1
    # the boxes still holding a pixel of their rectangle once every box is in
    held = [
        i
        for i, (k, (r0, r1, c0, c1)) in enumerate(zip(candidates, rectangles.tolist(), strict=True))
        if np.any(index[r0:r1, c0:c1] == k)
    ]
    return BoxPicture(index, candidates[held], rectangles[held])


class _OwnPoints:
    """The lidar's points that lie in each box of a camera frame (:func:`box_index`), found through
    the boxes' pictures: a box's points project into its picture's rectangle."""

    def __init__(
        self,
        view: CameraView,
        points_m: np.ndarray,
        spacing_m: np.ndarray | None,
        origins_m: np.ndarray | None,
        pictures,
        sight,
    ) -> None:
        self._view = view
        self._points_m = points_m
        self._spacing_m = spacing_m
        self._origins_m = None if origins_m is None else np.asarray(origins_m, np.float64)
        self._pictures = pictures
        self._sight = sight

    def passed(self, T_box_world: np.ndarray, local_m: np.ndarray) -> np.ndarray:
        """Which places (a box's axes, ``T_box_world`` its pose, [M,3], m) a line of sight passed
        through (``sight.passed``), bool [M]."""
        return self._sight.passed(local_m @ T_box_world[:3, :3].T + T_box_world[:3, 3])

    def _project(self) -> None:
        """The points ahead of the camera, by image column: their rows, image points and depths."""
        view = self._view
        xyz = self._points_m @ view.T_world_camera[:3, :3].T + view.T_world_camera[:3, 3]
        ahead = np.flatnonzero(xyz[:, 2] > MIN_DEPTH_M)
        u, v = view.pinhole.project(xyz[ahead])
        order = np.argsort(u, kind="stable")
        self._rows, self._u, self._v = ahead[order], u[order], v[order]
        self._depth = xyz[ahead[order], 2]

    def of_box(self, k: int, T_box_world: np.ndarray, half_m: np.ndarray) -> OwnPoints:
        """Box ``k``'s own points (within ``OWN_MARGIN_M`` of it)."""
        if not hasattr(self, "_rows"):
            self._project()
        u_lo, u_hi, v_lo, v_hi = (a[k] for a in self._pictures.rectangle_px)
        span = slice(np.searchsorted(self._u, u_lo), np.searchsorted(self._u, u_hi + 1))
        near = np.flatnonzero((self._v[span] >= v_lo) & (self._v[span] < v_hi + 1)) + span.start
        local = (self._points_m[self._rows[near]] - T_box_world[:3, 3]) @ T_box_world[:3, :3]
        own = np.all(np.abs(local) <= half_m + OWN_MARGIN_M, axis=1)
        near = near[own]
        rows = self._rows[near]
        spacing = np.full((len(rows), 2), CELL_M) if self._spacing_m is None else self._spacing_m[rows]
        origins = self._origins_m
        if origins is not None:
            origins = ((origins[rows] if origins.ndim == 2 else origins) - T_box_world[:3, 3]) @ T_box_world[:3, :3]
        return OwnPoints(local[own], spacing, origins, self._u[near], self._v[near], self._depth[near])


@dataclass(frozen=True)
class OwnPoints:
    """One box's own points (:meth:`_OwnPoints.of_box`).

    Attributes:
        local_m: in the box's axes, [P,3], m; spacing_m: the lidar's spacing between neighbouring
            returns at each, across and along its rows, [P,2], m; origins_m: where the lidar was as
            it measured each, box axes, [P,3] or [3] (None: not known).
        u_px, v_px: where each shows in the camera's image, [P] each; depth_m: its camera z, [P], m.
    """

    local_m: np.ndarray
    spacing_m: np.ndarray
    origins_m: np.ndarray | None
    u_px: np.ndarray
    v_px: np.ndarray
    depth_m: np.ndarray


def footprints(u_px: np.ndarray, v_px: np.ndarray, size_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The pixels of a picture of ``shape`` (rows, columns) that points' footprints cover: each point at
    image point (``u_px``, ``v_px``), [P] each, covers a rectangle of ``size_px`` [P,2] (width, height)
    centred on it, a pixel more each way (the object's outline lies within half the lidar's spacing of
    its outermost returns). bool [rows, columns]."""
    half = size_px / 2.0 + 1.0
    return rectangles_cover(
        np.floor(v_px - half[:, 1]),
        np.floor(v_px + half[:, 1]),
        np.floor(u_px - half[:, 0]),
        np.floor(u_px + half[:, 0]),
        shape,
    )


def rectangles_cover(
    first_row: np.ndarray, last_row: np.ndarray, first_col: np.ndarray, last_col: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """The pixels of a picture of ``shape`` (rows, columns) that rectangles cover: each from row
    ``first_row`` to ``last_row`` and column ``first_col`` to ``last_col`` (whole pixels, inclusive,
    [R] each; clipped to the picture). bool [rows, columns]."""
    n_rows, n_cols = shape
    r0 = np.clip(first_row, 0, n_rows).astype(np.int64)
    r1 = np.clip(np.asarray(last_row) + 1, 0, n_rows).astype(np.int64)
    c0 = np.clip(first_col, 0, n_cols).astype(np.int64)
    c1 = np.clip(np.asarray(last_col) + 1, 0, n_cols).astype(np.int64)
    # each rectangle's corners, summed below; a pixel's sum counts the rectangles holding it, so the
    # narrowest integer that holds their number will do (a quarter of the memory traffic of int64)
    dtype = np.int16 if len(r0) < np.iinfo(np.int16).max else np.int32
    count = np.zeros((n_rows + 1, n_cols + 1), dtype)
    sign = np.ones(len(r0), dtype)
    np.add.at(count, (np.r_[r0, r0, r1, r1], np.r_[c0, c1, c0, c1]), np.r_[sign, -sign, -sign, sign])
    np.cumsum(count, axis=0, dtype=dtype, out=count)
    return np.cumsum(count, axis=1, dtype=dtype, out=count)[:n_rows, :n_cols] > 0


def cover_picture(
    view: CameraView,
    T_box_world: np.ndarray,
    half_m: np.ndarray,
    top: np.ndarray,
    bottom: np.ndarray,
    rectangle: tuple[int, int, int, int],
) -> np.ndarray:
    """The pixels of a box's picture (rows ``r0:r1``, columns ``c0:c1`` of ``rectangle``) that its
    :func:`objects.cores.cover_map` (``top``, ``bottom``) covers: the pixels whose centres lie in one of
    its columns' pictures (each column's bounding rectangle in the image: at most a column's slant
    more at an outline), bool [r1-r0, c1-c0].

    Args:
        T_box_world: the box -> fixed frame, float64 [4,4]; half_m: its half sizes, [3], m.
    """
    r0, r1, c0, c1 = rectangle
    centres, halves = cover_columns(half_m, top, bottom)
    R_camera_box = view.T_world_camera[:3, :3] @ T_box_world[:3, :3]
    t_camera_box = view.T_world_camera[:3, :3] @ T_box_world[:3, 3] + view.T_world_camera[:3, 3]
    corners = box_corners(
        np.broadcast_to(R_camera_box, (len(centres), 3, 3)), centres @ R_camera_box.T + t_camera_box, halves
    )
    ahead = np.any(corners[..., 2] > MIN_DEPTH_M, axis=1)
    corners = corners[ahead]
    corners[..., 2] = np.maximum(corners[..., 2], MIN_DEPTH_M)  # a column reaching behind the camera: its near end
    u, v = (a.reshape(-1, 8) for a in view.pinhole.project(corners.reshape(-1, 3)))
    return rectangles_cover(  # the pixels whose centres lie in a column's rectangle
        np.ceil(v.min(axis=1) - 0.5) - r0,
        np.floor(v.max(axis=1) - 0.5) - r0,
        np.ceil(u.min(axis=1) - 0.5) - c0,
        np.floor(u.max(axis=1) - 0.5) - c0,
        (r1 - r0, c1 - c0),
    )


def box_labels(picture: BoxPicture, instance_of_box: np.ndarray, dynamic_of_box: np.ndarray):
    """``segmentation.instance`` and ``mask.dynamic`` of a :func:`box_index` picture, written box
    by box within their rectangles.

    Args:
        instance_of_box: each box's instance index, int [K] (1 upwards); dynamic_of_box: each box's
            track moves, bool [K].

    Returns:
        uint16 [H,W] instance indices (0: none); bool [H,W] dynamic; the instances shown, sorted list.
    """
    instance = np.zeros(picture.index.shape, np.uint16)
    dynamic = np.zeros(picture.index.shape, bool)
    for k, (r0, r1, c0, c1) in zip(picture.shown.tolist(), picture.rectangles.tolist(), strict=True):
        own = picture.index[r0:r1, c0:c1] == k
        instance[r0:r1, c0:c1][own] = instance_of_box[k]
        if dynamic_of_box[k]:
            dynamic[r0:r1, c0:c1] |= own
    return instance, dynamic, sorted(int(instance_of_box[k]) for k in picture.shown)
