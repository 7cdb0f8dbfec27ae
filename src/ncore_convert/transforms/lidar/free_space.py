"""What moves, from the lidar alone: a point is on a mover when, at another time, the lidar saw through
the place where it was (free-space carving; docs/motion.md).

The test of one place against one other sweep (:class:`SweepSight`) is a bracket: a spinning lidar
samples the world on rows (its beams) and columns (its firing steps), so a place lies between two
rows and two columns of every sweep that looked its way. If all four of those rays ended beyond the
place, any surface there larger than their spacing would have stopped one of them: the place was
empty then. One ray beyond a place proves nothing: on a surface seen at a grazing angle (the road,
a roof) the nearest ray lands a metre further along the same surface; its neighbour on the other side
lands before the place. A ray without a return proves nothing either (a dark or glossy surface may
return nothing), nor does a bracket whose rays end before the place (it was hidden then).

A point with such evidence marks its object: :func:`flag_sweep` groups a sweep's points off the
ground into objects (depth clustering in the sweep's own image, :func:`objects`) and flags every
point of an object that enough of its points prove moved; an object too few of whose points other
sweeps had in view is not judged (``SweepFlags.unknown``). The ground never moves.
``motion_window.MotionWindow`` streams the sweeps and carries movers between neighbouring ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ncore_convert.transforms.lidar.range_image import nearest_per_cell

#: A column of a sweep's image: the VLP-32C fires a cycle every 0.199 degrees at 10 Hz.
COLUMN_RAD = np.radians(0.2)
#: All four rays of a bracket must end this far beyond the place, and this share of its range (the
#: returns' noise, AV2's float16 coordinates: 1.6 cm at 30 m, and the pose's drift within a window).
BEYOND_M = 0.25
BEYOND_FRACTION = 0.02
#: The largest gap between two rows (or columns) that still brackets a place, radians: a VLP-32C's
#: widest rows are 3-4 degrees apart.
MAX_ROW_GAP_RAD = np.radians(5.0)


class SweepSight:
    """One lidar unit's sweep as its rows and columns saw it.

    Args:
        points_m: the returns, fixed frame, float64 [N,3].
        origins_m: where the unit was as it measured each, fixed frame, float64 [N,3].
        beams: each return's beam (laser) index, int [N]; the rows are the beams ordered by elevation.
    """

    def __init__(self, points_m: np.ndarray, origins_m: np.ndarray, beams: np.ndarray) -> None:
        sight = np.asarray(points_m, np.float64) - origins_m
        range_m = np.linalg.norm(sight, axis=1)
        elevation = np.arcsin(np.clip(sight[:, 2] / np.maximum(range_m, 1e-9), -1.0, 1.0))
        beam_of, n_rows = _rank(np.asarray(beams, np.int64))
        beam_el = np.bincount(beam_of, elevation, n_rows) / np.maximum(np.bincount(beam_of, minlength=n_rows), 1)
        order = np.argsort(beam_el)
        row_of_beam = np.empty(n_rows, np.int64)
        row_of_beam[order] = np.arange(n_rows)
        row = row_of_beam[beam_of]
        self.row_elevation_rad = beam_el[order]  # each row's mean elevation, increasing [R]
        self._n_cols = int(np.ceil(2 * np.pi / COLUMN_RAD))
        col = self._column(np.arctan2(sight[:, 1], sight[:, 0]))
        self._middle_m = np.median(origins_m, axis=0) if len(origins_m) else np.zeros(3)
        self._range_m = nearest_per_cell(row * self._n_cols + col, range_m, max(n_rows, 1) * self._n_cols)
        # where the unit was as it looked along each column, and its attitude there (the rows' offset
        # from their median elevation)
        counts = np.bincount(col, minlength=self._n_cols)
        self._origin_m = np.tile(self._middle_m, (self._n_cols, 1))
        seen = counts > 0
        for axis in range(3):
            self._origin_m[seen, axis] = np.bincount(col, origins_m[:, axis], self._n_cols)[seen] / counts[seen]
        offset = elevation - (self.row_elevation_rad[row] if n_rows else 0.0)
        self._offset_rad = np.zeros(self._n_cols)
        self._offset_rad[seen] = np.bincount(col, offset, self._n_cols)[seen] / counts[seen]
        self._n_rows = n_rows
        self.points_m = np.asarray(points_m, np.float64)
        self.row, self.col, self.range_m = row, col, range_m

    @property
    def n_cols(self) -> int:
        """Columns in a turn."""
        return self._n_cols

    def _column(self, azimuth_rad: np.ndarray) -> np.ndarray:
        return ((azimuth_rad + np.pi) / COLUMN_RAD).astype(np.int64) % self._n_cols

    def bracket(self, xyz_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The four rays around each place ``xyz_m`` (fixed frame, [M,3]): the ranges where the rows
        above and below it in the columns either side ended (m [M,4]; NaN: no return there, or no
        such rows within ``MAX_ROW_GAP_RAD``), and the place's own range from where the lidar looked
        (m [M])."""
        xyz_m = np.asarray(xyz_m, np.float64)
        ends = np.full((len(xyz_m), 4), np.nan)
        if self._n_rows < 2 or not len(xyz_m):
            return ends, np.zeros(len(xyz_m))
        sight = xyz_m - self._middle_m
        origin = self._origin_m[self._column(np.arctan2(sight[:, 1], sight[:, 0]))]  # where it looked from
        sight = xyz_m - origin
        range_m = np.linalg.norm(sight, axis=1)
        azimuth = np.arctan2(sight[:, 1], sight[:, 0])
        elevation = np.arcsin(np.clip(sight[:, 2] / np.maximum(range_m, 1e-9), -1.0, 1.0))
        left = np.floor((azimuth + np.pi) / COLUMN_RAD - 0.5).astype(np.int64)  # the columns' centres either side
        for c, col in enumerate((left % self._n_cols, (left + 1) % self._n_cols)):
            el = elevation - self._offset_rad[col]
            above = np.searchsorted(self.row_elevation_rad, el)
            inside = (above > 0) & (above < self._n_rows)
            above = np.clip(above, 1, self._n_rows - 1)
            gap = self.row_elevation_rad[above] - self.row_elevation_rad[above - 1]
            usable = inside & (gap <= MAX_ROW_GAP_RAD)
            for k, r in enumerate((above - 1, above)):
                ends[:, 2 * c + k] = np.where(usable, self._range_m[r * self._n_cols + col], np.nan)
        return ends, range_m

    def passed(self, xyz_m: np.ndarray) -> np.ndarray:
        """Which places ``xyz_m`` (fixed frame, [M,3]) this sweep saw through: the four rays around
        each (:meth:`bracket`) all ended beyond it (``BEYOND_M`` and ``BEYOND_FRACTION``). bool [M]."""
        return _beyond(*self.bracket(xyz_m))

    def seen_at(self, xyz_m: np.ndarray) -> np.ndarray:
        """Which places ``xyz_m`` (fixed frame, [M,3]) this sweep saw something at: the four rays
        around each all ended there (within ``BEYOND_M`` and ``BEYOND_FRACTION``). bool [M]."""
        return _at(*self.bracket(xyz_m))


