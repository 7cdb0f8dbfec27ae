"""Checks of a converted NCore V4 sequence, read back through ``SequenceLoaderV4``.

Each check is a :class:`Check` (name, pass/fail, one-line detail). Lidar frames are streamed one at
a time, so memory does not grow with log length. The cuboid-occupancy check, which needs the
motion-compensated points of a frame, runs on ``OCCUPANCY_FRAMES`` frames spread over the log.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from ncore.impl.common.transformations import is_within_3d_bboxes
from upath import UPath

UNIT_TOLERANCE = 1e-4  #: |‖direction‖ − 1| allowed (directions are stored as float32)
#: A frame interval more than this times the median is a dropped frame; less than 1/this, a shifted one.
GAP_FACTOR = 1.5
OCCUPANCY_FRAMES = 5
OCCUPANCY_RANGE_M = 30.0  #: boxes whose centre is within this range of the lidar are expected to hold points
OCCUPANCY_MIN_FRACTION = 0.5  #: of those boxes, at least this fraction must hold a point
OCCUPANCY_MIN_BOXES = 5  #: fewer near boxes than this: the occupancy check is not decisive


@dataclass(frozen=True)
class Check:
    name: str
    ok: bool
    detail: str


@dataclass
class Report:
    sequence: str
    checks: list[Check] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.checks)

    def add(self, name: str, ok: bool, detail: str) -> None:
        self.checks.append(Check(name, bool(ok), detail))

    def to_dict(self) -> dict:
        return {"sequence": self.sequence, "ok": self.ok, "checks": [asdict(c) for c in self.checks]}


def _regularity(report: Report, name: str, end_us: np.ndarray) -> None:
    """Frame end times strictly increase, with no interval beyond GAP_FACTOR × (or below 1/GAP_FACTOR ×) the median."""
    if len(end_us) < 3:
        report.add(f"{name}: frame spacing", True, f"{len(end_us)} frame(s): not checked")
        return
    step = np.diff(end_us.astype(np.int64))
    median = float(np.median(step))
    bad = np.flatnonzero((step <= 0) | (step > GAP_FACTOR * median) | (step < median / GAP_FACTOR))
    detail = f"median {median / 1e3:.1f} ms" + (
        f"; irregular after frame(s) {bad[:5].tolist()} ({(step[bad[:5]] / 1e3).round(1).tolist()} ms):"
        " a dropped or shifted frame"
        if len(bad)
        else ""
    )
    report.add(f"{name}: frame spacing", not len(bad), detail)


def _within_sequence(report: Report, name: str, frames_us: np.ndarray, interval) -> None:
    inside = (
        (frames_us[:, 0] >= interval.start) & (frames_us[:, 1] < interval.stop) & (frames_us[:, 0] <= frames_us[:, 1])
    )
    outside = f"{int((~inside).sum())} of {len(frames_us)} frames outside [{interval.start}, {interval.stop})"
    report.add(f"{name}: frames within the sequence", inside.all(), outside)


def _covered(loader: SequenceLoaderV4, sensor_id: str, timestamps_us: np.ndarray) -> bool:
    try:
        loader.pose_graph.evaluate_poses(sensor_id, "world", np.asarray(timestamps_us, dtype=np.uint64))
    except (ValueError, KeyError, AssertionError):
        return False
    return True


def boxes_at(observations: list, t0_us: int, t1_us: int) -> list:
    """The cuboid observations of one labelled instant in a frame [t0_us, t1_us]: the earliest
    label time within it (consecutive lidar frames can overlap by a few ms, so a frame's interval
    may also hold the next sweep's label time)."""
    inside = [o for o in observations if t0_us <= o.timestamp_us <= t1_us]
    first = min((o.timestamp_us for o in inside), default=None)
    return [o for o in inside if o.timestamp_us == first]


def sample_frames(n_frames: int) -> np.ndarray:
    """OCCUPANCY_FRAMES frame indices spread evenly over a sensor's ``n_frames`` frames."""
    return np.unique(np.linspace(0, n_frames - 1, OCCUPANCY_FRAMES).round().astype(int))


def world_points(
    loader: SequenceLoaderV4, lidar_id: str, frame: int, target: str = "world"
) -> tuple[np.ndarray, np.ndarray]:
    """A lidar frame's points, motion-compensated with the per-point times, in ``target`` (``world``
    or ``world_global``).

    Returns:
        xyz_m in target, float64 [N,3], and the sensor's position there at the frame end, float64 [3].
    """
    lidar = loader.get_lidar_sensor(lidar_id)
    t_end = lidar.frames_timestamps_us[frame, 1:2].astype(np.uint64)
    T_world_sensor = loader.pose_graph.evaluate_poses(lidar_id, target, t_end)[0].astype(np.float64)
    xyz = lidar.get_frame_point_cloud(frame, motion_compensation=True, with_start_points=False).xyz_m_end
    return xyz.astype(np.float64) @ T_world_sensor[:3, :3].T + T_world_sensor[:3, 3], T_world_sensor[:3, 3]


def box_point_counts(loader: SequenceLoaderV4, boxes: list, xyz_world_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How many of the points (world, float64 [N,3]) lie inside each box, int [B], and the box centres
    in world, float64 [B,3]; each box is tested in its own reference frame at its reference time."""
    counts, centres = np.zeros(len(boxes), dtype=np.int64), np.zeros((len(boxes), 3))
    for k, box in enumerate(boxes):
        T_world_ref = loader.pose_graph.evaluate_poses(
            box.reference_frame_id, "world", np.array([box.reference_frame_timestamp_us], dtype=np.uint64)
        )[0].astype(np.float64)
        centres[k] = T_world_ref[:3, :3] @ np.asarray(box.bbox3.centroid) + T_world_ref[:3, 3]
        xyz_ref = (xyz_world_m - T_world_ref[:3, 3]) @ T_world_ref[:3, :3]
        bbox = np.array([[*box.bbox3.centroid, *box.bbox3.dim, *box.bbox3.rot]], dtype=np.float32)
        counts[k] = int(is_within_3d_bboxes(xyz_ref.astype(np.float32), bbox).sum())
    return counts, centres


def _occupancy(loader: SequenceLoaderV4, lidar_id: str, observations: list) -> tuple[int, int]:
    """(near boxes holding a point, near boxes) over OCCUPANCY_FRAMES frames of one lidar."""
    frames_us = loader.get_lidar_sensor(lidar_id).frames_timestamps_us
    held = near = 0
    for i in sample_frames(len(frames_us)):
        boxes = boxes_at(observations, int(frames_us[i, 0]), int(frames_us[i, 1]))
        if not boxes:
            continue
        xyz_world, sensor_world = world_points(loader, lidar_id, i)
        counts, centres = box_point_counts(loader, boxes, xyz_world)
        is_near = np.linalg.norm(centres - sensor_world, axis=1) <= OCCUPANCY_RANGE_M
        near += int(is_near.sum())
        held += int((counts[is_near] > 0).sum())
    return held, near


def _check_lidar(report: Report, loader: SequenceLoaderV4, lidar_id: str, observations: list) -> None:
    lidar = loader.get_lidar_sensor(lidar_id)
    frames_us = lidar.frames_timestamps_us
    name = f"lidar {lidar_id}"
    _within_sequence(report, name, frames_us, loader.sequence_timestamp_interval_us)
    _regularity(report, name, frames_us[:, 1])
    model = lidar.model_parameters
    worst_norm, outside_time, bad_intensity, bad_element, uncovered, points, unreadable = 0.0, 0, 0, 0, [], 0, []
    for i in range(lidar.frames_count):
        try:
            direction = lidar.get_frame_ray_bundle_direction(i)
            t_us = lidar.get_frame_ray_bundle_timestamp_us(i)
            intensity = lidar.get_frame_ray_bundle_return_intensity(i)
        except (KeyError, ValueError, OSError) as err:
            unreadable.append(f"frame {i}: {type(err).__name__} {err}")
            continue
        points += len(t_us)
        if len(direction):
            worst_norm = max(worst_norm, float(np.abs(np.linalg.norm(direction, axis=1) - 1).max()))
        outside_time += int(np.sum((t_us < frames_us[i, 0]) | (t_us > frames_us[i, 1])))
        bad_intensity += int(np.sum(~((intensity >= 0) & (intensity <= 1))))
        if model is not None and (element := lidar.get_frame_ray_bundle_model_element(i)) is not None:
            bad_element += int(np.sum((element[:, 0] >= model.n_rows) | (element[:, 1] >= model.n_columns)))
        span = [t_us.min(), t_us.max()] if len(t_us) else []
        if not _covered(loader, lidar_id, np.array([frames_us[i, 0], frames_us[i, 1], *span])):
            uncovered.append(i)
    first = f" ({unreadable[0]})" if unreadable else ""
    report.add(
        f"{name}: frames readable", not unreadable, f"{len(unreadable)} of {lidar.frames_count} unreadable{first}"
    )
    report.add(f"{name}: unit directions", worst_norm <= UNIT_TOLERANCE, f"max |norm - 1| = {worst_norm:.2e}")
    report.add(f"{name}: point times within frames", outside_time == 0, f"{outside_time} of {points} points outside")
    report.add(f"{name}: intensity in [0, 1]", bad_intensity == 0, f"{bad_intensity} of {points} outside")
    if model is not None:
        report.add(f"{name}: model elements within the model", bad_element == 0,
                   f"{bad_element} outside {model.n_rows} rows x {model.n_columns} columns")  # fmt: skip
    which = f": {uncovered[:5]}" if uncovered else ""
    report.add(f"{name}: poses cover every frame and point time", not uncovered,
               f"{len(uncovered)} of {lidar.frames_count} frames uncovered{which}")  # fmt: skip
    if observations and not uncovered and not unreadable and outside_time == 0:  # what motion compensation needs
        held, near = _occupancy(loader, lidar_id, observations)
        decisive = near >= OCCUPANCY_MIN_BOXES
        ok = not decisive or held >= OCCUPANCY_MIN_FRACTION * near
        report.add(f"{name}: cuboids hold points", ok,
                   f"{held} of {near} boxes within {OCCUPANCY_RANGE_M:.0f} m hold a point"
                   + ("" if decisive else " (too few boxes to decide)"))  # fmt: skip


def _check_camera(report: Report, loader: SequenceLoaderV4, camera_id: str, lidar_frames_us: np.ndarray | None) -> None:
    camera = loader.get_camera_sensor(camera_id)
    frames_us = camera.frames_timestamps_us
    name = f"camera {camera_id}"
    _within_sequence(report, name, frames_us, loader.sequence_timestamp_interval_us)
    _regularity(report, name, frames_us[:, 1])
    every = _covered(loader, camera_id, frames_us.ravel())  # one call; frame by frame only to name the failures
    uncovered = [] if every else [i for i in range(len(frames_us)) if not _covered(loader, camera_id, frames_us[i])]
    report.add(f"{name}: poses cover every frame", not uncovered, f"{len(uncovered)} of {len(frames_us)} uncovered")
    if lidar_frames_us is not None and len(lidar_frames_us) and len(frames_us):
        mid_cam = frames_us.astype(np.float64).mean(axis=1)
        mid_lidar = lidar_frames_us.astype(np.float64).mean(axis=1)
        nearest = np.abs(mid_cam[:, None] - mid_lidar[None, :]).min(axis=1)
        report.add(f"{name}: time sync to the lidar", True,
                   f"|camera - nearest lidar frame| mid-times: median {np.median(nearest) / 1e3:.1f} ms,"
                   f" max {nearest.max() / 1e3:.1f} ms")  # fmt: skip


def validate_sequence(sequence_json: UPath, source_root: UPath | None = None) -> Report:
    """Open a sequence (its ``<sequence_id>.json``) with the default instance names and check it;
    with ``source_root`` (the converter's --root-dir), also compare its counts with the source."""
    report = Report(str(sequence_json))
    try:
        reader = SequenceComponentGroupsReader([UPath(sequence_json)])
        loader = SequenceLoaderV4(reader)
    except Exception as err:  # noqa: BLE001 - any failure to open is the finding
        report.add(
            "opens with SequenceLoaderV4",
            False,
            f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}",
        )
        return report
    report.add(
        "opens with SequenceLoaderV4", True, f"{len(loader.lidar_ids)} lidar(s), {len(loader.camera_ids)} camera(s)"
    )
    report.add(
        "world_global in the pose graph", "world_global" in loader.pose_graph.nodes, "static world -> world_global edge"
    )
    observations = list(loader.get_cuboid_track_observations())
    lidar_frames = None
    for lidar_id in loader.lidar_ids:
        _check_lidar(report, loader, lidar_id, observations)
        lidar_frames = loader.get_lidar_sensor(lidar_id).frames_timestamps_us if lidar_frames is None else lidar_frames
    for camera_id in loader.camera_ids:
        _check_camera(report, loader, camera_id, lidar_frames)
    if source_root is not None:
        from ncore_convert.validate_source import compare_with_source

        compare_with_source(report, loader, reader, source_root)
    return report


def validate_tree(path: UPath, source_root: UPath | None = None, relative_to: UPath | None = None) -> list[Report]:
    """Validate a sequence meta, or every sequence and cooperative scenario (``scenario.json``:
    co-registration of its agents) below a folder. Reports name their file relative to
    ``relative_to`` when given."""
    from ncore_convert.converters.opencood import MANIFEST
    from ncore_convert.coregister import check_coregistration

    path = UPath(path)
    reports = [validate_sequence(meta, source_root) for meta in find_sequences(path)]
    if path.is_dir():
        reports += [check_coregistration(m) for m in sorted(path.rglob(MANIFEST), key=str) if _visible(m, path)]
    if relative_to is not None:
        for report in reports:
            report.sequence = str(UPath(report.sequence).relative_to(UPath(relative_to)))
    return reports


def find_sequences(path: UPath) -> list[UPath]:
    """A sequence meta file itself, or every sequence meta (``<sequence_id>.json``) below an output folder
    (unfinished ``.<log>.partial`` folders are skipped)."""
    path = UPath(path)
    if path.is_file():
        return [path]
    return sorted((p for p in path.rglob("*.json") if _visible(p, path) and _is_sequence_meta(p)), key=str)


def _visible(path: UPath, root: UPath) -> bool:
    return not any(part.startswith(".") for part in path.relative_to(root).parts)


def _is_sequence_meta(path: UPath) -> bool:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and "sequence_id" in data and "component_stores" in data


def summarise(reports: list[Report]) -> dict:
    """The run report's record of a log's validation: counts and the failed checks, one line each."""
    failed = [f"{r.sequence}: {c.name}: {c.detail}" for r in reports for c in r.checks if not c.ok]
    return {
        "ok": not failed,
        "files": len(reports),
        "checks": sum(len(r.checks) for r in reports),
        "failed": failed,
    }


class ValidationFailed(Exception):
    """A converted log failed validation; ``validation`` is its :func:`summarise` record."""

    def __init__(self, message: str, validation: dict) -> None:
        super().__init__(message, validation)  # both in args: survives pickling from a worker
        self.validation = validation

    def __str__(self) -> str:
        return self.args[0]


def convert_and_validate(task, sequence_dir: UPath, log_id: str, *, source_root: UPath | None = None, **kwargs):
    """A log task followed by :func:`validate_tree` of its output (with the source counts when
    ``source_root`` is given). Raises ValidationFailed, so the log is not published, on any failure."""
    summary = task(sequence_dir, log_id, **kwargs)
    started = time.perf_counter()
    record = summarise(validate_tree(sequence_dir, source_root, relative_to=sequence_dir))
    record["seconds"] = round(time.perf_counter() - started, 3)
    if not record["ok"]:
        raise ValidationFailed(
            f"validation: {len(record['failed'])} of {record['checks']} checks failed, first: {record['failed'][0]}",
            record,
        )
    summary.validation = record
    return summary
