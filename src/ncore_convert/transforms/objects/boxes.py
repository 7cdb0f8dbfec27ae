"""The box-geometry kernel: every oriented-box computation of the project is written here once.

- :func:`box_corners`: a box's 8 corners (``CORNER_SIGNS`` order) and :func:`box_edges` its 12 edges;
- :func:`near_plane_crossings`: where the edges cross a camera's near plane (a box partly behind
  the camera is pictured by its corners ahead and these crossings);
- :func:`slab_span`: where rays enter and leave a box (the slab test), vectorised over rays;
- :func:`convex_span`: the same for convex solids of any faces (a shape's parts), vectorised over
  rays and solids;
- :func:`first_seen`: which of two boxes apart in space a viewer sees in front (the separating-axis test);
- :class:`PointGrid`, :func:`in_box` and :func:`points_in_box`: which points lie in a box.

Boxes are given by their rotation ``R_box_frame`` (box axes -> frame), centre and half sizes in
metres; rays by their origin and direction in the box's own axes.
"""

from __future__ import annotations

import numpy as np

#: The 8 corners of a box as signs of its half sizes, x outermost: (-,-,-), (-,-,+), (-,+,-), ... float64 [8,3].
CORNER_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
#: The 12 edges, as pairs of indices into ``CORNER_SIGNS`` (corners that differ in one sign), int [12,2].
BOX_EDGES = np.array(
    [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(CORNER_SIGNS[i] != CORNER_SIGNS[j]) == 1]
)


def box_corners(R_box_frame: np.ndarray, centre_m: np.ndarray, half_m: np.ndarray) -> np.ndarray:
    """The corners of boxes in their frame, float64 [K,8,3] (``CORNER_SIGNS`` order).

    Args:
        R_box_frame: box axes -> frame, [K,3,3]; centre_m: [K,3]; half_m: half sizes, [K,3] (m).
    """
    return np.einsum("kij,kcj->kci", R_box_frame, CORNER_SIGNS[None] * half_m[:, None]) + centre_m[:, None]