def _beyond(ends_m: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Whether all four rays of each bracket (``SweepSight.bracket``) ended beyond its place, bool [M]."""
    return np.all(ends_m > (range_m * (1.0 + BEYOND_FRACTION) + BEYOND_M)[:, None], axis=1)  # NaN: False


def _at(ends_m: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Whether all four rays of each bracket ended at its place, bool [M]."""
    return np.all(np.abs(ends_m - range_m[:, None]) <= (range_m * BEYOND_FRACTION + BEYOND_M)[:, None], axis=1)


def _in_view(ends_m: np.ndarray, range_m: np.ndarray) -> np.ndarray:
    """Whether all four rays of each bracket reached its place (ended at it or beyond): that sweep could
    judge it. A ray that ended before it (it was hidden) or returned nothing judges nothing. bool [M]."""
    return np.all(ends_m >= (range_m * (1.0 - BEYOND_FRACTION) - BEYOND_M)[:, None], axis=1)  # NaN: False


#: Returns this far over the ground are tested (a line of sight that grazes the street proves nothing
#: of a place just over it) ...
GROUND_CLEARANCE_M = 0.2
#: ... and returns this far over it may belong to an object (a car's wheels and sills, a pedestrian's
#: feet), joined to it where they make one surface with it (:func:`objects`).
OBJECT_CLEARANCE_M = 0.05
GROUND_CELL_M = 2.0  #: the ground's height: the lowest returns per cell of this size
#: An object moved if at least this many of its points, and this share, were seen through.
MIN_EVIDENCE = 3
#: How many returns of an object are tested (spread over it): the share of them seen through decides.
SAMPLES_PER_OBJECT = 24
MIN_EVIDENCE_SHARE = 0.1
#: An object is judged when other sweeps had this share of its tested returns in view (:func:`_in_view`).
JUDGED_SHARE = 0.5
#: An object is settled when the farthest sweeps saw this share of its tested returns at their places:
#: a car parked beside a passing one is not carried with it (``motion_window.follow``).
SETTLED_SHARE = 0.5


def ground_clearance_m(xyz_m: np.ndarray) -> np.ndarray:
    """Each point's height over the ground under it, m [N] (fixed frame, z up; float64 [N,3]): the
    ground is the lowest return within a cell of ``GROUND_CELL_M`` either way (a cell of its own may
    hold no ground: the lidar's low rows are far apart, and a pedestrian shades the street behind it)."""
    cell = np.floor(xyz_m[:, :2] / GROUND_CELL_M).astype(np.int64)
    if not len(cell):
        return np.zeros(0)
    cell -= cell.min(axis=0)
    shape = tuple(cell.max(axis=0) + 1)
    flat = cell[:, 0] * shape[1] + cell[:, 1]  # flat indices: ufunc.at and gathers are several times faster
    lowest = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(lowest, flat, xyz_m[:, 2])
    ground = ndimage.minimum_filter(lowest.reshape(shape), size=3, mode="nearest").ravel()
    return xyz_m[:, 2] - ground[flat]


#: Two neighbouring returns (rows or columns) are one surface when the line between them leans at
#: least this much from the farther one's line of sight (Bogoslavskyi and Stachniss's depth
#: clustering: a gap in depth between objects makes it flat).
SURFACE_ANGLE_RAD = np.radians(10.0)
#: ... and lie at most this much apart in depth (the lidar's widest rows are 4 degrees apart, where
#: the angle alone joins a car to a wall a few metres behind it).
JOIN_DEPTH_M = 0.5
JOIN_DEPTH_FRACTION = 0.05


def objects(sight: SweepSight, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which object (int >= 0; -1: none) each return of ``sight`` in ``candidates`` (bool [N])
    belongs to: the returns joined through neighbouring cells of its image (the next column, the
    next row) whose depths make one surface (``SURFACE_ANGLE_RAD``), int [N]; and which returns
    lie on a surface that faces the lidar (joined to the row above or below: a wall, a car's side),
    not one it grazes (a roof at the lidar's height), bool [N]."""
    n_cols, n_rows = sight.n_cols, len(sight.row_elevation_rad)
    label = np.full(len(candidates), -1, np.int64)
    facing = np.zeros(len(candidates), bool)
    idx = np.flatnonzero(candidates)
    if not len(idx):
        return label, facing
    cell = sight.row[idx] * n_cols + sight.col[idx]
    size = n_rows * n_cols
    rng = nearest_per_cell(cell, sight.range_m[idx], size).reshape(n_rows, n_cols)
    gaps = np.diff(sight.row_elevation_rad)
    edges = []
    for a, b, alpha in (
        (rng, np.roll(rng, -1, axis=1), np.full((n_rows, 1), COLUMN_RAD)),
        (rng[:-1], rng[1:], gaps[:, None]),
    ):
        near, gap = np.minimum(a, b), np.abs(a - b)  # NaN (an empty cell): no edge
        beta = np.arctan2(near * np.sin(alpha), near + gap - near * np.cos(alpha))
        edges.append((beta > SURFACE_ANGLE_RAD) & (gap <= JOIN_DEPTH_M + JOIN_DEPTH_FRACTION * near))  # NaN: False
    flat = np.arange(size).reshape(n_rows, n_cols)
    src = np.concatenate([flat[edges[0]], flat[:-1][edges[1]]])
    dst = np.concatenate([np.roll(flat, -1, axis=1)[edges[0]], flat[1:][edges[1]]])
    graph = coo_matrix((np.ones(len(src), bool), (src, dst)), shape=(size, size))
    _, component = connected_components(graph, directed=False)
    label[idx] = component[cell]
    upright = np.zeros((n_rows, n_cols), bool)
    upright[1:] |= edges[1]  # joined to the row below
    upright[:-1] |= edges[1]  # joined to the row above
    facing[idx] = upright.ravel()[cell]
    return label, facing


def _flanks(sight: SweepSight, picks: np.ndarray) -> np.ndarray:
    """The returns beside each of ``picks`` (indices into ``sight``'s returns) in its row, the columns
    either side, int [M,2] (-1: none there).

    At an object's vertical edge, a bracket of another sweep may lie across the edge with its inner
    rays on a face that recedes from that sweep's lidar: they end beyond the place although the face
    is there. That happens a column or two wide; a place a mover left is seen through across its face,
    so a return's evidence counts only where its neighbours either side have evidence too."""
    n_cols = sight.n_cols
    at = np.full((max(len(sight.row_elevation_rad), 1), n_cols), -1, np.int64)
    at[sight.row, sight.col] = np.arange(len(sight.row))
    row, col = sight.row[picks], sight.col[picks]
    return np.stack([at[row, (col - 1) % n_cols], at[row, (col + 1) % n_cols]], axis=1)


def _rank(ids: np.ndarray) -> tuple[np.ndarray, int]:
    """Each of ``ids`` (non-negative ints [N], a beam's laser number) as its rank among the distinct
    ones, int [N], and how many there are (``np.unique``'s inverse, without its sort)."""
    present = np.bincount(ids) > 0 if len(ids) else np.zeros(0, bool)
    rank = np.cumsum(present) - 1
    return rank[ids], int(present.sum())


def _grouped(label: np.ndarray) -> np.ndarray:
    """The order that groups ``label`` (non-negative ints below 2**32 [N]) by value, stable: a radix
    sort of two 16-bit passes (numpy sorts 16-bit keys by radix; a stable sort of int64 keys is a
    merge sort, seven times slower on a sweep's objects), int [N]."""
    low = np.argsort((label & 0xFFFF).astype(np.uint16), kind="stable")
    return low[np.argsort((label[low] >> 16).astype(np.uint16), kind="stable")]


def _samples(label: np.ndarray, n_objects: int) -> np.ndarray:
    """Up to about ``SAMPLES_PER_OBJECT`` returns of each object (``label`` [N], -1: none), spread
    over it: indices, int [M]."""
    members = np.flatnonzero(label >= 0)
    members = members[_grouped(label[members])]  # grouped by object, in order
    size = np.bincount(label[members], minlength=n_objects)
    first = np.concatenate([[0], np.cumsum(size)[:-1]])
    of = label[members]
    rank = np.arange(len(members)) - first[of]
    step = np.maximum(size // SAMPLES_PER_OBJECT, 1)
    return members[rank % step[of] == 0]


@dataclass
class SweepFlags:
    """What :func:`flag_sweep` found for one sweep's returns (its units' in order).

    Attributes:
        points_m: the returns, fixed frame, float64 [N,3].
        objects: which object each return belongs to (-1: the ground), int [N].
        dynamic: on a mover, bool [N].
        samples: up to ``SAMPLES_PER_OBJECT`` returns of each object, spread over all of it, int [M]: what
            ``motion_window.follow`` compares (an object none of whose returns were tested, a car's sills and
            wheels under 0.2 m, is carried all the same).
        settled: on an object other sweeps saw at its place (``SETTLED_SHARE`` of its samples), bool [N]:
            it is not carried from a mover next to it (``motion_window.follow``).
        unknown: on an object no other sweep could judge: fewer than ``JUDGED_SHARE`` of its samples were
            in view of one (hidden, between the rows, beyond the range), or none was tested, bool [N].
            ``not_judged`` leaves out the movers found all the same.
        followable: per object, whether ``motion_window.follow`` may carry it: some of its returns were tested (off
            the ground, facing the lidar), or it has ``MIN_EVIDENCE`` returns at least, bool [objects].
    """

    points_m: np.ndarray
    objects: np.ndarray
    dynamic: np.ndarray
    samples: np.ndarray
    settled: np.ndarray
    unknown: np.ndarray
    followable: np.ndarray

    @property
    def not_judged(self) -> np.ndarray:
        """The returns whose motion is not known: on an object no other sweep could judge, and not
        flagged (found from a mover next to it), bool [N]."""
        return self.unknown & ~self.dynamic

    def unit_parts(self, own: list[SweepSight], values: np.ndarray) -> list[np.ndarray]:
        """``values`` (one per return, [N]) split by unit (``own``: the units the sweep was made of)."""
        bounds = np.cumsum([0] + [len(unit.points_m) for unit in own])
        return [values[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def flag_sweep(
    own: list[SweepSight], others: list[list[SweepSight]], far: list[list[SweepSight]] | None = None
) -> SweepFlags:
    """The movers among one sweep's returns (``own``: its units), from the sweeps ``others`` (each a
    list of its units' :class:`SweepSight`): every return of an object enough of whose sampled returns
    (``SAMPLES_PER_OBJECT``; ``MIN_EVIDENCE``, ``MIN_EVIDENCE_SHARE``) other sweeps saw through, and
    the returns either side of them too (:func:`_flanks`)."""
    xyz = np.concatenate([unit.points_m for unit in own])
    bounds = np.cumsum([0] + [len(unit.points_m) for unit in own])
    clearance_m = ground_clearance_m(xyz)
    label = np.full(len(xyz), -1, np.int64)
    facing = np.zeros(len(xyz), bool)
    n_objects = 0
    for unit, a, b in zip(own, bounds[:-1], bounds[1:], strict=True):
        part, facing[a:b] = objects(unit, clearance_m[a:b] > OBJECT_CLEARANCE_M)
        label[a:b] = np.where(part >= 0, part + n_objects, -1)
        n_objects += int(part.max()) + 1 if len(part) else 0
    # tested: the returns off the ground on surfaces that face the lidar (a line of sight along a roof
    # at the lidar's height lands beyond the place beside it)
    picks = _samples(np.where((clearance_m > GROUND_CLEARANCE_M) & facing, label, -1), n_objects)
    flanks = np.full((len(picks), 2), -1, np.int64)
    for unit, a, b in zip(own, bounds[:-1], bounds[1:], strict=True):
        mine = (picks >= a) & (picks < b)
        beside = _flanks(unit, picks[mine] - a)
        flanks[mine] = np.where(beside >= 0, beside + a, -1)
    seen_through = np.zeros(len(xyz), bool)
    seen_at = np.zeros(len(xyz), bool)
    in_view = np.zeros(len(picks), bool)
    far_ids = {id(units) for units in far or []}
    for units in others:  # the samples; against the farthest sweeps, whether they were seen at their places
        for sight in units:
            ends_m, range_m = sight.bracket(xyz[picks])
            seen_through[picks] |= _beyond(ends_m, range_m)
            in_view |= _in_view(ends_m, range_m)
            if id(units) in far_ids:
                seen_at[picks] |= _at(ends_m, range_m)
    beside = flanks[seen_through[picks]]  # then the returns beside those seen through
    beside = np.unique(beside[beside >= 0])
    for units in others:
        for sight in units:
            seen_through[beside] |= sight.passed(xyz[beside])
    evidence = seen_through[picks] & (flanks >= 0).all(axis=1) & seen_through[flanks].all(axis=1)
    size = np.bincount(label[picks], minlength=n_objects)
    hits = np.bincount(label[picks], evidence, n_objects)
    moving = (hits >= MIN_EVIDENCE) & (hits >= MIN_EVIDENCE_SHARE * size)
    # settled: seen at its place, so tested (an object none of whose returns were tested is not)
    settled = (size > 0) & (np.bincount(label[picks], seen_at[picks], n_objects) >= SETTLED_SHARE * size)
    judged = np.bincount(label[picks], in_view, n_objects) >= JUDGED_SHARE * np.maximum(size, 1)
    on_object = label >= 0
    of = np.maximum(label, 0)
    return SweepFlags(
        xyz,
        label,
        on_object & moving[of],
        _samples(label, n_objects),
        on_object & settled[of],
        on_object & ~moving[of] & ~judged[of],
        # an object none of whose returns were tested (a car's sills under 0.2 m, an edge no row joins)
        # may be carried too, unless it is a fragment of fewer returns than an object needs to be
        # flagged on its own: that is no shape to follow (two returns of a parked car beside a passing
        # one lie within a metre of it as well; the real AV2 sample has one)
        (size > 0) | (np.bincount(label[on_object], minlength=n_objects) >= MIN_EVIDENCE),
    )
