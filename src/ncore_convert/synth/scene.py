"""A simple synthetic driving scene with known truth: ego trajectory, ground plane and boxes.

Everything is analytic in the city frame so tests can compare converter output to exact truth.
Times are seconds relative to the log start unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ncore_convert.synth.paths import EGO_FRONT_M, EGO_HALF_WIDTH_M, clear_paths_of, collide
from ncore_convert.synth.shapes import Shape, shape_of

GROUND_Z_M = 45.0  #: city height of the ground plane
EGO_ORIGIN_HEIGHT_M = 0.33  #: ego origin above ground (AV2 rear-axle origin)
CITY_ORIGIN_M = np.array([5072.4, 2283.9])  #: offset of the scene from the city origin (large, as in AV2)
NEXT_LANE_M = 3.4  #: lateral offset of the lanes next to the ego's
FAR_LANE_M = 9.5  #: lateral offset of the slow traffic's lane, clear of the parked cars and pedestrians
PARKED_JITTER_M = (0.1, 1.5)  #: peak of a parked car's annotation walk (the real AV2 sample: 0.1-1.4 m)
PARKED_JITTER_DEG = (1.0, 4.0)  #: peak of its heading walk
SLOW_JITTER_M = (0.05, 0.3)  #: the same for the slow traffic, which annotators follow more closely
SLOW_JITTER_DEG = (0.5, 1.5)
CREEPER_MIN_S = 9.0  #: logs this long get a creeper (0.5 m/s for 8 s) and a car that drives and parks
GO_STOP_M = 6.0  #: how far the latter drives before it parks
STOP_AND_GO_MIN_S = 13.0  #: logs this long get a car that waits 10 s, then drives off


def rotation_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Rz(yaw) @ Ry(pitch) @ Rx(roll) for arrays of angles [N] (radians) -> [N,3,3]."""
    cy, sy, cp, sp, cr, sr = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    return np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], axis=-1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], axis=-1),
            np.stack([-sp, cp * sr, cp * cr], axis=-1),
        ],
        axis=-2,
    )


@dataclass(frozen=True)
class EgoMotion:
    """Constant-speed arc with small pitch/roll oscillations. ``T_ego_city(t)`` in closed form."""

    speed_mps: float
    yaw_rate_rps: float
    yaw0_rad: float

    def T_ego_city(self, t_s: np.ndarray) -> np.ndarray:
        """Ego poses at times t_s (seconds from log start, [N]) -> float64 [N,4,4]."""
        t_s = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        w, v, psi0 = self.yaw_rate_rps, self.speed_mps, self.yaw0_rad
        yaw = psi0 + w * t_s
        x = CITY_ORIGIN_M[0] + v / w * (np.sin(yaw) - np.sin(psi0))
        y = CITY_ORIGIN_M[1] - v / w * (np.cos(yaw) - np.cos(psi0))
        pitch = 0.010 * np.sin(2 * np.pi * 0.3 * t_s)
        roll = 0.008 * np.sin(2 * np.pi * 0.5 * t_s + 1.0)
        z = GROUND_Z_M + EGO_ORIGIN_HEIGHT_M + 0.02 * np.sin(2 * np.pi * 0.7 * t_s)
        T = np.tile(np.eye(4), (len(t_s), 1, 1))
        T[:, :3, :3] = rotation_zyx(yaw, pitch, roll)
        T[:, :3, 3] = np.stack([x, y, z], axis=1)
        return T

    def lateral_m(self, xy_city_m: np.ndarray) -> np.ndarray:
        """Signed distance of city points ([N,2], m) from the ego's path (its arc), left positive: [N]."""
        radius = self.speed_mps / self.yaw_rate_rps
        centre = CITY_ORIGIN_M[:2] + radius * np.array([-np.sin(self.yaw0_rad), np.cos(self.yaw0_rad)])
        return radius - np.linalg.norm(np.asarray(xy_city_m) - centre, axis=-1)


