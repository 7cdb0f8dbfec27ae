"""A vehicle's shape from every sweep of its track, for its camera masks (issue 74).

One sweep sees a parked car's near side; the sweeps before and after see its front, its back, and
through the gaps beside it. Every sweep of a track lends the track's cover map
(:func:`cores.cover_map`) two kinds of evidence, in the box's own axes:

- **its own points** (the returns inside the box, within ``OWN_MARGIN_M``), with where the lidar was
  as it measured them: they show the object's tops and, through the lines of sight to the street
  under it, its underside. Kept one per ``KEEP_CELL_M`` voxel of the box: memory is bounded by the
  object's size, not by the log's length.
- **the places its lines of sight passed through** (:meth:`lidar.range_image.RangeImage.passed`):
  a voxel grid over the box (the cover map's ``CELL_M`` cells, ``LEVEL_M`` levels) marked where any
  sweep's line of sight passed. It cuts the generous car shape where one sweep never looked.

Which boxes pool, and how:

- a static track at its one median box (``dynamic.static_pose``: a parked car does not move,
  whatever its annotation's jitter), and every box of a simulator's exact ground truth (CARLA: each
  box is where its actor is at the tick): as they are;
- a moving track's annotated boxes: a human's, centimetres off from sweep to sweep, so each sweep's
  own points are first registered to those pooled so far (:func:`_registered`, a translation, point
  to plane) and pool only where they agree; a frame's map is moved by its nearest sweep's offset.
  A moving object's points are taken where its box was at their own times (a 100 ms sweep sees a
  car at 15 m/s move 1.5 m), and its free space where its box was when the lidar saw it.

Every own point of every pooled sweep covers its cell (:func:`cores.cover_map`): what any sweep saw
of the object is in every frame's mask (recall first; an opened door is covered all along).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ncore_convert.transforms.objects.boxes import PointGrid
from ncore_convert.transforms.objects.cores import CARVE_STEP_M, CELL_M, OWN_MARGIN_M, cover_map, footprint_cells

KEEP_CELL_M = 0.03  #: own points are kept one per voxel of this size (half a cover-map cell)
LEVEL_M = CARVE_STEP_M  #: the free-space grid's step in height (the cover map's carving step)
#: A box further than this from where the lidar was gathers no evidence: a VLP-32C's rows are 0.2-0.7 m
#: apart there, too sparse to show a car's shape (its frames keep their own sweep's map if no sweep
#: came nearer).
REACH_M = 40.0
#: A track whose boxes may jitter (annotations) registers each sweep's own points to those pooled so
#: far before adding them (:func:`_registered`: a translation, point to plane); the sweep agrees (and
#: pools) when at least ``MIN_PAIRS`` and half its points then lie within ``AGREE_M`` of the pooled
#: surfaces (about the returns' spread on a surface), its offset no longer than ``PAIR_M`` (an
#: annotation's error; a fit further off is another surface, not the same one moved).
PAIR_M = 0.3
ICP_STEPS = 8
NORMAL_NEIGHBOURS = 8
REGISTERED_POINTS = 400  #: a sweep's own points registered at most
RIDGE = 1e-4  #: per pair: a direction fixed by fewer than about this share of the pairs' normals stays put
MIN_PAIRS = 30
AGREE_M = 0.04


@dataclass
class _Track:
    """One track's evidence in its box's axes (see the module docstring)."""

    half_m: np.ndarray
    passed: np.ndarray  # bool [nx, ny, nz]
    own_m: list = field(default_factory=list)  # [P,3] arrays
    spacing_m: list = field(default_factory=list)  # [P,2]
    origins_m: list = field(default_factory=list)  # [P,3]
    kept: set = field(default_factory=set)  # the kept points' voxels (keys: :meth:`TrackShapes._keep`)
    normals: list = field(default_factory=list)  # [P,3] arrays: each kept point's surface normal (registering)
    sweeps: int = 0
    #: sweep time (µs) -> where the pooled shape lies in that sweep's box, box axes [3] (m), None where
    #: the sweep's points did not agree with it (its frames keep their own sweep's map)
    offsets: dict = field(default_factory=dict)


def _levels(half_m: np.ndarray) -> int:
    return max(1, int(np.ceil(2 * float(half_m[2]) / LEVEL_M)))


def _voxel_centres(half_m: np.ndarray) -> np.ndarray:
    """The free-space grid's voxel centres in the box's axes, float64 [nx, ny, nz, 3], m."""
    nx, ny = footprint_cells(half_m)
    axes = [(np.arange(n) + 0.5) * step - float(h) for n, step, h in ((nx, CELL_M, half_m[0]), (ny, CELL_M, half_m[1]))]
    z_m = (np.arange(_levels(half_m)) + 0.5) * LEVEL_M - float(half_m[2])
    return np.stack(np.meshgrid(*axes, z_m, indexing="ij"), axis=-1)


class TrackShapes:
    """The evidence of every gathered track (module docstring), keyed by track; lives as long as
    one log's (or one agent's) labelling. ``gather`` each sweep first, then label with
    :meth:`evidence` (the labeller's second pass)."""

    def __init__(self) -> None:
        self._tracks: dict = {}
        self._covers: dict = {}  # track -> its cover map, made once every sweep is gathered

    def gather(
        self,
        keys: list,
        T_box_world: np.ndarray,
        half_m: np.ndarray,
        points_m: np.ndarray,
        spacing_m: np.ndarray,
        origins_m: np.ndarray,
        sight,
        velocity_mps: np.ndarray | None = None,
        dt_s: np.ndarray | None = None,
        register: np.ndarray | None = None,
        time_us: int = 0,
    ) -> None:
        """Add one sweep's evidence of the boxes ``keys`` [K] (hashable), each where its object was as
        the sweep saw it: box -> fixed frame ``T_box_world`` [K,4,4], half sizes ``half_m`` [K,3], m.

        Args:
            points_m: the sweep's points, fixed frame, float64 [N,3]; spacing_m: the lidar's spacing
                between neighbouring returns at each, across and along its rows, [N,2], m.
            origins_m: where the lidar was as it measured each point, fixed frame, [N,3] or [3].
            sight: the sweep's lines of sight (``sight.passed(places [M,3], fixed frame) -> bool [M]``).
            velocity_mps: each box's velocity, fixed frame, [K,3], m/s (None: every box still), and
                dt_s: each point's time less the boxes' time, [N], s: a moving box's own points are
                found, and kept, where the box was at their times, and its free space looked up
                where it was at its own points' median time (none without own points: when the
                lidar looked at it is not known).
            register: which boxes may jitter against their objects (annotations), bool [K] (None:
                none): their sweeps are registered to the track's pooled points first, and pool only
                where they agree (``AGREE_M``); ``time_us``: the sweep's time, which the frames near
                it find their offset by (:meth:`cover`).
        """
        if not len(keys):
            return
        origins = np.broadcast_to(np.asarray(origins_m, np.float64), np.shape(points_m))
        middle_m = np.median(origins, axis=0) if len(origins) else np.zeros(3)
        points = PointGrid(points_m)
        velocity = np.zeros((len(keys), 3)) if velocity_mps is None else np.asarray(velocity_mps, np.float64)
        span_s = 0.0 if dt_s is None or not len(dt_s) else float(np.max(np.abs(dt_s)))
        jitters = np.zeros(len(keys), bool) if register is None else np.asarray(register, bool)
        for key, T, half, v, jittery in zip(keys, T_box_world, half_m, velocity, jitters, strict=True):
            if not np.isfinite(T).all() or np.linalg.norm(T[:3, 3] - middle_m) > REACH_M:
                continue
            moving = bool(np.any(v)) and dt_s is not None
            track = self._tracks.get(key)
            if track is None:
                grid = np.zeros((*footprint_cells(half), _levels(half)), bool)
                track = self._tracks[key] = _Track(np.array(half, np.float64), grid)
            elif not np.allclose(track.half_m, half, atol=0.01):  # another size: its voxels are not these
                continue
            track.sweeps += 1
            reach_m = float(np.linalg.norm(half + OWN_MARGIN_M)) + (
                float(np.linalg.norm(v)) * span_s if moving else 0.0
            )
            rows = points.near(T[:3, 3], reach_m)
            shift_m = np.outer(dt_s[rows], v) if moving else np.zeros((len(rows), 3))  # where the box was then
            local = (points_m[rows] - shift_m - T[:3, 3]) @ T[:3, :3]
            own = np.all(np.abs(local) <= half + OWN_MARGIN_M, axis=1)
            offset_m = np.zeros(3)
            if jittery:
                offset_m = _registered(track, local[own])
                track.offsets[int(time_us)] = offset_m
                if offset_m is None:  # its points do not agree with the track's: nothing pooled
                    continue
            origins_local = (origins[rows[own]] - shift_m[own] - T[:3, 3]) @ T[:3, :3]
            self._keep(track, local[own] + offset_m, spacing_m[rows[own]], origins_local + offset_m)
            if moving and not own.any():
                continue
            seen_at_m = T[:3, 3] + (float(np.median(dt_s[rows[own]])) * v if moving else 0.0)
            _look_down(
                track, lambda local_m, T=T, at=seen_at_m, off=offset_m: sight.passed((local_m - off) @ T[:3, :3].T + at)
            )

    @staticmethod
    def _keep(track: _Track, local_m: np.ndarray, spacing_m: np.ndarray, origins_m: np.ndarray) -> None:
        """Keep the own points ``local_m`` [P,3] (box axes) whose ``KEEP_CELL_M`` voxel holds none yet
        (a voxel's key: its three indices, 21 bits each)."""
        index = np.floor((local_m + track.half_m + OWN_MARGIN_M) / KEEP_CELL_M).astype(np.int64)
        keys = (index[:, 0] << 42) | (index[:, 1] << 21) | index[:, 2]
        keys, first = np.unique(keys, return_index=True)
        fresh = [i for i, key in enumerate(keys.tolist()) if key not in track.kept]
        if not fresh:
            return
        new = first[fresh]
        track.kept.update(keys[fresh].tolist())
        track.own_m.append(local_m[new])
        track.spacing_m.append(spacing_m[new])
        track.origins_m.append(origins_m[new])

    def cover(self, key, half_m: np.ndarray, t_us: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Track ``key``'s :func:`cores.cover_map` from every gathered sweep, for its box of half
        sizes ``half_m`` ([3], m) at time ``t_us``: (top, bottom) [nx, ny] each, and the registration
        offset of the sweep nearest ``t_us`` (box axes, [3], m; 0 for a track that does not register):
        the map lies at minus it in that box. None where no sweep was gathered for it, for a box of
        another size, or near a sweep whose points did not agree. Made once per track."""
        if key not in self._covers:
            pooled = self.evidence(key)
            self._covers[key] = (
                None
                if pooled is None
                else cover_map(pooled.half_m, pooled.own_m, pooled.spacing_m, pooled.origins_m, pooled.passed)
            )
        track = self._tracks.get(key)
        if track is None or self._covers[key] is None or not np.allclose(track.half_m, half_m, atol=0.01):
            return None
        offset_m = np.zeros(3)
        if track.offsets:
            times = np.array(list(track.offsets))
            offset_m = track.offsets[int(times[np.argmin(np.abs(times - t_us))])]
            if offset_m is None:
                return None
        return (*self._covers[key], offset_m)

    def evidence(self, key) -> TrackEvidence | None:
        """The gathered evidence of track ``key`` (None: none gathered)."""
        track = self._tracks.get(key)
        if track is None or not track.sweeps:
            return None
        stack = lambda parts, width: np.concatenate(parts) if parts else np.zeros((0, width))  # noqa: E731
        return TrackEvidence(
            track.half_m, track.passed, stack(track.own_m, 3), stack(track.spacing_m, 2), stack(track.origins_m, 3)
        )


def _look_down(track: _Track, passed) -> None:
    """Mark the voxels a sweep's lines of sight passed through, column by column from the top down
    (``passed(places [M,3], the track's box axes) -> bool [M]``). A cover map's column is cut down to
    its highest place no line passed through (``cores._carved``): what lies below that place does not
    change it, so each column looks only at its highest voxel not yet passed, and on down while this
    sweep passed through it. A place below that voxel counts as not passed (recall first: an
    overhang the lines of sight passed under stays covered)."""
    nx, ny, nz = track.passed.shape
    highest = nz - 1 - np.argmax(~track.passed[:, :, ::-1], axis=2)  # each column's highest voxel not passed
    highest[track.passed.all(axis=2)] = -1
    centres = _voxel_centres(track.half_m)
    columns = np.flatnonzero(highest.reshape(-1) >= 0)
    while len(columns):
        i, j = np.unravel_index(columns, (nx, ny))
        k = highest[i, j]
        through = passed(centres[i, j, k])
        if not through.any():
            return
        track.passed[i[through], j[through], k[through]] = True
        highest[i[through], j[through]] -= 1
        columns = columns[through][highest[i[through], j[through]] >= 0]


def _registered(track: _Track, local_m: np.ndarray) -> np.ndarray | None:
    """Where a sweep's own points ``local_m`` (its box's axes, [P,3], m) lie against the track's pooled
    points: the offset [3] that moves them onto the pooled surfaces (0 for the track's first points),
    None where they do not agree (see ``AGREE_M``).

    Point to plane: each point is paired with its nearest pooled point within ``PAIR_M``, and the
    offset is the least-squares shift along the pooled surfaces' normals (each pooled point's from
    its ``NORMAL_NEIGHBOURS`` nearest: the smallest principal axis), ``ICP_STEPS`` times. A shift
    along a surface is not seen by it (a flank does not fix a car's length): what no surface fixes
    stays 0 (``RIDGE`` on the normal equations)."""
    if not track.own_m:
        return np.zeros(3) if len(local_m) else None
    if len(local_m) > REGISTERED_POINTS:  # evenly thinned: the fit needs the surfaces, not every return
        local_m = local_m[np.linspace(0, len(local_m) - 1, REGISTERED_POINTS).astype(np.int64)]
    pooled = np.concatenate(track.own_m)
    if len(local_m) < MIN_PAIRS or len(pooled) < NORMAL_NEIGHBOURS:
        return None
    tree = cKDTree(pooled)
    done = sum(len(n) for n in track.normals)  # the points kept since the last registration need theirs
    _, neighbours = tree.query(pooled[done:], k=NORMAL_NEIGHBOURS)
    around = pooled[neighbours] - pooled[neighbours].mean(axis=1, keepdims=True)
    track.normals.append(np.linalg.eigh(np.einsum("pki,pkj->pij", around, around))[1][:, :, 0])  # smallest axis
    normals = np.concatenate(track.normals)
    offset = np.zeros(3)
    for _ in range(ICP_STEPS + 1):
        distance, nearest = tree.query(local_m + offset, distance_upper_bound=PAIR_M)
        paired = np.flatnonzero(np.isfinite(distance))
        if len(paired) < MIN_PAIRS:
            return None
        n = normals[nearest[paired]]
        off_plane = np.einsum("ij,ij->i", n, local_m[paired] + offset - pooled[nearest[paired]])
        if _ == ICP_STEPS:
            close = np.abs(off_plane) <= AGREE_M
            agree = close.sum() >= MIN_PAIRS and close.sum() >= 0.5 * len(local_m)
            return offset if agree and np.linalg.norm(offset) <= PAIR_M else None  # beyond: not a jitter
        A = n.T @ n + RIDGE * len(paired) * np.eye(3)
        offset -= np.linalg.solve(A, n.T @ off_plane)
    return None


@dataclass(frozen=True)
class TrackEvidence:
    """One track's pooled evidence (:meth:`TrackShapes.evidence`), box axes.

    Attributes:
        half_m: the box's half sizes the grid is laid on, [3], m.
        passed_grid: where a line of sight of some sweep passed, bool [nx, ny, nz].
        own_m: the kept own points, [P,3], m; spacing_m: the lidar's spacing at each, [P,2], m;
            origins_m: where the lidar was as it measured each, [P,3], m.
    """

    half_m: np.ndarray
    passed_grid: np.ndarray
    own_m: np.ndarray
    spacing_m: np.ndarray
    origins_m: np.ndarray

    def passed(self, local_m: np.ndarray) -> np.ndarray:
        """Which places (box axes, [M,3], m) some sweep's line of sight passed through: their voxel's
        mark; False outside the box. bool [M]."""
        shape = self.passed_grid.shape
        steps = np.array([CELL_M, CELL_M, LEVEL_M])
        index = np.floor((local_m + self.half_m) / steps).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(shape)), axis=1)
        out = np.zeros(len(local_m), bool)
        out[inside] = self.passed_grid[tuple(index[inside].T)]
        return out
