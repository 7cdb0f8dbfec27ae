"""Traffic that never moves through anything (``synth --clear-paths``, the generator's default): the
overlap test of two boxes seen from above over a log, and the rules that keep a scene's movers clear
of each other, of the standing objects and of the ego's lane (:func:`clear_paths_of`).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Protocol

import numpy as np


class Box(Protocol):
    """What the rules read of a scene box (``synth.scene.Box``, a frozen dataclass): its pose,
    size and motion, city frame."""

    center0_m: np.ndarray
    velocity_mps: np.ndarray
    rotation: np.ndarray
    dims_m: np.ndarray
    category: str
    move_from_s: float
    move_until_s: float

    def center_m(self, t_s: np.ndarray) -> np.ndarray: ...


class EgoPath(Protocol):
    """What the rules read of the ego's motion (``synth.scene.EgoMotion``)."""

    def lateral_m(self, xy_city_m: np.ndarray) -> np.ndarray: ...


EGO_FRONT_M, EGO_HALF_WIDTH_M = 3.9, 0.98  #: the ego's front bumper ahead of its origin, its half width
FOLLOW_STEPS = 20  #: a following car starts up to this many 0.5 m steps further back
WALK_MARGIN_M = 0.3  #: what a pedestrian keeps clear of a post, a car or another pedestrian (each side)


def log_times_s(seconds: float) -> np.ndarray:
    """The times two boxes are compared at: every 50 ms of the log, [T]."""
    return np.arange(0.0, seconds + 0.05, 0.05)


def overlapping(a: Box, b: Box, times_s: np.ndarray, margin_m: float = 0.3) -> np.ndarray:
    """Whether boxes ``a`` and ``b``, seen from above and grown by ``margin_m``, overlap at each of
    ``times_s`` ([T] -> bool [T]): separating-axis test of two rectangles."""
    corners = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], float)
    axes = np.concatenate([a.rotation[:2, :2].T, b.rotation[:2, :2].T])  # each box's x and y
    spans = []
    for box in (a, b):
        outline = (corners * (box.dims_m[:2] / 2 + margin_m)) @ box.rotation[:2, :2].T  # [4,2]
        on_axes = outline @ axes.T  # [4 corners, 4 axes]
        centre = box.center_m(times_s)[:, :2] @ axes.T  # [T, 4 axes]
        spans.append((centre + on_axes.min(axis=0), centre + on_axes.max(axis=0)))
    (lo_a, hi_a), (lo_b, hi_b) = spans
    return np.all((lo_a <= hi_b) & (lo_b <= hi_a), axis=1)


def collide(a: Box, b: Box, seconds: float, margin_m: float = 0.3) -> bool:
    """Whether boxes ``a`` and ``b`` (grown by ``margin_m``) overlap at any time of the log."""
    return bool(overlapping(a, b, log_times_s(seconds), margin_m).any())


