"""The traffic of a synthetic OPV2V / V2XSet scenario (:mod:`synth.opencood`): a constant-curvature
road, the actors driving or parked on it (in CARLA's conventions: poses ``[x, y, z, roll, yaw,
pitch]``, degrees), their boxes, and the rules that keep vehicles clear of the CAVs and of the
close-range cars.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ncore_convert.synth.scene import Box
from ncore_convert.synth.shapes import shape_of

CAV_CLEARANCE_M = 7.0  #: along the lane, no other vehicle's centre comes nearer a CAV's than this


@dataclass(frozen=True)
class Actor:
    actor_id: int
    lane_m: float  #: lateral offset (to the right of the road centre line)
    start_m: float  #: arc length at t = 0
    speed_mps: float
    extent_m: tuple[float, float, float]
    center_m: tuple[float, float, float]
    intensity: int


@dataclass(frozen=True)
class Road:
    """A constant-curvature road in the CARLA world: centre line position and yaw by arc length."""

    origin_m: np.ndarray
    yaw0_deg: float
    curvature: float  #: 1/m (positive: turning clockwise seen from above, i.e. to the right)

    def at(self, s_m: float, lane_m: float) -> tuple[np.ndarray, float]:
        yaw = np.radians(self.yaw0_deg) + self.curvature * s_m
        y0 = np.radians(self.yaw0_deg)
        k = self.curvature
        x = self.origin_m[0] + (np.sin(yaw) - np.sin(y0)) / k
        y = self.origin_m[1] - (np.cos(yaw) - np.cos(y0)) / k
        right = np.array([-np.sin(yaw), np.cos(yaw)])
        xy = np.array([x, y]) + lane_m * right
        return np.array([xy[0], xy[1], 0.0]), float(np.degrees(yaw))


def actor_pose(road: Road, actor: Actor, t_s: float, wobble: bool) -> np.ndarray:
    """[x, y, z, roll, yaw, pitch] of an actor's origin (on the ground) at time t_s."""
    xyz, yaw = road.at(actor.start_m + actor.speed_mps * t_s, actor.lane_m)
    roll = 0.3 * np.sin(1.3 * t_s + actor.actor_id) if wobble else 0.0
    pitch = 0.4 * np.sin(0.9 * t_s + 0.5 * actor.actor_id) if wobble else 0.0
    return np.array([xyz[0], xyz[1], 0.03, roll, yaw, pitch])


def actor_box(T_actor_world: np.ndarray, actor: Actor, category: str, shaped: bool) -> Box:
    center = T_actor_world[:3, :3] @ np.array(actor.center_m) + T_actor_world[:3, 3]
    dims = 2 * np.array(actor.extent_m)
    return Box(
        center,
        np.zeros(3),
        T_actor_world[:3, :3],
        dims,
        category,
        str(actor.actor_id),
        actor.intensity,
        shape=shape_of(category, dims) if shaped else None,
    )


def close_to(cav: Actor, camera_ahead_m: float, ids: list[int], rng: np.random.Generator) -> list[Actor]:
    """A car queued 0.3-1.0 m ahead of ``cav``'s front camera (``camera_ahead_m`` ahead of its
    origin) and one 1-2 m from its left side, both at its speed (their ids from ``ids``)."""
    cars = []
    for k, ahead in enumerate((True, False)):
        extent = (float(rng.uniform(2.15, 2.45)), float(rng.uniform(0.9, 1.0)), float(rng.uniform(0.72, 0.8)))
        gap = float(rng.uniform(0.3, 1.0) if ahead else rng.uniform(1.0, 2.0))
        if ahead:
            lane, start = cav.lane_m, cav.start_m + camera_ahead_m + gap + extent[0]
        else:
            lane, start = cav.lane_m - (cav.extent_m[1] + gap + extent[1]), cav.start_m + float(rng.uniform(-1.0, 2.0))
        intensity = int(rng.integers(20, 250))
        cars.append(Actor(ids[k], lane, start, cav.speed_mps, extent, (0.0, 0.0, extent[2]), intensity))
    return cars


def clear_of(others: list[Actor], cars: list[Actor], span_s: float) -> list[Actor]:
    """``others`` without the vehicles that would drive into one of ``cars`` during the scenario
    (lanes less than a car's width apart, centres nearer than ``CAV_CLEARANCE_M`` along the road)."""
    t_s = np.linspace(0.0, span_s, 50)

    def into(act: Actor) -> bool:
        return any(
            abs(act.lane_m - car.lane_m) < act.extent_m[1] + car.extent_m[1] + 0.2
            and np.min(np.abs(act.start_m - car.start_m + (act.speed_mps - car.speed_mps) * t_s)) < CAV_CLEARANCE_M
            for car in cars
        )

    return [act for act in others if not into(act)]


def clear_of_cavs(others: list[Actor], cavs: list[Actor], span_s: float) -> list[Actor]:
    """``others`` with every vehicle that would drive through a CAV during the scenario moved to the
    lane left of the CAVs': a CAV's cameras inside another vehicle's box would see through it, while
    its lidar does not."""
    t_s = np.linspace(0.0, span_s, 50)

    def through_a_cav(act: Actor) -> bool:
        return any(
            act.lane_m == cav.lane_m
            and np.min(np.abs(act.start_m - cav.start_m + (act.speed_mps - cav.speed_mps) * t_s)) < CAV_CLEARANCE_M
            for cav in cavs
        )

    return [replace(act, lane_m=-1.75) if act.speed_mps and through_a_cav(act) else act for act in others]
