"""Which tracks move, and which lidar points lie on them: the per-point ``dynamic_flag``.

The rule (docs/consumers.md, "Dynamic tracks"):

- A track is dynamic when its NCore class is always dynamic (``labels.ALWAYS_DYNAMIC``: pedestrians,
  riders, animals, ...) or when it **moved further than annotation noise can carry a parked box**.
  Always-static classes (``labels.ALWAYS_STATIC``: signs, cones, barriers, bollards) never are.
- Human-annotated boxes of a parked car wander: on the real AV2 sample the centres of the parked
  cars stay within 0.1-1.4 m of their median and their two ends lie at most 1.8 m apart, while
  their paths zig-zag 1-4.5 m in total, so any speed taken from them reads 0.3-1 m/s. What jitter
  cannot do is carry a box far away and keep it there. So, on the track's box centres in a fixed
  frame (median-filtered over ``MEDIAN_WINDOW`` observations, so that one or two stray boxes count
  for nothing):

  - ``net_m``: the distance between the median centre of its first ``END_WINDOW_S`` and of its
    last (a quarter of the track each, if it is shorter than 2 s); dynamic above ``NET_DYNAMIC_M``;
  - ``peak_deviation_m``: the largest distance of a centre from the track's median centre (a car
    that drives off and comes back); dynamic above ``DEVIATION_DYNAMIC_M``.

  Both thresholds sit in the gap the real sample shows between jitter (net <= 1.8 m, deviation
  <= 1.4 m) and driving (net >= 5 m, but one 2.6 m track), below a creeper's 4 m (0.5 m/s for
  8 s). Motion below them is not told from jitter: such a track is static.
- Measured speeds replace the boxes where every observation of a track carries one (OPV2V/V2XSet:
  CARLA's exact speed): dynamic when the largest exceeds ``DYNAMIC_SPEED_MPS`` (1 km/h).
- A static track's boxes are noise around one pose: :func:`static_pose` is its median box.
- A point is dynamic when, at its own timestamp, it lies inside the box of a dynamic track grown by
  ``BOX_MARGIN_M`` on every side. The box at a point's time: its centre interpolated linearly between
  the track's observations (extended up to ``HOLD_S`` beyond the first and last), its rotation and
  size those of the nearest observation.

Points and boxes are in one fixed frame (``world`` or ``world_global``), metres; times in µs.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ncore_convert.transforms.geometry import sorted_run_starts
from ncore_convert.transforms.objects.boxes import PointGrid, in_box
from ncore_convert.transforms.objects.classes import ALWAYS_DYNAMIC, ALWAYS_STATIC

DYNAMIC_SPEED_MPS = 1.0 / 3.6  #: 1 km/h, for measured speeds
NET_DYNAMIC_M = 3.0  #: net displacement beyond any parked car's jitter (real sample: <= 1.8 m)
DEVIATION_DYNAMIC_M = 2.5  #: distance from the median beyond any parked car's jitter (real: <= 1.4 m)
END_WINDOW_S = 0.5  #: the start and the end of a track are the medians over this long
BOX_MARGIN_M = 0.5
MEDIAN_WINDOW = 5
HOLD_S = 0.15
CLASS_DECIDES = ALWAYS_DYNAMIC | ALWAYS_STATIC  #: classes whose motion the boxes do not decide


@dataclass(frozen=True)
class TrackObservations:
    """Cuboid observations in a fixed frame, columnar.

    Attributes:
        track_ids: str [M]; timestamps_us: int64 [M]; centers_m: box centres [M,3];
        R_box_frame: box rotations [M,3,3] (box axes -> fixed frame); dims_m: (length, width, height) [M,3].
        speeds_mps: measured speed of each observation [M] (NaN where none), or None.
    """

    track_ids: list[str]
    timestamps_us: np.ndarray
    centers_m: np.ndarray
    R_box_frame: np.ndarray
    dims_m: np.ndarray
    speeds_mps: np.ndarray | None = None


@dataclass(frozen=True)
class TrackMotion:
    """How one track moved (see the module docstring).

    Attributes:
        dynamic: the decision; net_m, peak_deviation_m: the box figures (metres);
        max_speed_mps: the largest measured speed, or None when the boxes decided.
    """

    dynamic: bool
    net_m: float
    peak_deviation_m: float
    max_speed_mps: float | None = None

    def as_meta(self) -> dict:
        """The figures as the cuboids' metadata records them."""
        out = {"net_m": round(self.net_m, 3), "peak_deviation_m": round(self.peak_deviation_m, 3)}
        return out if self.max_speed_mps is None else {**out, "max_speed_mps": round(self.max_speed_mps, 3)}


