"""Checks of one converted NCore V4 sequence, read back through ``SequenceLoaderV4`` (``readback``).

Each check is a :class:`~ncore_convert.validate.report.Check` (name, pass/fail, one-line detail).
Lidar frames are streamed one at a time, so memory does not grow with log length. The
cuboid-occupancy check (``occupancy``), which needs the motion-compensated points of a frame, runs
on ``readback.SAMPLED_FRAMES`` frames spread over the log.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from ncore.data.v4 import SequenceLoaderV4
from upath import UPath

from ncore_convert import contract
from ncore_convert.sources.reader import Reader
from ncore_convert.transforms.lidar.rays import EXACT_DISTANCE_STEPS
from ncore_convert.validate.cuboids import CuboidColumns, check_cuboids, read_cuboids
from ncore_convert.validate.labels import check_camera_labels, held_boxes
from ncore_convert.validate.occupancy import check_occupancy
from ncore_convert.validate.poses import sensor_poses, world_global_edge
from ncore_convert.validate.readback import (
    OpenSequence,
    open_failure,
    open_sequence,
)
from ncore_convert.validate.report import Report
from ncore_convert.validate.source import compare_with_source

#: A worker pool's ``run``: a list of (function, args) jobs -> their results, in order.
RunJobs = Callable[[list[tuple[Callable, tuple]]], list]
#: |‖direction‖ − 1| allowed: a float32 unit direction is off by at most one unit roundoff (2**-24),
#: exact rays (CARLA) move their distance up to EXACT_DISTANCE_STEPS float32 steps off the range
#: (each changes the direction's length by at most 2**-23), and this check's float32 norm adds two
#: roundoffs: 8 * 2**-23 + 3 * 2**-24 = 1.13e-6 (measured: AV2 1.19e-7, OPV2V 9.54e-7).
UNIT_TOLERANCE = EXACT_DISTANCE_STEPS * 2.0**-23 + 3 * 2.0**-24
#: float64 steps of its largest element the stored world -> world_global edge may differ from the metadata's
EDGE_STEPS = 4
#: A frame interval more than this times the median is a dropped frame; less than 1/this, a shifted one.
GAP_FACTOR = 1.5


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
        sensor_poses(loader, sensor_id, "world", timestamps_us)
    except (ValueError, KeyError, AssertionError):
        return False
    return True


def _uncovered(loader: SequenceLoaderV4, sensor_id: str, spans_us: np.ndarray) -> list[int]:
    """The frames (uint64 [F,2] µs spans) whose start or end the poses do not cover: one pose
    evaluation for all of them (the pose curve is interpolated, so the ends decide), frame by frame
    only to name the failures."""
    if _covered(loader, sensor_id, spans_us.ravel()):
        return []
    return [i for i in range(len(spans_us)) if not _covered(loader, sensor_id, spans_us[i])]


def _check_lidar(report: Report, loader: SequenceLoaderV4, lidar_id: str) -> bool:
    """Every frame read back; returns whether the frames allow the occupancy check (all readable,
    every point time within its frame and covered by the poses)."""
    lidar = loader.get_lidar_sensor(lidar_id)
    frames_us = lidar.frames_timestamps_us
    name = f"lidar {lidar_id}"
    _within_sequence(report, name, frames_us, loader.sequence_timestamp_interval_us)
    _regularity(report, name, frames_us[:, 1])
    model = lidar.model_parameters
    worst_norm, outside_time, bad_intensity, bad_element, points, unreadable = 0.0, 0, 0, 0, 0, []
    spans_us = frames_us.astype(np.uint64).copy()  # per frame: its interval widened to its points' times
    for i in range(lidar.frames_count):
        try:
            direction = lidar.get_frame_ray_bundle_direction(i)
            t_us = lidar.get_frame_ray_bundle_timestamp_us(i)
            intensity = lidar.get_frame_ray_bundle_return_intensity(i)
        except (KeyError, ValueError, OSError) as err:
            unreadable.append(f"frame {i}: {type(err).__name__} {err}")
            continue
        points += len(t_us)
        if not len(t_us):
            continue
        # each check looks at the extremes first and counts element by element only when they fail
        norm2 = np.einsum("ij,ij->i", direction, direction)  # the extreme squared norms decide |norm - 1|
        worst_norm = max(worst_norm, *(abs(float(np.sqrt(v)) - 1) for v in (norm2.min(), norm2.max())))
        t_min, t_max = t_us.min(), t_us.max()
        if t_min < frames_us[i, 0] or t_max > frames_us[i, 1]:
            outside_time += int(np.sum((t_us < frames_us[i, 0]) | (t_us > frames_us[i, 1])))
        if not (intensity.min() >= 0 and intensity.max() <= 1):  # NaN fails both
            bad_intensity += int(np.sum(~((intensity >= 0) & (intensity <= 1))))
        if model is not None and (element := lidar.get_frame_ray_bundle_model_element(i)) is not None:
            if len(element) and (element[:, 0].max() >= model.n_rows or element[:, 1].max() >= model.n_columns):
                bad_element += int(np.sum((element[:, 0] >= model.n_rows) | (element[:, 1] >= model.n_columns)))
        spans_us[i] = min(spans_us[i, 0], t_min), max(spans_us[i, 1], t_max)
    uncovered = _uncovered(loader, lidar_id, spans_us)
    first = f" ({unreadable[0]})" if unreadable else ""
    report.add(
        f"{name}: frames readable", not unreadable, f"{len(unreadable)} of {lidar.frames_count} unreadable{first}"
    )
    report.add(f"{name}: unit directions", worst_norm <= UNIT_TOLERANCE, f"max |norm - 1| = {worst_norm:.2e}")
    report.add(f"{name}: point times within frames", outside_time == 0, f"{outside_time} of {points} points outside")
    report.add(f"{name}: intensity in [0, 1]", bad_intensity == 0, f"{bad_intensity} of {points} outside")
    if model is not None:
        report.add(
            f"{name}: model elements within the model",
            bad_element == 0,
            f"{bad_element} outside {model.n_rows} rows x {model.n_columns} columns",
        )
    which = f": {uncovered[:5]}" if uncovered else ""
    report.add(
        f"{name}: poses cover every frame and point time",
        not uncovered,
        f"{len(uncovered)} of {lidar.frames_count} frames uncovered{which}",
    )
    return not uncovered and not unreadable and outside_time == 0  # what motion compensation needs


def _check_camera(report: Report, loader: SequenceLoaderV4, camera_id: str, lidar_frames_us: np.ndarray | None) -> None:
    camera = loader.get_camera_sensor(camera_id)
    frames_us = camera.frames_timestamps_us
    name = f"camera {camera_id}"
    _within_sequence(report, name, frames_us, loader.sequence_timestamp_interval_us)
    _regularity(report, name, frames_us[:, 1])
    _check_ego_mask(report, camera, name)
    uncovered = _uncovered(loader, camera_id, frames_us)
    report.add(f"{name}: poses cover every frame", not uncovered, f"{len(uncovered)} of {len(frames_us)} uncovered")
    if lidar_frames_us is not None and len(lidar_frames_us) and len(frames_us):
        mid_cam = frames_us.astype(np.float64).mean(axis=1)
        mid_lidar = lidar_frames_us.astype(np.float64).mean(axis=1)
        nearest = np.abs(mid_cam[:, None] - mid_lidar[None, :]).min(axis=1)
        report.add(
            f"{name}: time sync to the lidar",
            True,
            f"|camera - nearest lidar frame| mid-times: median {np.median(nearest) / 1e3:.1f} ms,"
            f" max {nearest.max() / 1e3:.1f} ms",
        )


def _check_ego_mask(report: Report, camera, name: str) -> None:
    """A present ``ego`` mask has the camera's resolution and covers a plausible share of it."""
    mask = camera.get_mask_images().get(contract.EGO_MASK)
    if mask is None:
        return
    width, height = (int(v) for v in camera.model_parameters.resolution)
    covered = float((np.asarray(mask) > 0).mean())
    ok = mask.size == (width, height) and 0.0 < covered <= contract.EGO_MASK_MAX_FRACTION
    report.add(
        f"{name}: ego mask",
        ok,
        f"{mask.size[0]}x{mask.size[1]} px for a {width}x{height} camera,"
        f" covers {covered:.2%} (plausible: above 0, at most {contract.EGO_MASK_MAX_FRACTION:.0%})",
    )