def clear_paths_of(boxes: list[Box], seconds: float, ego: EgoPath) -> list[Box]:
    """``boxes`` with nothing moving through another object during the log. Moving vehicles are kept
    in order, the scheduled slow traffic first (the creeper, the car that parks, the stop-and-go
    car), each clear of those kept before it: a car that would drive into one going its way follows
    it at its speed instead, starting up to 10 m further back if it would start inside it; one still
    not clear is left out. A parked car in a kept vehicle's way
    stands further from it (in 0.25 m steps, up to 2 m; else it is left out; a bollard it then
    stands on is left out). A pedestrian walks until just before touching anything (a vehicle, a
    bollard, a building front, a pedestrian kept before, the ego's lane) unless it can walk the other
    way or across instead, then stands; one who starts touching, or whom a vehicle would drive into
    where they stand, is left out. Real traffic goes round
    obstacles, and a place two objects share is neither's."""

    def moving(b: Box) -> bool:
        return bool(np.any(b.velocity_mps))

    def walks(b: Box) -> bool:
        return b.category in ("PEDESTRIAN", "BICYCLIST")

    times_s = log_times_s(seconds)
    in_order = sorted((m for m in boxes if moving(m) and not walks(m)), key=lambda m: not np.isfinite(m.move_from_s))
    kept: dict[int, Box] = {}  # id of a moving vehicle of ``boxes`` -> the vehicle as kept
    for m in in_order:
        ahead = [v for v in kept.values() if collide(m, v, seconds) and v.velocity_mps @ m.velocity_mps > 0]
        m_as_kept = m
        if ahead and np.isinf(m.move_from_s):  # it follows the first it would drive into, at its speed,
            back = -ahead[0].velocity_mps / np.linalg.norm(ahead[0].velocity_mps)
            m_as_kept = replace(m, velocity_mps=ahead[0].velocity_mps)
            for _ in range(FOLLOW_STEPS):  # starting further back if it would start inside it
                if not collide(m_as_kept, ahead[0], seconds):
                    break
                m_as_kept = replace(m_as_kept, center0_m=m_as_kept.center0_m + 0.5 * back)
        if not any(collide(m_as_kept, v, seconds) for v in kept.values()):
            kept[id(m)] = m_as_kept
    vehicles = list(kept.values())
    paths = {id(v): v.center_m(times_s)[:, :2] for v in vehicles}
    boxes = [kept.get(id(b), b) for b in boxes if id(b) in kept or not moving(b) or walks(b)]
    standing = []
    for b in boxes:
        if moving(b) or b.category == "BUILDING":
            standing.append(b)
            continue
        for _ in range(9):
            blocking = [m for m in vehicles if collide(b, m, seconds)]
            if not blocking:
                standing.append(b)
                break
            path = paths[id(blocking[0])]
            away = b.center0_m[:2] - path[np.argmin(np.linalg.norm(path - b.center0_m[:2], axis=1))]
            b = replace(b, center0_m=b.center0_m + np.append(0.25 * away / max(np.linalg.norm(away), 1e-9), 0.0))
    parked = [b for b in standing if not moving(b) and b.category == "REGULAR_VEHICLE"]
    standing = [b for b in standing if b.category != "BOLLARD" or not any(collide(b, car, seconds) for car in parked)]
    others = [b for b in standing if b.category != "PEDESTRIAN"]
    cleared: list[Box] = []  # in the scene's order
    walkers: list[Box] = []
    for b in standing:
        if b.category == "PEDESTRIAN":
            b = _walk_until_blocked(b, others + walkers, ego, times_s)
            walkers += [b] if b is not None else []
        if b is not None:
            cleared.append(b)
    return cleared


def _walk_until_blocked(walker: Box, others: list[Box], ego: EgoPath, times_s: np.ndarray) -> Box | None:
    """``walker`` on a free path: the first of its own direction, the opposite one and the two across
    it in which it touches none of ``others`` nor the ego's lane all log long; else, on its own
    direction, standing from the last time before it would touch one (at most 50 ms before). None if
    it touches one from the start, or one touches it where it then stands. Both grown by
    ``WALK_MARGIN_M`` (the lane: the ego's half width and the walker's)."""
    lane_m = EGO_HALF_WIDTH_M + np.linalg.norm(walker.dims_m[:2]) / 2 + 2 * WALK_MARGIN_M

    def touching(w: Box) -> np.ndarray:
        out = np.abs(ego.lateral_m(w.center_m(times_s)[:, :2])) < lane_m
        for other in others:
            out |= overlapping(w, other, times_s, WALK_MARGIN_M)
        return out

    blocked = touching(walker)
    if not blocked.any():
        return walker
    vx, vy, vz = walker.velocity_mps
    for velocity in ((-vx, -vy, vz), (-vy, vx, vz), (vy, -vx, vz)):
        turned = replace(walker, velocity_mps=np.array(velocity))
        if not touching(turned).any():
            return turned
    first = int(np.argmax(blocked))
    if first == 0:
        return None
    walker = replace(walker, move_until_s=min(walker.move_until_s, float(times_s[first - 1])))
    return None if touching(walker).any() else walker
