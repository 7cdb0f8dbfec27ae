"""Which tracks move, and which lidar points lie on them: the per-point ``dynamic_flag``.

The rule (NCore's Waymo converter, and docs/consumers.md):

- A track is dynamic when its NCore class is always dynamic (``labels.ALWAYS_DYNAMIC``: pedestrians,
  riders, animals, ...), or when its robust speed exceeds 1 km/h anywhere in the log. Always-static
  classes (``labels.ALWAYS_STATIC``: signs, cones, barriers, bollards) never are.
- Robust speed: the track's box centres in a fixed frame are median-filtered over
  ``MEDIAN_WINDOW`` observations (one or two stray observations cannot move a parked car), then the
  speed is the displacement over a baseline of at least ``SPEED_BASELINE_S`` (annotation jitter of a
  few centimetres between frames does not add up to a speed). A track seen for less than
  ``MIN_SPAN_S`` has no measurable speed (speed 0).
- A point is dynamic when, at its own timestamp, it lies inside the box of a dynamic track grown by
  ``BOX_MARGIN_M`` on every side. The box at a point's time: its centre interpolated linearly between
  the track's observations (extended up to ``HOLD_S`` beyond the first and last), its rotation and
  size those of the nearest observation.

Points and boxes are in one fixed frame (``world`` or ``world_global``), metres; times in µs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ncore_convert.transforms.geometry import sorted_run_starts
from ncore_convert.transforms.labels import ALWAYS_DYNAMIC, ALWAYS_STATIC

DYNAMIC_SPEED_MPS = 1.0 / 3.6  #: 1 km/h
BOX_MARGIN_M = 0.5
MEDIAN_WINDOW = 5
SPEED_BASELINE_S = 2.0
MIN_SPAN_S = 0.3
HOLD_S = 0.15


@dataclass(frozen=True)
class TrackObservations:
    """Cuboid observations in a fixed frame, columnar.

    Attributes:
        track_ids: str [M]; timestamps_us: int64 [M]; centers_m: box centres [M,3];
        R_box_frame: box rotations [M,3,3] (box axes -> fixed frame); dims_m: (length, width, height) [M,3].
    """

    track_ids: list[str]
    timestamps_us: np.ndarray
    centers_m: np.ndarray
    R_box_frame: np.ndarray
    dims_m: np.ndarray


def _median_filtered(centers_m: np.ndarray) -> np.ndarray:
    """Component-wise running median over MEDIAN_WINDOW observations (shrinking at the ends), [K,3]."""
    n, half = len(centers_m), MEDIAN_WINDOW // 2
    if n < 3:
        return centers_m
    padded = np.concatenate([np.repeat(centers_m[:1], half, 0), centers_m, np.repeat(centers_m[-1:], half, 0)])
    windows = np.lib.stride_tricks.sliding_window_view(padded, MEDIAN_WINDOW, axis=0)  # [K,3,W]
    return np.median(windows, axis=-1)


def robust_speed_mps(timestamps_us: np.ndarray, centers_m: np.ndarray) -> float:
    """The largest speed of one track over the log (see the module docstring).

    Args:
        timestamps_us: the track's observation times, int64 [K], increasing.
        centers_m: its box centres in a fixed frame, float64 [K,3].
    """
    t_s = (np.asarray(timestamps_us, dtype=np.int64) - int(timestamps_us[0])) * 1e-6
    if len(t_s) < 2 or t_s[-1] < MIN_SPAN_S:
        return 0.0
    smooth = _median_filtered(np.asarray(centers_m, dtype=np.float64))
    baseline_s = min(SPEED_BASELINE_S, float(t_s[-1]))
    later = np.searchsorted(t_s, t_s + baseline_s - 1e-9)
    ok = later < len(t_s)
    i, j = np.flatnonzero(ok), later[ok]
    speeds = np.linalg.norm(smooth[j] - smooth[i], axis=1) / (t_s[j] - t_s[i])
    return float(speeds.max(initial=0.0))


def _by_track(ids: np.ndarray, timestamps_us: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Observations grouped by track, each track by time: the row order [M], and the group bounds
    (track k is ``order[bounds[k]:bounds[k+1]]``), int64 [T+1].

    Args:
        ids: track id per observation, str [M]; timestamps_us: int [M].
    """
    order = np.lexsort((timestamps_us, ids))
    starts = sorted_run_starts(ids[order])
    return order, np.append(np.zeros(0, np.int64) if starts is None else starts, len(order)).astype(np.int64)