@dataclass(frozen=True)
class AnnotationJitter:
    """How a human annotator's boxes of one track wander around the true box: a mean-reverting random
    walk of the centre (horizontal) and heading, sampled on a time grid and interpolated.

    Attributes:
        times_s: the grid, float64 [K] (increasing); offset_m: centre offsets [K,3] (z = 0);
        yaw_rad: heading offsets [K].
    """

    times_s: np.ndarray
    offset_m: np.ndarray
    yaw_rad: np.ndarray

    def at(self, t_s: float) -> tuple[np.ndarray, float]:
        """(centre offset [3] in metres, heading offset in radians) at time ``t_s``."""
        offset = np.array([np.interp(t_s, self.times_s, self.offset_m[:, k]) for k in range(3)])
        return offset, float(np.interp(t_s, self.times_s, self.yaw_rad))


def returning_walk(rng: np.random.Generator, times_s: np.ndarray, peak: float, dims: int, tau_s: float) -> np.ndarray:
    """A mean-reverting (Ornstein-Uhlenbeck) walk on ``times_s`` [K] that starts at 0 and is scaled so
    that its largest distance from 0 is ``peak``: float64 [K,dims]."""
    dt = np.diff(times_s, prepend=times_s[0])
    walk = np.zeros((len(times_s), dims))
    for k in range(1, len(times_s)):
        walk[k] = walk[k - 1] * (1.0 - dt[k] / tau_s) + np.sqrt(dt[k]) * rng.normal(size=dims)
    largest = np.linalg.norm(walk, axis=1).max()
    return walk * (peak / largest) if largest > 0 else walk


def annotation_jitter(
    rng: np.random.Generator, t_lo_s: float, t_hi_s: float, peak_m: float, peak_yaw_rad: float
) -> AnnotationJitter:
    """Jitter over ``[t_lo_s, t_hi_s]`` on a 0.1 s grid: the centre's walk peaks at ``peak_m`` from
    the true centre, the heading's at ``peak_yaw_rad``; 3 cm of white noise per grid step on top."""
    times = np.arange(t_lo_s, t_hi_s + 0.1, 0.1)
    xy = returning_walk(rng, times, peak_m, 2, tau_s=float(rng.uniform(1.5, 4.0)))
    xy += rng.normal(0.0, 0.03, xy.shape)
    yaw = returning_walk(rng, times, peak_yaw_rad, 1, tau_s=float(rng.uniform(1.5, 4.0)))[:, 0]
    return AnnotationJitter(times, np.column_stack([xy, np.zeros(len(times))]), yaw)


@dataclass(frozen=True)
class Box:
    """An oriented box (city frame), standing still or moving at constant velocity within a time window.

    Attributes:
        center0_m: centre at t = 0 if it moved all the time, [3]; velocity_mps: [3] while it moves;
        rotation: city_R_box [3,3]; dims_m: (length, width, height) along box x, y, z;
        category: AV2 class or "BUILDING"; move_from_s, move_until_s: it moves only within this
        window (seconds from the log start; default: always); jitter: how its annotations wander
        (None: annotations are exact); shape: what the object is inside (and, mirrors, just
        outside) its box, in the box's axes (None: the box itself).
    """

    center0_m: np.ndarray
    velocity_mps: np.ndarray
    rotation: np.ndarray
    dims_m: np.ndarray
    category: str
    track_uuid: str
    intensity: int
    move_from_s: float = -np.inf
    move_until_s: float = np.inf
    jitter: AnnotationJitter | None = None
    shape: Shape | None = None

    @property
    def annotated(self) -> bool:
        return self.category != "BUILDING"

    def center_m(self, t_s: np.ndarray | float) -> np.ndarray:
        """The true centre at times ``t_s`` (scalar -> [3], [N] -> [N,3])."""
        t_moving = np.clip(np.asarray(t_s, dtype=np.float64), self.move_from_s, self.move_until_s)
        return self.center0_m + np.multiply.outer(t_moving, self.velocity_mps)

    @property
    def bound_m(self) -> tuple[np.ndarray, np.ndarray]:
        """The lowest and highest corner of what rays can hit, in the box's axes, [3] each."""
        if self.shape is None:
            return -self.dims_m / 2, self.dims_m / 2
        return self.shape.lo_m, self.shape.hi_m

    def speed_mps(self, t_s: np.ndarray | float) -> np.ndarray:
        """The true speed at times ``t_s`` (s [N] or scalar), m/s: its velocity's within the span it
        moves, else 0."""
        t_s = np.asarray(t_s, dtype=np.float64)
        moving = (t_s >= self.move_from_s) & (t_s <= self.move_until_s)
        return np.where(moving, np.linalg.norm(self.velocity_mps), 0.0)

    def moved_m(self, t_lo_s: float, t_hi_s: float) -> float:
        """The true distance travelled between two times (the truth a motion test is scored on)."""
        return float(np.linalg.norm(self.center_m(t_hi_s) - self.center_m(t_lo_s)))

    def T_box_city(self, t_s: float) -> np.ndarray:
        """The true box pose at ``t_s``, [4,4]."""
        T = np.eye(4)
        T[:3, :3] = self.rotation
        T[:3, 3] = self.center_m(t_s)
        return T

    def T_annotated_city(self, t_s: float) -> np.ndarray:
        """The box as annotated at ``t_s``: the true pose with the annotator's jitter, [4,4]."""
        T = self.T_box_city(t_s)
        if self.jitter is not None:
            offset, yaw = self.jitter.at(t_s)
            T[:3, 3] += offset
            T[:3, :3] = Rotation.from_euler("Z", yaw).as_matrix() @ self.rotation
        return T