def _check_world_global(report: Report, loader: SequenceLoaderV4) -> None:
    """``world -> world_global`` is what the sequence's ``--world-global-mode`` says: the dataset's
    global frame (localized), the identity, or absent (none)."""
    record = loader.generic_meta_data.get(contract.WORLD_GLOBAL) or {"mode": "localized"}
    mode = record.get("mode", "localized")
    present = "world_global" in loader.pose_graph.nodes
    if mode == "none":
        report.add(
            "no world_global (--world-global-mode none)",
            not present,
            f"world_global node {'present' if present else 'absent'}",
        )
        return
    name = "world_global in the pose graph"
    if not present:
        report.add(name, False, f"no static world -> world_global edge (--world-global-mode {mode})")
        return
    edge = world_global_edge(loader)
    expected = np.eye(4) if mode == "identity" else np.asarray(record.get("T_world_dataset_global", edge))
    error_m = float(np.abs(edge - expected).max())
    # the same float64 values written to the pose store and the metadata; reading the edge back may
    # compose it once: EDGE_STEPS float64 steps of its largest element
    tolerance_m = EDGE_STEPS * float(np.spacing(np.abs(expected).max()))
    report.add(
        name,
        error_m <= tolerance_m,
        f"static edge as --world-global-mode {mode}: max |edge - expected| = {error_m:.1e} (<= {tolerance_m:.1e})",
    )