def dynamic_tracks(
    track_ids: list[str], classes: list[str], timestamps_us: np.ndarray, centers_m: np.ndarray
) -> dict[str, float]:
    """Track id -> robust speed (m/s) of every dynamic track.

    Args:
        track_ids, classes: per observation [M] (NCore class names).
        timestamps_us: int64 [M]; centers_m: box centres in a fixed frame, float64 [M,3].
    """
    ids = np.asarray(track_ids, dtype=object).astype(str)
    order, bounds = _by_track(ids, np.asarray(timestamps_us))
    out = {}
    for start, end in zip(bounds[:-1], bounds[1:], strict=True):
        rows = order[start:end]
        cls = classes[rows[0]]
        if cls in ALWAYS_STATIC:
            continue
        speed = robust_speed_mps(np.asarray(timestamps_us)[rows], np.asarray(centers_m)[rows])
        if cls in ALWAYS_DYNAMIC or speed > DYNAMIC_SPEED_MPS:
            out[str(ids[rows[0]])] = round(speed, 4)
    return out


@dataclass(frozen=True)
class DynamicBoxes:
    """The observations of the dynamic tracks, grouped by track and sorted by time.

    Attributes:
        bounds: track k's rows are ``bounds[k]:bounds[k+1]``, int [T+1].
        timestamps_us: int64 [M]; centers_m: [M,3]; R_box_frame: [M,3,3];
        half_extent_m: half the box size grown by BOX_MARGIN_M, [M,3].
        reach_m: per track, the largest distance from its centre to a grown corner, [T].
        speed_mps: per track, the largest speed between consecutive observations, [T].
    """

    bounds: np.ndarray
    timestamps_us: np.ndarray
    centers_m: np.ndarray
    R_box_frame: np.ndarray
    half_extent_m: np.ndarray
    reach_m: np.ndarray
    speed_mps: np.ndarray

    @classmethod
    def select(cls, observations: TrackObservations, dynamic: dict[str, float]) -> DynamicBoxes:
        """The observations of the ``dynamic`` tracks (ids as keys)."""
        ids = np.asarray(observations.track_ids, dtype=object).astype(str)
        keep = np.flatnonzero(np.isin(ids, list(dynamic)))
        order, bounds = _by_track(ids[keep], observations.timestamps_us[keep])
        keep = keep[order]
        centers = observations.centers_m[keep]
        half = observations.dims_m[keep] / 2 + BOX_MARGIN_M
        times = observations.timestamps_us[keep].astype(np.int64)
        reach = np.array(
            [np.linalg.norm(half[a:b], axis=1).max() for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        )
        step_speed = np.zeros(len(bounds) - 1)
        for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            if b - a > 1:
                dt_s = np.maximum(np.diff(times[a:b]) * 1e-6, 1e-6)
                step_speed[k] = float((np.linalg.norm(np.diff(centers[a:b], axis=0), axis=1) / dt_s).max())
        return cls(bounds, times, centers, observations.R_box_frame[keep], half, reach, step_speed)

    def __len__(self) -> int:
        return len(self.bounds) - 1


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
    by_x = np.argsort(xyz_m[:, 0])  # the cull below takes each track's x range by bisection
    x_sorted, y_m = xyz_m[by_x, 0], np.ascontiguousarray(xyz_m[:, 1])
    for k in range(len(boxes)):
        a, b = int(boxes.bounds[k]), int(boxes.bounds[k + 1])
        times = boxes.timestamps_us[a:b]
        if times[-1] + hold_us < t_lo or times[0] - hold_us > t_hi:
            continue
        # cull: only points near the track's centre during the frame can be inside (a square in x, y)
        mid = _centres_at(times, boxes.centers_m[a:b], np.array([(t_lo + t_hi) // 2]))[0][0]
        reach = boxes.reach_m[k] + boxes.speed_mps[k] * (t_hi - t_lo) * 1e-6 + 1e-3
        near = by_x[np.searchsorted(x_sorted, mid[0] - reach) : np.searchsorted(x_sorted, mid[0] + reach, "right")]
        near = near[np.abs(y_m[near] - mid[1]) <= reach]
        if not len(near):
            continue
        t_near = t_us[near]
        alive = (t_near >= times[0] - hold_us) & (t_near <= times[-1] + hold_us)
        near, t_near = near[alive], t_near[alive]
        centres, nearest = _centres_at(times, boxes.centers_m[a:b], t_near)
        R = boxes.R_box_frame[a:b][nearest]
        local = np.einsum("nji,nj->ni", R, xyz_m[near] - centres)
        inside = np.all(np.abs(local) <= boxes.half_extent_m[a:b][nearest], axis=1)
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