@dataclass(frozen=True)
class Scene:
    ego: EgoMotion
    boxes: list[Box]


def make_scene(
    rng: np.random.Generator,
    seconds: float,
    traffic_rng: np.random.Generator,
    shapes: bool = False,
    close_range: bool = False,
    clear_paths: bool = True,
) -> Scene:
    """Ego on a gentle arc with parked and moving cars, pedestrians, bollards and buildings.

    Parked cars' annotations jitter like human labels of real parked cars (AV2: a returning walk of
    0.1-1.5 m peak, heading a few degrees). A log of at least ``CREEPER_MIN_S`` adds a creeper
    (0.5 m/s for 8 s) and a car that drives ``GO_STOP_M`` and parks; one of at least
    ``STOP_AND_GO_MIN_S`` adds a car that waits 10 s and then drives off; their annotations jitter
    a little (5-30 cm). ``traffic_rng`` draws all of that, so ``rng``'s stream (and everything the
    generator draws from it after the scene) is the same as without it.

    ``shapes``: vehicles, pedestrians and cyclists are shaped inside their boxes (:mod:`synth.shapes`),
    and cyclists ride along the ego's lane. ``close_range``: a car drives just ahead of the ego
    (0.3-1.0 m from its front bumper) and one alongside it (1-2 m from its side), at its speed.
    Both draw from ``traffic_rng`` after everything else, so the rest of the scene is unchanged.
    ``clear_paths``: nothing moves through anything else (:func:`synth.paths.clear_paths_of`). Without it, the
    cars in the next lane drive through the parked cars they pass (0-0.8 m of overlap) and pedestrians
    walk through parked cars and bollards; it is off by default only because the scenes every other
    test was measured on would change (issue 53's motion bench and tests use it).
    """
    ego = EgoMotion(
        speed_mps=float(rng.uniform(6.0, 9.0)),
        yaw_rate_rps=float(rng.uniform(0.03, 0.07)),
        yaw0_rad=float(rng.uniform(-np.pi, np.pi)),
    )

    def along(t_s: float, lateral_m: float, z_m: float) -> tuple[np.ndarray, float]:
        T = ego.T_ego_city(np.array([t_s]))[0]
        yaw = np.arctan2(T[1, 0], T[0, 0])
        left = np.array([-np.sin(yaw), np.cos(yaw)])
        xy = T[:2, 3] + lateral_m * left
        return np.array([xy[0], xy[1], z_m]), float(yaw)

    def uuid() -> str:
        h = rng.bytes(16).hex()
        return f"{h[:8]}-{h[8:12]}-4{h[13:16]}-a{h[17:20]}-{h[20:32]}"

    boxes: list[Box] = []

    def add(center, yaw, dims, category, velocity=(0.0, 0.0, 0.0), tilt=(0.0, 0.0), intensity=60, **motion):
        R = Rotation.from_euler("ZYX", [yaw, tilt[0], tilt[1]]).as_matrix()
        boxes.append(
            Box(
                np.asarray(center, float),
                np.asarray(velocity, float),
                R,
                np.asarray(dims, float),
                category,
                uuid(),
                intensity,
                **motion,
                shape=shape_of(category, dims) if shapes else None,
            )
        )

    def jitter(peak_m: tuple[float, float], peak_yaw_deg: tuple[float, float]) -> AnnotationJitter:
        return annotation_jitter(
            traffic_rng,
            -2.0,
            seconds + 2.0,
            float(traffic_rng.uniform(*peak_m)),
            np.radians(traffic_rng.uniform(*peak_yaw_deg)),
        )

    t_end = seconds + 2.0
    for t in np.arange(-1.0, t_end, 1.1):  # parked cars on both curbs, slightly tilted (full 3-DOF boxes)
        for side in (-1, 1):
            if rng.random() < 0.6:
                dims = (rng.uniform(4.2, 5.0), rng.uniform(1.8, 2.0), rng.uniform(1.4, 1.8))
                c, yaw = along(t + rng.uniform(-0.2, 0.2), side * rng.uniform(4.5, 5.5), GROUND_Z_M + dims[2] / 2)
                add(
                    c,
                    yaw + rng.normal(0, 0.05),
                    dims,
                    "REGULAR_VEHICLE",
                    tilt=(rng.normal(0, 0.03), rng.normal(0, 0.03)),
                    intensity=int(rng.integers(40, 120)),
                    jitter=jitter(PARKED_JITTER_M, PARKED_JITTER_DEG),
                )
    for _ in range(3):  # cars moving in the next lane
        dims = (rng.uniform(4.3, 5.2), 1.9, 1.6)
        c, yaw = along(rng.uniform(0, seconds + 1.0), rng.choice([-1.0, 1.0]) * NEXT_LANE_M, GROUND_Z_M + dims[2] / 2)
        speed = rng.uniform(3.0, 10.0)
        add(
            c,
            yaw,
            dims,
            "REGULAR_VEHICLE",
            velocity=(speed * np.cos(yaw), speed * np.sin(yaw), 0.0),
            intensity=int(rng.integers(60, 160)),
        )
    for t in np.arange(0.0, t_end, 0.8):  # pedestrians and bollards on the sidewalks
        side = rng.choice([-1, 1])
        c, yaw = along(t, side * rng.uniform(6.5, 8.0), GROUND_Z_M + 0.85)
        add(
            c,
            yaw + rng.uniform(-3, 3),
            (0.6, 0.6, 1.7),
            "PEDESTRIAN",
            velocity=(rng.normal(0, 0.8), rng.normal(0, 0.8), 0.0),
            intensity=int(rng.integers(20, 80)),
        )
        c, yaw = along(t + 0.4, side * 6.0, GROUND_Z_M + 0.5)
        add(c, yaw, (0.25, 0.25, 1.0), "BOLLARD", intensity=200)
    for t in np.arange(-2.0, t_end + 1.0, 2.2):  # building fronts along both sides (not annotated)
        for side in (-1, 1):
            c, yaw = along(t, side * rng.uniform(14.0, 18.0), GROUND_Z_M + 6.0)
            add(c, yaw, (14.0, 6.0, 12.0), "BUILDING", intensity=int(rng.integers(10, 40)))
    _add_slow_traffic(traffic_rng, seconds, along, add, jitter)
    if shapes:
        for _ in range(2):  # cyclists at the edge of the ego's lane, overtaken at about 1 m
            dims = (float(traffic_rng.uniform(1.7, 1.9)), 0.6, float(traffic_rng.uniform(1.6, 1.8)))
            t_s, side = float(traffic_rng.uniform(0.5, seconds + 3.0)), float(traffic_rng.choice([-1.0, 1.0]))
            c, yaw = along(t_s, side * 2.0, GROUND_Z_M + dims[2] / 2)
            speed = float(traffic_rng.uniform(3.0, 5.5))
            add(c, yaw, dims, "BICYCLIST", velocity=(speed * np.cos(yaw), speed * np.sin(yaw), 0.0), intensity=90)
    if clear_paths:
        boxes = clear_paths_of(boxes, seconds, ego)
    if close_range:
        n_before = len(boxes)
        _add_close_traffic(traffic_rng, ego, along, add)
        close = boxes[n_before:]  # on the ego's lane and the next: no other car may drive through them
        boxes[:n_before] = [b for b in boxes[:n_before] if not any(collide(b, c, seconds) for c in close)]
    return Scene(ego, boxes)