def _check_window(report: Report, loader: SequenceLoaderV4, cuboids: CuboidColumns) -> None:
    """With a clip window: camera frames and cuboids lie in it, and every lidar frame overlaps it."""
    clip = loader.generic_meta_data.get(contract.CLIP)
    if not clip:
        return
    start, end = int(clip["start_us"]), int(clip["end_us"])
    outside = []
    for camera_id in sorted(loader.camera_ids):
        frames_us = loader.get_camera_sensor(camera_id).frames_timestamps_us.astype(np.int64)
        outside += [f"{camera_id}[{i}]" for i in np.flatnonzero((frames_us[:, 1] < start) | (frames_us[:, 1] > end))]
    for lidar_id in sorted(loader.lidar_ids):
        frames_us = loader.get_lidar_sensor(lidar_id).frames_timestamps_us.astype(np.int64)
        outside += [f"{lidar_id}[{i}]" for i in np.flatnonzero((frames_us[:, 1] < start) | (frames_us[:, 0] > end))]
    t_us = cuboids.timestamp_us
    outside += [f"cuboid {cuboids.track_id[i]}@{t_us[i]}" for i in np.flatnonzero((t_us < start) | (t_us > end))]
    report.add(
        "frames and cuboids within the clip window",
        not outside,
        f"[{start}, {end}] us ({(end - start) / 1e6:.3f} s); {len(outside)} outside"
        + (f": {outside[:3]}" if outside else ""),
    )


def _check_dynamic_flag(report: Report, loader: SequenceLoaderV4, lidar_id: str) -> None:
    """Where the lidar has ``dynamic_flag``, every frame has one int8 value in {0, 1} per ray; where it
    has ``dynamic_flag_unknown`` too, the same, and never 1 on a flagged ray."""
    source = loader.get_point_clouds_source(lidar_id)
    if not source.pcs_count or not source.has_pc_generic_data(0, contract.DYNAMIC_FLAG):
        return
    with_unknown = source.has_pc_generic_data(0, contract.DYNAMIC_UNKNOWN)
    bad, bad_unknown, lidar = [], [], loader.get_lidar_sensor(lidar_id)
    for i in range(source.pcs_count):
        try:
            flag = source.get_pc_generic_data(i, contract.DYNAMIC_FLAG)
            unknown = source.get_pc_generic_data(i, contract.DYNAMIC_UNKNOWN) if with_unknown else None
            n = lidar.get_frame_ray_bundle_count(i)
        except (KeyError, ValueError, OSError):  # an unreadable frame: "frames readable" names it
            continue
        if not _binary_per_ray(flag, n):
            bad.append(i)
        elif unknown is not None and (not _binary_per_ray(unknown, n) or np.any((unknown == 1) & (flag == 1))):
            bad_unknown.append(i)
    report.add(
        f"lidar {lidar_id}: dynamic_flag per ray",
        not bad,
        f"int8 in {{0, 1}}, one per ray; {len(bad)} of {source.pcs_count} frames not",
    )
    if with_unknown:
        report.add(
            f"lidar {lidar_id}: {contract.DYNAMIC_UNKNOWN} per ray",
            not bad_unknown,
            f"int8 in {{0, 1}}, one per ray, 0 where dynamic_flag is 1; {len(bad_unknown)} of"
            f" {source.pcs_count} frames not",
        )