def _median_filtered(centers_m: np.ndarray) -> np.ndarray:
    """Component-wise running median over MEDIAN_WINDOW observations (shrinking at the ends), [K,3]."""
    n, half = len(centers_m), MEDIAN_WINDOW // 2
    if n < 3:
        return centers_m
    padded = np.concatenate([np.repeat(centers_m[:1], half, 0), centers_m, np.repeat(centers_m[-1:], half, 0)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, MEDIAN_WINDOW, axis=0)  # [K,3,W]
    return np.median(windows, axis=-1)


def box_motion(timestamps_us: np.ndarray, centers_m: np.ndarray) -> tuple[float, float]:
    """(net displacement, peak deviation from the median) of one track's boxes, metres.

    Args:
        timestamps_us: the track's observation times, int64 [K], increasing.
        centers_m: its box centres in a fixed frame, float64 [K,3].
    """
    t_s = (np.asarray(timestamps_us, dtype=np.int64) - int(timestamps_us[0])) * 1e-6
    smooth = _median_filtered(np.asarray(centers_m, dtype=np.float64))
    window_s = min(END_WINDOW_S, float(t_s[-1]) / 4)  # a short track's ends must not overlap
    first = np.median(smooth[t_s <= window_s], axis=0)
    last = np.median(smooth[t_s >= t_s[-1] - window_s], axis=0)
    deviation = np.linalg.norm(smooth - np.median(smooth, axis=0), axis=1)
    return float(np.linalg.norm(last - first)), float(deviation.max())


def track_motion(timestamps_us: np.ndarray, centers_m: np.ndarray, speeds_mps: np.ndarray | None) -> TrackMotion:
    """One track's figures and decision (its class aside), from measured speeds [K] when every
    observation has one, else from its boxes (arguments as in :func:`box_motion`)."""
    net, deviation = box_motion(timestamps_us, centers_m)
    if speeds_mps is not None and len(speeds_mps) and np.all(np.isfinite(speeds_mps)):
        top = float(np.max(speeds_mps))
        return TrackMotion(top > DYNAMIC_SPEED_MPS, net, deviation, top)
    return TrackMotion(net > NET_DYNAMIC_M or deviation > DEVIATION_DYNAMIC_M, net, deviation)


def by_track(ids: np.ndarray, timestamps_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Observations grouped by track, each track by time: the row order [M], and the group bounds
    (track k is ``order[bounds[k]:bounds[k+1]]``), int64 [T+1].

    Args:
        ids: track id per observation, str [M]; timestamps_us: int [M].
    """
    order = np.lexsort((timestamps_us, ids))
    starts = sorted_run_starts(ids[order])
    return order, np.append(np.zeros(0, np.int64) if starts is None else starts, len(order)).astype(np.int64)


def static_pose(centers_m: np.ndarray, R_box_frame: np.ndarray, dims_m: np.ndarray) -> tuple[np.ndarray, ...]:
    """The median box of a static track's observations: the component-wise median centre [3] and
    size [3] (metres), and the medoid rotation [3,3] (the observed one with the least summed angle
    to the others, so a flipped box or two cannot turn it).

    Args:
        centers_m: [K,3]; R_box_frame: [K,3,3]; dims_m: [K,3], in one fixed frame.
    """
    traces = np.einsum("aij,bij->ab", R_box_frame, R_box_frame)  # trace(Ra^T Rb) = 1 + 2 cos(angle)
    angles = np.arccos(np.clip((traces - 1.0) / 2.0, -1.0, 1.0))
    medoid = int(np.argmin(angles.sum(axis=1)))
    return np.median(centers_m, axis=0), R_box_frame[medoid], np.median(dims_m, axis=0)


def _tracks(observations: TrackObservations) -> Iterator[tuple[str, np.ndarray]]:
    """(track id, its rows in time order) of every track in ``observations``."""
    ids = np.asarray(observations.track_ids, dtype=object).astype(str)
    order, bounds = by_track(ids, np.asarray(observations.timestamps_us))
    for start, end in zip(bounds[:-1], bounds[1:], strict=True):
        rows = order[start:end]
        yield str(ids[rows[0]]), rows


def classify_tracks(observations: TrackObservations, classes: list[str]) -> dict[str, TrackMotion]:
    """Track id -> its motion and decision, for every track (see the module docstring).

    Args:
        observations: the log's boxes in a fixed frame; classes: the NCore class of each [M].
    """
    out = {}
    for track_id, rows in _tracks(observations):
        speeds = None if observations.speeds_mps is None else observations.speeds_mps[rows]
        motion = track_motion(observations.timestamps_us[rows], observations.centers_m[rows], speeds)
        cls = classes[rows[0]]
        out[track_id] = replace(motion, dynamic=cls in ALWAYS_DYNAMIC) if cls in CLASS_DECIDES else motion
    return out


def static_poses(observations: TrackObservations, static_ids: set[str]) -> dict[str, tuple[np.ndarray, ...]]:
    """Track id -> :func:`static_pose` of each track in ``static_ids``."""
    return {
        track_id: static_pose(observations.centers_m[rows], observations.R_box_frame[rows], observations.dims_m[rows])
        for track_id, rows in _tracks(observations)
        if track_id in static_ids
    }


@dataclass(frozen=True)
class DynamicBoxes:
    """The observations of the dynamic tracks, grouped by track and sorted by time.

    Attributes:
        bounds: track k's rows are ``bounds[k]:bounds[k+1]``, int [T+1].
        timestamps_us: int64 [M]; centers_m: [M,3]; R_box_frame: [M,3,3];
        half_extent_m: half the box size, grown by a margin (BOX_MARGIN_M for ``dynamic_flag``), [M,3].
        reach_m: per track, the largest distance from its centre to a grown corner, [T].
        speed_mps: per track, the largest speed between consecutive observations, [T].
        track_ids: per track, its id, str [T].
    """

    bounds: np.ndarray
    timestamps_us: np.ndarray
    centers_m: np.ndarray
    R_box_frame: np.ndarray
    half_extent_m: np.ndarray
    reach_m: np.ndarray
    speed_mps: np.ndarray
    track_ids: np.ndarray

    @classmethod
    def select(
        cls, observations: TrackObservations, dynamic: Collection[str], margin_m: float = BOX_MARGIN_M
    ) -> DynamicBoxes:
        """The observations of the ``dynamic`` tracks (their ids), boxes grown by ``margin_m``."""
        ids = np.asarray(observations.track_ids, dtype=object).astype(str)
        keep = np.flatnonzero(np.isin(ids, list(dynamic)))
        order, bounds = by_track(ids[keep], observations.timestamps_us[keep])
        keep = keep[order]
        centers = observations.centers_m[keep]
        half = observations.dims_m[keep] / 2 + margin_m
        times = observations.timestamps_us[keep].astype(np.int64)
        reach = np.array(
            [np.linalg.norm(half[a:b], axis=1).max() for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        )
        step_speed = np.zeros(len(bounds) - 1)
        for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            if b - a > 1:
                dt_s = np.maximum(np.diff(times[a:b]) * 1e-6, 1e-6)
                step_speed[k] = float((np.linalg.norm(np.diff(centers[a:b], axis=0), axis=1) / dt_s).max())
        track_ids = ids[keep][bounds[:-1]]
        return cls(bounds, times, centers, observations.R_box_frame[keep], half, reach, step_speed, track_ids)

    def __len__(self) -> int:
        return len(self.bounds) - 1

    @cached_property
    def _track_time_key(self) -> tuple[np.ndarray, int, int]:
        """Every row's (track, time) as one ascending int64 key, track * length + (time - t0) [M]; t0; length."""
        times = self.timestamps_us
        t0, length = int(times.min()), int(times.max() - times.min()) + 1
        return np.repeat(np.arange(len(self), dtype=np.int64), np.diff(self.bounds)) * length + (times - t0), t0, length

    def at(self, t_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The tracks observed at ``t_us`` (up to ``HOLD_S`` beyond their ends), int [K]; their centres
        then, as :func:`_centres_at` gives them, [K,3]; and the row of each one's nearest observation, int [K]."""
        hold_us = round(HOLD_S * 1e6)
        first, last = self.bounds[:-1], self.bounds[1:] - 1
        start_us, end_us = self.timestamps_us[first] - hold_us, self.timestamps_us[last] + hold_us
        tracks = np.flatnonzero((start_us <= t_us) & (t_us <= end_us))
        if not len(tracks):
            return tracks, np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        a, b = first[tracks], last[tracks] + 1
        single = b - a == 1
        # the observation at or before t_us within each track (one bisection over (track, time) keys),
        # kept off the track's last so that a segment follows it
        key, t0, length = self._track_time_key
        before = np.searchsorted(key, tracks * length + min(max(t_us - t0, 0), length - 1), side="right") - 1
        i = np.clip(before, a, np.maximum(b - 2, a))
        j = np.where(single, i, i + 1)
        span = np.where(single, 1, self.timestamps_us[j] - self.timestamps_us[i])
        alpha = np.where(single, 0.0, (t_us - self.timestamps_us[i]) / span)
        centres = self.centers_m[i] + alpha[:, None] * (self.centers_m[j] - self.centers_m[i])
        return tracks, centres, np.where(alpha < 0.5, i, j)


VELOCITY_SPAN_US = 100_000  #: a moving vehicle's velocity is its track's motion over this span


def static_boxes(static: dict[str, tuple[np.ndarray, ...]]) -> tuple[np.ndarray, np.ndarray]:
    """The static tracks' boxes (``static``: track id -> :func:`static_pose`): box -> fixed frame,
    float64 [S,4,4], and half sizes, m [S,3], in ``static``'s order."""
    T = np.tile(np.eye(4), (len(static), 1, 1))
    half = np.zeros((len(static), 3))
    for k, (centre, R, dims) in enumerate(static.values()):
        T[k, :3, :3], T[k, :3, 3], half[k] = R, centre, dims / 2
    return T, half


@dataclass(frozen=True)
class SolidBoxes:
    """The labelled objects as solid occluders (lidar colouring): each static track at its median box
    (:func:`static_pose`: a parked car's annotation jitter averaged out), each moving track where its
    box is at a given time.

    Attributes:
        static_T_box_frame: box -> fixed frame, float64 [S,4,4]; static_half_m: half sizes [S,3].
        moving: the other tracks' observations, not grown.
        track_ids: every track's id, the static ones first (in ``static_T_box_frame``'s order),
            then the moving ones (in ``moving``'s), str [S+T].
        kind: the kind of solid each track's object is (:func:`cores.kind_of`; -1: its box hides
            nothing), int [S+T].
    """

    static_T_box_frame: np.ndarray
    static_half_m: np.ndarray
    moving: DynamicBoxes
    track_ids: np.ndarray
    kind: np.ndarray

    @classmethod
    def select(
        cls,
        observations: TrackObservations,
        static: dict[str, tuple[np.ndarray, ...]],
        dynamic: Collection[str],
        kinds: dict[str, int] | None = None,
    ) -> SolidBoxes:
        """``static``: track id -> :func:`static_pose` of the static tracks (as :func:`static_poses`
        gives them); ``dynamic``: the ids of the moving tracks, taken from ``observations``;
        ``kinds``: track id -> the kind of solid its object is (:func:`cores.kind_of`; missing: -1)."""
        T, half = static_boxes(static)
        moving = DynamicBoxes.select(observations, dynamic, margin_m=0.0)
        track_ids = np.concatenate([np.array(list(static), dtype=str), moving.track_ids])
        kind = np.array([(kinds or {}).get(str(t), -1) for t in track_ids], dtype=np.int64)
        return cls(T, half, moving, track_ids, kind)

    def solids_at(self, t_us: int) -> tuple[np.ndarray, ...]:
        """The boxes at ``t_us`` of the objects with solid parts, the occluders (:mod:`cores`): box ->
        fixed frame [V,4,4], half sizes [V,3], velocity, m/s [V,3] (a moving track's over
        ``VELOCITY_SPAN_US`` around ``t_us``; 0 for a static one) and kind, int [V]."""
        tracks, T, half, velocity = self.moving_at(t_us)
        kind = self.kind[tracks]
        solid = kind >= 0
        return T[solid], half[solid], velocity[solid], kind[solid]

    def moving_at(self, t_us: int) -> tuple[np.ndarray, ...]:
        """:meth:`tracks_at` (tracks [K], box -> fixed frame [K,4,4], half sizes [K,3]) and each box's
        velocity, m/s [K,3]: a moving track's over ``VELOCITY_SPAN_US`` around ``t_us`` (0 where it
        is not observed on both sides), 0 for a static one."""
        tracks, T, half = self.tracks_at(t_us)
        velocity = np.zeros((len(tracks), 3))
        n_static = len(self.static_T_box_frame)
        before, centres_before, _ = self.moving.at(t_us - VELOCITY_SPAN_US // 2)
        after, centres_after, _ = self.moving.at(t_us + VELOCITY_SPAN_US // 2)
        both, i, j = np.intersect1d(before, after, return_indices=True)
        rate = (centres_after[j] - centres_before[i]) / (VELOCITY_SPAN_US * 1e-6)
        moving = np.flatnonzero(tracks >= n_static)
        known = np.isin(tracks[moving] - n_static, both)
        velocity[moving[known]] = rate[np.searchsorted(both, tracks[moving[known]] - n_static)]
        return tracks, T, half, velocity

    def tracks_at(self, t_us: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The boxes at ``t_us``: each one's track (index into ``track_ids``), int [K]; box -> fixed
        frame [K,4,4]; half sizes [K,3]. A moving track's centre is interpolated, its rotation and size
        the nearest observation's, while it is observed (up to ``HOLD_S`` beyond its ends)."""
        tracks, centres, nearest = self.moving.at(t_us)
        T_moving = np.tile(np.eye(4), (len(tracks), 1, 1))
        T_moving[:, :3, :3], T_moving[:, :3, 3] = self.moving.R_box_frame[nearest], centres
        n_static = len(self.static_T_box_frame)
        return (
            np.concatenate([np.arange(n_static), n_static + tracks]),
            np.concatenate([self.static_T_box_frame, T_moving]),
            np.concatenate([self.static_half_m, self.moving.half_extent_m[nearest]]),
        )


def dynamic_flags(xyz_m: np.ndarray, timestamps_us: np.ndarray, boxes: DynamicBoxes) -> np.ndarray:
    """1 where a point lies, at its own time, in a dynamic track's grown box; else 0.

    Args:
        xyz_m: points in the boxes' fixed frame at their own times, float64 [N,3].
        timestamps_us: each point's time, int [N].
        boxes: the dynamic tracks (:meth:`DynamicBoxes.select`).

    Returns:
        int8 [N].
    """
    flags = np.zeros(len(xyz_m), dtype=np.int8)
    if not len(xyz_m) or not len(boxes):
        return flags
    t_us = np.asarray(timestamps_us, dtype=np.int64)
    t_lo, t_hi = int(t_us.min()), int(t_us.max())
    hold_us = round(HOLD_S * 1e6)
    points = PointGrid(xyz_m)
    for k in range(len(boxes)):
        a, b = int(boxes.bounds[k]), int(boxes.bounds[k + 1])
        times = boxes.timestamps_us[a:b]
        if times[-1] + hold_us < t_lo or times[0] - hold_us > t_hi:
            continue
        # cull: only points near the track's centre during the frame can be inside
        mid = _centres_at(times, boxes.centers_m[a:b], np.array([(t_lo + t_hi) // 2]))[0][0]
        near = points.near(mid, boxes.reach_m[k] + boxes.speed_mps[k] * (t_hi - t_lo) * 1e-6 + 1e-3)
        if not len(near):
            continue
        t_near = t_us[near]
        alive = (t_near >= times[0] - hold_us) & (t_near <= times[-1] + hold_us)
        near, t_near = near[alive], t_near[alive]
        centres, nearest = _centres_at(times, boxes.centers_m[a:b], t_near)
        inside = in_box(xyz_m[near], centres, boxes.R_box_frame[a:b][nearest], boxes.half_extent_m[a:b][nearest])
        flags[near[inside]] = 1
    return flags


def _centres_at(times_us: np.ndarray, centers_m: np.ndarray, t_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One track's centre at times ``t_us`` [Q] (linear between observations, and beyond the ends
    along the end segments), [Q,3], and the index of the nearest observation, int [Q]."""
    if len(times_us) == 1:
        return np.repeat(centers_m, len(t_us), axis=0), np.zeros(len(t_us), dtype=np.int64)
    i = np.clip(np.searchsorted(times_us, t_us, side="right") - 1, 0, len(times_us) - 2)
    alpha = (t_us - times_us[i]) / (times_us[i + 1] - times_us[i])
    centres = centers_m[i] + alpha[:, None] * (centers_m[i + 1] - centers_m[i])
    return centres, np.where(alpha < 0.5, i, i + 1)