def _add_close_traffic(rng: np.random.Generator, ego: EgoMotion, along, add) -> None:
    """A car just ahead of the ego and one alongside it (see :func:`make_scene`) at the log's start,
    at the ego's speed along the road where each starts (straight on: the ego's arc bends away from
    them by about 0.5 * yaw rate * speed * t^2, 0.2 m after 1 s)."""
    for ahead in (True, False):
        dims = (float(rng.uniform(4.3, 4.9)), float(rng.uniform(1.8, 1.95)), float(rng.uniform(1.45, 1.6)))
        gap = float(rng.uniform(0.3, 1.0) if ahead else rng.uniform(1.0, 2.0))
        side = float(rng.choice([-1.0, 1.0]))
        lead_m = EGO_FRONT_M + gap + dims[0] / 2 if ahead else float(rng.uniform(-1.0, 3.0))
        lateral_m = 0.0 if ahead else side * (EGO_HALF_WIDTH_M + gap + dims[1] / 2)
        c, yaw = along(lead_m / ego.speed_mps, lateral_m, GROUND_Z_M + dims[2] / 2)
        v = ego.speed_mps * np.array([np.cos(yaw), np.sin(yaw), 0.0])
        add(c, yaw, dims, "REGULAR_VEHICLE", velocity=v, intensity=int(rng.integers(60, 160)))


