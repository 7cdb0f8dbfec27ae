"""The cuboid-occupancy check of a converted sequence (a plausibility heuristic, docs/validation.md):
the stored lidar registration fills the near boxes with points at least as well as gross
misregistrations do, on ``readback.SAMPLED_FRAMES`` frames spread over the log.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import numpy as np
from scipy.spatial.transform import Rotation

from ncore_convert.validate.cuboids import CuboidColumns
from ncore_convert.validate.poses import sensor_poses
from ncore_convert.validate.readback import OpenSequence, box_centres_world, box_point_counts, boxes_at, sample_frames
from ncore_convert.validate.report import Report

OCCUPANCY_RANGE_M = 30.0  #: boxes whose centre is within this range of the lidar are looked at
#: Fewer near objects (tracks, not box-frames: the same object is near in frame after frame) than this:
#: the occupancy check is not decisive (:func:`occupancy_verdict`).
OCCUPANCY_MIN_OBJECTS = 5
#: Slack of the distance filter before the occupancy counts (metres): far above rounding, so no point
#: that lies in a near box is left out.
OCCUPANCY_FILTER_SLACK_M = 1.0
#: Gross misregistrations the occupancy is compared with (a plausibility heuristic, docs/validation.md):
#: the frame's points turned about the lidar, in its own axes, by these xyz Euler angles (degrees):
#: yawed a quarter, half and three quarters round, and upside down.
OCCUPANCY_ALTERNATIVES_DEG = ((0, 0, 90), (0, 0, 180), (0, 0, 270), (180, 0, 0))
#: The occupancy fails when an alternative holds more near boxes than the stored registration by more
#: than this many binomial standard deviations (boxes hold points or not, as occlusion decides).
OCCUPANCY_SIGMAS = 3.0


@dataclass(frozen=True)
class Occupancy:
    """What the occupancy check counted over the sampled frames of one lidar, per near track
    (an object, whatever the number of frames it was near in), int [T] each.

    Attributes:
        frames: the sampled frames in which the track's box was near.
        held: of those, the frames in which its box held a point.
        turned: the same for the alternative registration that held the most near boxes in all.
    """

    frames: np.ndarray
    held: np.ndarray
    turned: np.ndarray


def _occupancy(sequence: OpenSequence, lidar_id: str, cuboids: CuboidColumns) -> Occupancy:
    """The near boxes holding a point, for the stored registration and each of the
    OCCUPANCY_ALTERNATIVES_DEG, per track over the sampled frames of one lidar. Only the points that
    can lie in a near box are counted: those within OCCUPANCY_RANGE_M and the largest near box's
    half diagonal of the lidar (a turn about the lidar keeps each point's distance to it)."""
    loader = sequence.loader
    frames_us = loader.get_lidar_sensor(lidar_id).frames_timestamps_us
    turns = Rotation.from_euler("xyz", OCCUPANCY_ALTERNATIVES_DEG, degrees=True).as_matrix()
    tracks: dict[str, int] = {}
    rows: list[tuple[int, int, np.ndarray]] = []  # per near box-frame: its track, held, held when turned [A]
    for i in sample_frames(len(frames_us)):
        boxes = boxes_at(cuboids, int(frames_us[i, 0]), int(frames_us[i, 1]))
        if not len(boxes):
            continue
        xyz_world, sensor_world = sequence.world_points(lidar_id, i)
        with np.errstate(invalid="ignore"):  # a box that cannot be posed has a NaN centre: never near
            is_near = np.linalg.norm(box_centres_world(loader, boxes) - sensor_world, axis=1) <= OCCUPANCY_RANGE_M
        if not is_near.any():
            continue
        near_boxes = boxes.rows(is_near)
        half_diagonal_m = float(np.linalg.norm(near_boxes.dim_m, axis=1).max()) / 2
        reach_m = OCCUPANCY_RANGE_M + half_diagonal_m + OCCUPANCY_FILTER_SLACK_M
        xyz_world = xyz_world[np.linalg.norm(xyz_world - sensor_world, axis=1) <= reach_m]
        _, counts = box_point_counts(loader, near_boxes, xyz_world)
        R_sensor_world = sensor_poses(loader, lidar_id, "world", frames_us[i, 1:2])[0][:3, :3]
        turned = np.zeros((len(near_boxes), len(turns)), dtype=bool)
        for k, turn in enumerate(turns):  # about the lidar, in its own axes
            R_turn_world = R_sensor_world @ turn @ R_sensor_world.T
            _, moved = box_point_counts(loader, near_boxes, (xyz_world - sensor_world) @ R_turn_world.T + sensor_world)
            turned[:, k] = moved > 0
        for track_id, count, alternatives in zip(near_boxes.track_id.tolist(), counts, turned, strict=True):
            rows.append((tracks.setdefault(track_id, len(tracks)), int(count > 0), alternatives))
    if not rows:
        return Occupancy(*(np.zeros(0, np.int64) for _ in range(3)))
    track = np.array([r[0] for r in rows])
    held = np.array([r[1] for r in rows])
    turned = np.array([r[2] for r in rows], dtype=np.int64)
    best = int(np.argmax(turned.sum(axis=0)))  # the alternative holding the most near boxes
    per_track = partial(np.bincount, track, minlength=len(tracks))
    return Occupancy(per_track(), per_track(held), per_track(turned[:, best]))


def _binomial(frames: int, held: int, turned: int) -> tuple[int, float]:
    """The turned count's excess over the stored one, and its OCCUPANCY_SIGMAS allowance as if each
    of the ``frames`` near box-frames were an independent draw (p: the pooled share holding a point)."""
    share = (held + turned) / (2 * frames) if frames else 0.0
    return turned - held, OCCUPANCY_SIGMAS * float(np.sqrt(frames * share * (1 - share)))


def occupancy_verdict(counted: Occupancy) -> tuple[bool, bool, float]:
    """Whether the stored registration fills the near boxes at least as well as the best gross
    misregistration: (ok, decisive, slack in boxes).

    The turned count may exceed the stored one by OCCUPANCY_SIGMAS binomial standard deviations of
    the near box-frames. But an object is occluded, or not, in frame after frame: one car always
    hidden near the agent is empty in every frame for the stored registration and filled by the
    turned one's stray points, and moves the count by every frame it is near in, at once. A
    misregistration empties the boxes of every object alike. So the check refuses only when the
    excess stays beyond its allowance without the object that adds most to it (a leave-one-out of
    the objects, not the box-frames), and it decides only with OCCUPANCY_MIN_OBJECTS near objects.
    The slack returned is the allowance of that second count.
    """
    frames = int(counted.frames.sum())
    if not frames:
        return True, False, 0.0
    held, turned = int(counted.held.sum()), int(counted.turned.sum())
    excess, slack = _binomial(frames, held, turned)
    decisive = len(counted.frames) >= OCCUPANCY_MIN_OBJECTS
    most = int(np.argmax(counted.turned - counted.held))  # the object that adds most to the excess
    rest = _binomial(
        frames - int(counted.frames[most]), held - int(counted.held[most]), turned - int(counted.turned[most])
    )
    return not decisive or excess <= slack or rest[0] <= rest[1], decisive, rest[1]


def check_occupancy(report: Report, sequence: OpenSequence, lidar_id: str, cuboids: CuboidColumns) -> None:
    """A plausibility heuristic: the stored registration fills the near boxes with points at least as
    well as gross misregistrations do (:func:`occupancy_verdict`)."""
    counted = _occupancy(sequence, lidar_id, cuboids)
    ok, decisive, slack = occupancy_verdict(counted)
    report.add(
        f"lidar {lidar_id}: cuboids hold points",
        ok,
        f"{int(counted.held.sum())} of {int(counted.frames.sum())} boxes ({len(counted.frames)} objects) within"
        f" {OCCUPANCY_RANGE_M:.0f} m hold a point; turned about the lidar (yaw 90/180/270°, upside down) at most"
        f" {int(counted.turned.sum())} (slack {slack:.1f})" + ("" if decisive else " (too few objects to decide)"),
    )