def box_edges(corners_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The start and end of each box's 12 edges (``BOX_EDGES``), [K,12,3] each, from its corners [K,8,3]."""
    return corners_m[:, BOX_EDGES[:, 0]], corners_m[:, BOX_EDGES[:, 1]]


def near_plane_crossings(corners_m: np.ndarray, near_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each box's edges cross the plane z = ``near_m`` of a camera (corners in the camera frame,
    z forward, [K,8,3]): the points on the plane, float64 [K,12,3], and which edges cross it (their
    ends on either side, not touching it), bool [K,12]; the points of the other edges are meaningless."""
    start, end = box_edges(corners_m)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = (near_m - start[..., 2]) / (end[..., 2] - start[..., 2])
        return start + f[..., None] * (end - start), (f > 0) & (f < 1)


def slab_span(origin_m, directions, lo_m, hi_m, enter_from: float = -np.inf, dtype=np.float64, leave: bool = True):
    """Where rays enter and leave the box ``lo_m`` <= p <= ``hi_m`` (the slab test): the ray
    parameters ``enter`` and ``leave`` (a ray's point is origin + s * direction, s in units of its
    direction's length) between which the ray is inside every axis's slab. A ray meets the box where
    ``enter <= leave``; ``enter_from`` = 0 counts only what lies ahead of the origin.

    Each argument is taken axis by axis, ``arg[k]`` for k = 0, 1, 2 (``np.moveaxis(a, -1, 0)`` of an
    array [...,3]), in the box's axes and metres:

    Args:
        origin_m: the rays' origins: per axis a scalar or an array broadcastable to the rays' shape.
        directions: the rays' directions, per axis an array of (or broadcastable to) the rays' shape;
            a direction 0 along an axis (the ray parallel to its slab) is handled.
        lo_m, hi_m: the box's lowest and highest corner, per axis a scalar (or an array as origin_m).
        dtype: of the results (the accumulation; each ray parameter is computed in its inputs' type).
        leave: False: only ``enter`` is wanted (``leave`` is returned as None), at half the work.

    Returns:
        enter, leave: [rays' shape] each.
    """
    shape = np.broadcast_shapes(*(np.shape(directions[k]) for k in range(3)))
    enter = np.full(shape, enter_from, dtype)
    out = np.full(shape, np.inf, dtype) if leave else None
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(3):
            inverse = 1.0 / directions[k]
            t_lo, t_hi = (lo_m[k] - origin_m[k]) * inverse, (hi_m[k] - origin_m[k]) * inverse
            np.fmax(enter, np.fmin(t_lo, t_hi), out=enter)  # fmax/fmin skip the NaN of a ray in a slab's plane
            if leave:
                np.fmin(out, np.fmax(t_lo, t_hi), out=out)
    return enter, out


def convex_span(origin_m, directions: np.ndarray, normals: np.ndarray, offsets_m: np.ndarray):
    """Where rays enter and leave convex solids, each the points p with n . p <= offset for every
    face (n, offset) of it: the slab test for faces of any direction, vectorised over rays and solids.
    A ray meets a solid where ``enter <= leave``; a ray parallel to a face outside it never does.

    Args:
        origin_m: the rays' origins, float [K,3], or one shared origin [3]; directions: [K,3]; both
            in the solids' frame, metres (a point is origin + s * direction).
        normals: each solid's outward face normals, float [P,F,3]; offsets_m: float [P,F] (a face
            with normal 0 and offset 1 is padding: every point is inside it).

    Returns:
        enter, leave: the ray parameters, float64 [K,P] each.
    """
    rise = np.einsum("kc,pfc->kpf", directions, normals)  # how fast each ray crosses each face
    room = offsets_m[None] - np.einsum("...c,pfc->...pf", origin_m, normals)  # how far inside each face it starts
    with np.errstate(divide="ignore", invalid="ignore"):
        s = room / rise
    enter = np.where(rise < 0, s, -np.inf).max(axis=-1)
    leave = np.where(rise > 0, s, np.inf).min(axis=-1)
    outside = np.any((rise == 0) & (room < 0), axis=-1)
    return enter, np.where(outside, -np.inf, leave)


def first_seen(
    eye_m: np.ndarray, T_a_frame: np.ndarray, half_a_m: np.ndarray, T_b_frame: np.ndarray, half_b_m: np.ndarray
) -> int | None:
    """Which of two boxes apart in space is in front, seen from ``eye_m`` [3]: 0 (box a) or 1 (box b),
    on every ray from there that meets both; None when the boxes overlap (touching counts as overlap).

    The separating-axis test: a plane normal to one of the 15 axes (the boxes' 6 and the 9 products
    of one's with the other's) separates them, and a ray from the eye meets the box on the eye's
    side of it first, since it crosses the plane once.

    Args:
        eye_m: where the rays start, [3]; T_a_frame, T_b_frame: box -> frame, float64 [4,4];
        half_a_m, half_b_m: half sizes, [3], m; all in one frame.
    """
    A, B = T_a_frame[:3, :3], T_b_frame[:3, :3]
    axes = np.concatenate([A.T, B.T, np.cross(A.T[:, None], B.T[None]).reshape(9, 3)])
    axes = axes[np.linalg.norm(axes, axis=1) > 1e-9]  # parallel edges: their faces' axes decide
    a_m, b_m = axes @ T_a_frame[:3, 3], axes @ T_b_frame[:3, 3]
    reach_a_m, reach_b_m = np.abs(axes @ A) @ half_a_m, np.abs(axes @ B) @ half_b_m
    gap_m = np.abs(b_m - a_m) - reach_a_m - reach_b_m  # along each axis (in units of its length)
    j = int(np.argmax(gap_m))
    if gap_m[j] <= 0:
        return None
    axis = axes[j] if a_m[j] <= b_m[j] else -axes[j]  # from a towards b
    plane_m = (axis @ T_a_frame[:3, 3] + reach_a_m[j] + axis @ T_b_frame[:3, 3] - reach_b_m[j]) / 2  # mid-gap
    return 0 if axis @ eye_m <= plane_m else 1


#: Side of the grid columns points are bucketed into (metres; wider where the points spread over more
#: than ``GRID_COLUMNS`` columns along an axis).
GRID_CELL_M = 2.0
GRID_COLUMNS = 255  #: at most this many columns per axis, so that a column index fits uint16


COLUMN_SLACK = 1e-9  #: of a column: how far PointGrid.near widens its column range against rounding


class PointGrid:
    """Points bucketed once into square columns on the frame's x-y plane, so that each box looks
    only at the points in the columns its square covers: the one prefilter of every points-in-box
    test (dynamic flags, the synthetic annotations' interior counts, the validator's counts).

    Args:
        xyz_m: points in the boxes' frame, float [N,3] (non-finite points are never near anything).
    """

    def __init__(self, xyz_m: np.ndarray) -> None:
        self.xyz_m = xyz_m
        finite = None
        axes = [xyz_m[:, 0], xyz_m[:, 1]]  # axis by axis: reductions over [N,2] columns are several times slower
        lo, hi = _extremes(axes)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):  # only then look point by point
            finite = np.isfinite(axes[0]) & np.isfinite(axes[1])
            axes = [a[finite] for a in axes]
            lo, hi = _extremes(axes)
        self._lo = lo
        self._cell = np.maximum(GRID_CELL_M, (hi - lo) / (GRID_COLUMNS - 1) * (1 + 1e-9))
        self._shape = np.minimum(((hi - lo) / self._cell).astype(np.int64) + 1, GRID_COLUMNS)
        # offsets from the minimum are >= 0, so truncation is the floor
        i, j = (
            np.minimum(((a - lo[k]) * (1.0 / self._cell[k])).astype(np.int64), self._shape[k] - 1)
            for k, a in enumerate(axes)
        )
        column = (i * self._shape[1] + j).astype(np.uint16)
        if finite is None:
            cells = column
        else:
            cells = np.full(len(xyz_m), self._shape[0] * self._shape[1], dtype=np.uint16)  # beyond the grid
            cells[finite] = column
        self._order = np.argsort(cells, kind="stable")  # a radix sort on uint16
        counts = np.bincount(cells, minlength=self._shape[0] * self._shape[1] + 1)
        self._starts = np.concatenate([[0], np.cumsum(counts)])

    def near(self, centre_m: np.ndarray, reach_m: float) -> np.ndarray:
        """The rows within ``reach_m`` of ``centre_m`` [3] along every axis, int [K] (in no particular
        order): a box whose every point is within ``reach_m`` of its centre has no other."""
        centre_xy = np.asarray(centre_m[:2], dtype=np.float64)
        if not (np.isfinite(centre_xy).all() and np.isfinite(reach_m)):  # a NaN box holds no point
            return np.zeros(0, dtype=np.int64)
        # the columns are a superset: widened by a billionth of a column, since centre +- reach rounds
        # differently from the exact test's |point - centre| (a point at 1e-203 m, a centre at -1/3 m
        # and a reach of 1/3 m: -1/3 + 1/3 is 0.0, yet |1e-203 + 1/3| rounds to 1/3)
        lo = np.floor((centre_xy - reach_m - self._lo) * (1.0 / self._cell) - COLUMN_SLACK)
        hi = np.floor((centre_xy + reach_m - self._lo) * (1.0 / self._cell) + COLUMN_SLACK)
        lo, hi = np.maximum(lo, 0).astype(np.int64), np.minimum(hi, self._shape - 1).astype(np.int64)
        if np.any(hi < lo):
            return np.zeros(0, dtype=np.int64)
        ny = self._shape[1]
        spans = [
            self._order[self._starts[i * ny + lo[1]] : self._starts[i * ny + hi[1] + 1]]
            for i in range(lo[0], hi[0] + 1)
        ]
        rows = np.concatenate(spans)
        return rows[np.all(np.abs(self.xyz_m[rows] - centre_m) <= reach_m, axis=1)]


def _extremes(axes: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(min, max) of each coordinate array, float64 [2] each (zeros without points)."""
    if not len(axes[0]):
        return np.zeros(2), np.zeros(2)
    return np.array([float(a.min()) for a in axes]), np.array([float(a.max()) for a in axes])


def in_box(xyz_m: np.ndarray, centre_m: np.ndarray, R_box_frame: np.ndarray, half_m: np.ndarray) -> np.ndarray:
    """Whether points lie inside boxes (faces included), bool [K].

    Args:
        xyz_m: the points, float [K,3]; centre_m: the box centre [3], or each point's box's [K,3];
        R_box_frame: the box rotation (box axes -> frame) [3,3], or each point's [K,3,3];
        half_m: half the box size [3], or each point's box's [K,3]; all in one frame, metres.
    """
    offset = xyz_m - centre_m
    local = offset @ R_box_frame if R_box_frame.ndim == 2 else np.einsum("nji,nj->ni", R_box_frame, offset)
    return np.all(np.abs(local) <= half_m, axis=1)


def points_in_box(points: PointGrid, centre_m: np.ndarray, R_box_frame: np.ndarray, half_m: np.ndarray) -> np.ndarray:
    """The rows of ``points`` inside one box (faces included), int [K]: the grid's columns the box
    can reach, then :func:`in_box`.

    Args:
        centre_m: [3]; R_box_frame: box axes -> frame [3,3]; half_m: half sizes [3]; frame and
            metres of ``points``.
    """
    near = points.near(centre_m, float(np.linalg.norm(half_m)))  # no point further is inside
    return near[in_box(points.xyz_m[near], centre_m, R_box_frame, half_m)]


def count_in_box_band(
    points: PointGrid, centre_m: np.ndarray, R_box_frame: np.ndarray, half_m: np.ndarray, margin_m: float
) -> tuple[int, int]:
    """How many of ``points`` lie inside one box shrunk by ``margin_m`` on every face, and inside it
    grown by ``margin_m`` (faces included): (inner, outer), inner <= outer. A point that may have
    moved by up to ``margin_m`` was inside the box for inner <= n <= outer of the counts n it could
    give; with ``margin_m`` 0 both are the :func:`in_box` count.

    Args:
        centre_m: [3]; R_box_frame: box axes -> frame [3,3]; half_m: half sizes [3]; frame and metres
            of ``points``; margin_m: >= 0, metres.
    """
    near = points.near(centre_m, float(np.linalg.norm(half_m + margin_m)))
    local = np.abs((points.xyz_m[near] - centre_m) @ R_box_frame)
    outer = np.all(local <= half_m + margin_m, axis=1)
    inner = np.all(local[outer] <= half_m - margin_m, axis=1)
    return int(inner.sum()), int(outer.sum())