def _add_slow_traffic(rng: np.random.Generator, seconds: float, along, add, jitter) -> None:
    """The creeper, the car that drives and parks, and the stop-and-go car (see :func:`make_scene`);
    their velocity is along the road, their window of motion inside the log."""

    def moving(t_pos_s: float, lateral_m: float, speed_mps: float, start_s: float, end_s: float) -> None:
        dims = (rng.uniform(4.3, 5.0), 1.9, 1.6)
        c, yaw = along(t_pos_s, lateral_m, GROUND_Z_M + dims[2] / 2)
        v = speed_mps * np.array([np.cos(yaw), np.sin(yaw), 0.0])
        add(
            c - v * start_s,
            yaw,
            dims,
            "REGULAR_VEHICLE",
            velocity=v,
            intensity=int(rng.integers(60, 160)),
            move_from_s=start_s,
            move_until_s=end_s,
            jitter=jitter(SLOW_JITTER_M, SLOW_JITTER_DEG),
        )

    side = rng.choice([-1.0, 1.0])
    if seconds >= CREEPER_MIN_S:
        start = float(rng.uniform(0.0, seconds - 8.0))
        moving(start + 4.0, side * FAR_LANE_M, 0.5, start, start + 8.0)  # 0.5 m/s for 8 s: 4 m
        speed = float(rng.uniform(1.5, 2.5))
        moving(float(rng.uniform(3.0, 6.0)), -side * FAR_LANE_M, speed, 0.5, 0.5 + GO_STOP_M / speed)
    if seconds >= STOP_AND_GO_MIN_S:
        moving(
            float(rng.uniform(4.0, 8.0)),
            rng.choice([-1.0, 1.0]) * NEXT_LANE_M,
            float(rng.uniform(3.0, 6.0)),
            10.0,
            np.inf,
        )