def _binary_per_ray(values: np.ndarray, n: int) -> bool:
    """Whether ``values`` is one int8 0 or 1 per ray of a frame of ``n`` rays."""
    return values.dtype == np.int8 and values.shape == (n,) and (not n or values.view(np.uint8).max() <= 1)


def _lidar_checks(sequence: OpenSequence, lidar_id: str, cuboids: CuboidColumns) -> list:
    """One lidar's checks: every frame read back (:func:`_check_lidar`, ``dynamic_flag``), then, when
    the frames allow it, the boxes' occupancy on the sampled frames."""
    part = Report("")
    if _check_lidar(part, sequence.loader, lidar_id) and len(cuboids):
        check_occupancy(part, sequence, lidar_id, cuboids)
    _check_dynamic_flag(part, sequence.loader, lidar_id)
    return part.checks


def lidar_checks_job(sequence_json: UPath, lidar_id: str, progress=None) -> tuple[list, dict]:
    """:func:`_lidar_checks` as a pool job (``progress``: unused), so that a log's lidars are checked
    in its idle workers while the parent checks the rest: the checks, and the sampled frames' world
    points (the source comparison counts box points on the same frames)."""
    sequence = open_sequence(sequence_json)
    try:
        cuboids = read_cuboids(sequence.reader) or CuboidColumns.from_stored([])
    except ValueError:  # the parent's "cuboids: readable" names it
        cuboids = CuboidColumns.from_stored([])
    return _lidar_checks(sequence, lidar_id, cuboids), sequence.computed_points()


def validate_sequence(
    sequence_json: UPath,
    source_root: UPath | None = None,
    run_jobs: RunJobs | None = None,
    reader: Reader | None = None,
) -> Report:
    """Open a sequence (its ``<sequence_id>.json``) with the default instance names and check it;
    with ``source_root`` (the converter's --root-dir), also compare it with the source. With
    ``run_jobs`` (a worker pool's ``run``), each lidar is checked by a worker job
    (:func:`lidar_checks_job`) while this process checks the rest: the same checks in the same
    order either way."""
    report = Report(str(sequence_json))
    try:
        sequence = open_sequence(sequence_json)
    except Exception as err:  # noqa: BLE001 - any failure to open is the finding
        report.add("opens with SequenceLoaderV4", False, open_failure(sequence_json, err))
        return report
    loader = sequence.loader
    report.add(
        "opens with SequenceLoaderV4", True, f"{len(loader.lidar_ids)} lidar(s), {len(loader.camera_ids)} camera(s)"
    )
    # sensors in name order: the loader lists them in the order their stores finished loading
    lidar_ids, camera_ids = sorted(loader.lidar_ids), sorted(loader.camera_ids)
    with ThreadPoolExecutor(1) as waiter:  # waits on the workers while this thread checks
        jobs = [(lidar_checks_job, (sequence_json, lidar_id)) for lidar_id in lidar_ids]
        pending = waiter.submit(run_jobs, jobs) if run_jobs is not None and jobs else None
        _check_world_global(report, loader)
        try:
            cuboids = read_cuboids(sequence.reader)
        except ValueError as err:
            report.add("cuboids: readable", False, f"{contract.DEFAULT_INSTANCE} cuboids component: {err}")
            cuboids = None
        if cuboids is not None:
            check_cuboids(report, loader, cuboids)
        cuboids = cuboids if cuboids is not None else CuboidColumns.from_stored([])
        _check_window(report, loader, cuboids)
        cameras = Report(report.sequence)
        lidar_frames = loader.get_lidar_sensor(lidar_ids[0]).frames_timestamps_us if lidar_ids else None
        held = held_boxes(loader, cuboids) if loader.camera_labels_ids else None  # once: masks are checked on it
        for camera_id in camera_ids:
            _check_camera(cameras, loader, camera_id, lidar_frames)
            check_camera_labels(cameras, loader, camera_id, held)
        if pending is None:
            report.checks += [c for lidar_id in lidar_ids for c in _lidar_checks(sequence, lidar_id, cuboids)]
        for checks, points in pending.result() if pending else []:
            report.checks += checks
            sequence.keep_points(points)
        report.checks += cameras.checks
    if source_root is not None:
        compare_with_source(report, sequence, source_root, cuboids, reader)
    return report
