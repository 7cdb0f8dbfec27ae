"""Argoverse 2 Sensor and TbV, per log: write a planned log (``plan.py``) through the NCore writer.

The log's writing jobs (base components, all lidars, each camera) are grouped into parts that share
no component store, so the parts can run in separate worker processes; lidar sweeps and images are
streamed one at a time, so memory stays flat.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace

import numpy as np
from upath import UPath

from ncore_convert import contract
from ncore_convert.converters import consumer
from ncore_convert.converters.argoverse2.colours import COLOURS_TAKEN_FROM, SweepColours
from ncore_convert.converters.argoverse2.labels import FrameLabeller
from ncore_convert.converters.argoverse2.lidar import lidar_meta, sweep_frame, sweep_times_ns
from ncore_convert.converters.argoverse2.masks import EgoMask
from ncore_convert.converters.argoverse2.motion import LIDAR_FLAGS, with_motion
from ncore_convert.converters.argoverse2.plan import Argoverse2Options, LogPlan, plan_log
from ncore_convert.converters.common import Counts, LidarStore
from ncore_convert.errors import SourceError, warnings_kept
from ncore_convert.run.pool import JobPool, Progress, run_inline
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import argoverse2_annotations as av2_annotations
from ncore_convert.sources import argoverse2_map as av2_map
from ncore_convert.sources.reader import Reader, with_reader
from ncore_convert.transforms.geometry import euler_xyz_from_rotation
from ncore_convert.transforms.lidar.frames import (
    LidarFrame,
    LidarGeometry,
    PointData,
    lidar_frame,
    point_data_notes,
)
from ncore_convert.transforms.timebase import floor_us
from ncore_convert.writer import Cuboids, SequenceWriter, write_sequence_meta
from ncore_convert.writer.parts import BASE_JOB, WriteJob, independent_parts


@dataclass
class LogSummary(Counts):
    """What one log conversion produced."""

    log_id: str = ""
    seconds: float = 0.0  #: wall time of the whole log
    validation: dict | None = None  #: set by validate.tree.convert_and_validate (None: not validated)
    lidar_model_seconds: float = 0.0  #: slowest per-unit lidar model derivation

    def line(self) -> str:
        return (
            f"{self.log_id}: {self.frames} sweeps, {self.points} points"
            f" ({self.points_not_stored} not representable), {self.images} images,"
            f" {self.cuboids} cuboids, {'an HD map' if self.maps else 'no HD map'}"
            + (f", {self.camera_labels} camera labels" if self.camera_labels else "")
            + f", {self.seconds:.1f} s"
            + (f", {len(self.warnings)} warning(s)" if self.warnings else "")
        )


@dataclass
class JobResult(Counts):
    """Counts of the jobs of one writer part, and its sequence-meta part (None without meta)."""

    meta: object = None


def annotation_cuboids(annotations: av2_annotations.Annotations, class_ids: list[str]) -> Cuboids:
    """AV2 cuboids (ego frame at the sweep time) as rig-frame observations with full xyz-Euler rotation,
    named ``class_ids`` [M]."""
    return Cuboids(
        track_ids=annotations.track_uuids,
        class_ids=class_ids,
        timestamps_us=floor_us(annotations.timestamps_ns),
        centroids_m=annotations.T_object_ego[:, :3, 3],
        dims_m=annotations.dims_m,
        euler_xyz_rad=euler_xyz_from_rotation(annotations.T_object_ego[:, :3, :3]),
    )


def _camera_meta(intr: av2.CameraIntrinsics, spec: consumer.CameraSpec, ego_mask: EgoMask) -> dict:
    return {
        "camera_model": spec.meta(),
        "ego_mask": ego_mask.meta,
        "av2_original_distortion": {"k1": intr.k1, "k2": intr.k2, "k3": intr.k3},
        "av2_principal_point_px": {"cx": intr.cx_px, "cy": intr.cy_px},
        "principal_point_note": "stored principal point = av2 (cx, cy) + 0.5 (NCore pixel-corner convention)",
    }


def _open_writer(plan: LogPlan, output_dir: UPath, base: bool) -> SequenceWriter:
    return SequenceWriter(
        output_dir=output_dir,
        sequence_id=plan.log_id,
        interval_us=(plan.T_rig_world.start_us, plan.T_rig_world.end_us),
        generic_meta_data=plan.generic_meta,
        camera_ids=plan.camera_ids,
        lidar_ids=plan.lidar_ids,
        store_type=plan.options.store_type,
        profile=plan.options.profile,
        base=base,
        label_ids=plan.label_ids,
        poses_meta={
            "calibration_type": "argoverse2-calibration",
            "egomotion_type": "argoverse2-city_SE3_egovehicle",
        },
    )


def _write_base(
    plan: LogPlan, writer: SequenceWriter, result: JobResult, progress: Callable[[int], None], reader: Reader
) -> None:
    """Poses (trajectory, world_global, sensor extrinsics), camera and lidar models, masks and cuboids."""
    inputs = plan.inputs
    writer.store_trajectory(plan.T_rig_world.timestamps_us, plan.T_rig_world.poses, plan.T_world_world_global)
    for sensor in plan.lidar_ids + plan.camera_ids:
        writer.store_extrinsic(sensor, inputs.T_sensor_ego[sensor])  # av2's egovehicle is NCore's rig
    for cam in plan.camera_ids:
        spec = plan.cameras[cam]
        mask = plan.ego_masks[cam].image(*spec.pinhole.resolution_px)
        masks = {contract.EGO_MASK: mask} if mask is not None else {}
        writer.store_camera(cam, spec.pinhole, spec.model, spec.ftheta, masks)
    if plan.lidar_calibration is not None:
        for unit, model in plan.lidar_calibration.models.items():
            writer.store_lidar_model(unit, model)
    labels = plan.cuboid_labels
    if labels is not None:
        cuboids = annotation_cuboids(inputs.annotations, labels.class_ids)
        writer.store_cuboids(cuboids, labels.label_source, labels.meta)
    else:
        cuboids = None
        writer.store_cuboids(None)
    if plan.options.maps:
        _store_map(inputs.log_dir, writer, result, reader)
    result.cuboids = 0 if cuboids is None else len(cuboids)


def _store_map(log_dir: UPath, writer: SequenceWriter, result: JobResult, reader: Reader) -> None:
    """The log's HD map, as stored, in the city frame (= world_global), or a warning without one."""
    log_map = av2_map.read_log_map(log_dir, reader)
    if log_map is None:
        result.warnings.append(f"{log_dir / 'map'}: no map folder; no HD map written")
        return
    vector_name, raster_name, sim2_name = log_map.file_names
    writer.store_map(
        log_map.vector_map_json,
        log_map.ground_height_m,
        {
            "frame": "world_global (the AV2 city frame)",
            "vector_map_file": vector_name,
            "ground_height_file": raster_name,
            "img_Sim2_city_file": sim2_name,
            "city": vector_name.split("____")[1].split("_")[0] if "____" in vector_name else None,
            "img_Sim2_city": log_map.img_Sim2_city,
            "raster_lookup": "p_img = s * (R @ [x, y] + t) with (x, y) in world_global metres, R row-major 2x2;"
            " value = ground_height_m[int(p_img[1]), int(p_img[0])] (truncation; NaN outside the region of interest)",
            "resolution_m": 1.0 / float(log_map.img_Sim2_city["s"]),
        },
    )
    result.maps = 1


def _frames(plan: LogPlan, reader: Reader) -> Iterator[tuple[int, LidarFrame, dict[str, LidarGeometry], np.ndarray]]:
    """Each sweep of the log, one at a time: read, its points' own times, split by unit and how each
    unit's rays are made (:func:`sweep_frame`): (its timestamp ns, the frame, the units' geometry, every
    row's ``laser_number``)."""
    calibration = plan.lidar_calibration
    T_sensor_rig = {unit: plan.inputs.T_sensor_ego[unit] for unit in plan.lidar_ids}
    inputs = plan.inputs
    sweeps = av2.read_sweeps(
        inputs.log_dir, plan.sweep_timestamps_ns, not plan.options.tbv, inputs.files, reader=reader
    )
    for sweep in sweeps:
        sweep_ns = sweep.timestamp_ns
        times_ns = sweep_times_ns(sweep, calibration, plan.T_rig_world, T_sensor_rig)  # once, for everything
        frame, geometry = sweep_frame(sweep, times_ns, calibration, plan.T_rig_world, T_sensor_rig)
        yield int(sweep_ns), frame, geometry, sweep.laser_number


def _sweeps(
    plan: LogPlan, reader: Reader, colours: SweepColours | None, motion: bool = False
) -> Iterator[tuple[int, dict, PointData]]:
    """Each sweep of the log, one at a time (:func:`_frames`), its rays, model elements and per-point
    data assigned (``lidar_frames.lidar_frame``): (its timestamp ns, the units' rays, the point data).
    ``motion``: with what the lidar itself saw move (``plan.dynamic_source`` lidar or both; the
    frames are held a few sweeps for it, :func:`motion.with_motion`)."""
    frames = _frames(plan, reader)
    boxes = plan.stored_flag_boxes if motion else plan.dynamic_boxes  # the label jobs keep the annotated movers
    colouring = None if colours is None else colours.colours
    if not (motion and plan.moves_from_lidar):
        for sweep_ns, frame, geometry, _ in frames:
            units, data = lidar_frame(frame, geometry, boxes, colouring)
            yield sweep_ns, units, data
        return
    T_sensor_rig = {unit: plan.inputs.T_sensor_ego[unit] for unit in plan.lidar_ids}
    for sweep_ns, frame, geometry, moved, seconds in with_motion(frames, plan.T_rig_world, T_sensor_rig):
        units, data = lidar_frame(frame, geometry, boxes, colouring, replace(moved, parked=plan.parked_boxes))
        data.flag_seconds += seconds
        yield sweep_ns, units, data


def _write_lidars(
    plan: LogPlan,
    writer: SequenceWriter,
    job: WriteJob,
    result: JobResult,
    progress: Callable[[int], None],
    reader: Reader,
) -> None:
    """Stream sweeps one at a time (:func:`_sweeps`) and store them. Memory stays flat."""
    started = time.perf_counter()
    calibration = plan.lidar_calibration
    colours = SweepColours(plan, reader) if plan.options.lidar_rgb and plan.camera_ids else None
    flag_meta = point_data_notes(
        plan.stored_flag_boxes,
        "TbV has no cuboids" if plan.options.tbv else "the log has no annotations",
        plan.options.lidar_rgb,
        bool(plan.camera_ids),
        COLOURS_TAKEN_FROM,
        LIDAR_FLAGS if plan.moves_from_lidar else "",
    )
    lidars = {  # one metadata dict per lidar: the writer updates it in place
        unit: LidarStore(
            writer.add_lidar(unit, {**lidar_meta(calibration, unit, plan.options.lidar_model_source), **flag_meta}),
            colours is not None,
        )
        for unit in plan.lidar_ids
    }
    for sweep_ns, units, data in _sweeps(plan, reader, colours, motion=True):
        result.dynamic_flag_seconds += data.flag_seconds
        result.colour_seconds += data.colour_seconds
        for unit, unit_rays in units.items():
            rays = unit_rays.rays
            frame_meta = {
                "av2_sweep_timestamp_ns": sweep_ns,
                "points_zero_range": rays.n_zero_range,
                "points_non_finite": rays.n_non_finite,
            }
            if unit_rays.column_time_remap:
                frame_meta["model_column_time_remap"] = unit_rays.column_time_remap
            lidars[unit].store(unit_rays, frame_meta)
        result.frames += 1
        progress(1)
    for unit, store in lidars.items():
        tally = store.tally
        figures = {
            "source_points": tally.stored + tally.not_stored,
            contract.POINTS_NOT_STORED: {"zero_range": tally.zero_range, "non_finite": tally.non_finite},
        }
        store.finish(figures, result, unit)
    result.lidar_seconds = time.perf_counter() - started


def _write_labels(plan: LogPlan, writer: SequenceWriter, job: WriteJob, result: JobResult, reader: Reader) -> None:
    """The camera labels ``job.label_ids`` (every kind of some cameras) in a job of their own: the
    sweeps streamed again (:func:`_sweeps`, not stored: the lidars' job stores them), each camera frame
    labelled from the sweep nearest it."""
    cameras = [
        cam
        for cam in plan.camera_ids
        if any(contract.camera_label_id(k, cam) in job.label_ids for k in plan.label_kinds)
    ]
    labeller = FrameLabeller(plan, writer, cameras)
    if labeller.shapes is not None:  # a first pass: the static vehicles' shapes from every sweep
        for _, _, data in _sweeps(plan, reader, None, motion=False):
            labeller.gather(data.xyz_fixed_m, data.timestamps_us, data.spacing_m)
    for _, _, data in _sweeps(plan, reader, None, motion=plan.label_movers_from_lidar):
        labeller.add_sweep(data.xyz_fixed_m, data.timestamps_us, data.dynamic, data.spacing_m, data.unknown)
    labeller.finish()
    result.camera_labels += labeller.labels
    result.label_seconds += labeller.seconds


def _write_camera(
    plan: LogPlan, writer: SequenceWriter, cam: str, result: JobResult, progress: Callable[[int], None], reader: Reader
) -> None:
    """Copy every JPEG as-is into its camera component, with frame times [t, t] (global shutter)."""
    started = time.perf_counter()
    stream = writer.add_camera(cam, _camera_meta(plan.inputs.intrinsics[cam], plan.cameras[cam], plan.ego_masks[cam]))
    stamps_ns = plan.inputs.image_timestamps_ns[cam]
    images = av2.read_images(plan.inputs.log_dir, cam, stamps_ns, plan.inputs.files, reader=reader)
    for image_ns, (_, data) in zip(stamps_ns.tolist(), images, strict=True):
        if isinstance(data, SourceError):
            raise data
        t_us = floor_us(image_ns)
        stream.store_frame(av2.read_jpeg(plan.inputs.log_dir, cam, image_ns, data), "jpeg", (t_us, t_us))
        result.images += 1
        progress(1)
    result.camera_seconds += time.perf_counter() - started


def write_part(plan: LogPlan, output_dir: UPath, jobs: list[WriteJob], progress: Callable[[int], None]) -> JobResult:
    """Write the jobs of one independent part (see :func:`log_jobs`) with one writer; runs in a
    worker, reading with a reader of its own that shares the log's spool (its counts in the result)."""
    result = JobResult()
    with warnings_kept(result.warnings), Reader(plan.inputs.reading) as reader:
        writer = _open_writer(plan, output_dir, base=BASE_JOB in jobs)
        for job in jobs:
            if job.base:
                _write_base(plan, writer, result, progress, reader)
            elif not job.sensor_ids:
                _write_labels(plan, writer, job, result, reader)
            elif job.sensor_ids == tuple(plan.lidar_ids):
                _write_lidars(plan, writer, job, result, progress, reader)
            else:
                (cam,) = job.sensor_ids
                _write_camera(plan, writer, cam, result, progress, reader)
        result.meta = writer.finalize(with_meta=plan.options.sequence_meta)
        if (line := reader.not_kept_warning()) is not None:
            result.warnings.append(line)
        result.reads = asdict(reader.counts)
    return result


#: Rough single-core costs used to start the longest parts first (seconds per item; a label: one
#: kind of one camera frame).
_COST_S = {"sweep": 0.05, "image": 0.0035, "cuboid": 0.00025, "label": 0.035}


@dataclass(frozen=True)
class LogPart:
    """Jobs that one writer (and one worker process) writes, with their estimated cost."""

    jobs: list[WriteJob]
    cost_s: float


def log_jobs(plan: LogPlan, workers: int = 1) -> list[LogPart]:
    """The log's writing jobs grouped into independent parts, with an estimated cost per part.

    Jobs: the base components, all lidars (they share each sweep read), one per camera (its images),
    and the camera labels in jobs of their own, one per worker (``workers``, at most one per camera;
    every kind of a camera in one job). Each label job streams the sweeps again (about 50 ms a sweep,
    for about 30 ms a label), so there are no more of them than the workers that can make them at
    once: the labels, most of a labelled log's work, then end together. Parts are in store order:
    base first, then lidars, then cameras.
    """
    labelled = [cam for cam in plan.camera_ids if plan.label_kinds]
    n_label_jobs = min(len(labelled), max(1, workers))  # sharing the cameras evenly
    label_jobs = [
        tuple(contract.camera_label_id(k, cam) for cam in labelled[i::n_label_jobs] for k in plan.label_kinds)
        for i in range(n_label_jobs)
    ]
    jobs = [BASE_JOB] + ([WriteJob(tuple(plan.lidar_ids))] if plan.lidar_ids else [])
    jobs += [WriteJob((cam,)) for cam in plan.camera_ids]
    jobs += [WriteJob((), label_ids=ids) for ids in label_jobs]
    n_cuboids = 0 if plan.inputs.annotations is None else len(plan.inputs.annotations)
    n_images = {cam: len(plan.inputs.image_timestamps_ns[cam]) for cam in plan.camera_ids}
    frames_of = {contract.camera_label_id(k, cam): n for cam, n in n_images.items() for k in plan.label_kinds}
    n_sweeps = len(plan.sweep_timestamps_ns)
    cost = [_COST_S["cuboid"] * n_cuboids] + ([_COST_S["sweep"] * n_sweeps] if plan.lidar_ids else [])
    cost += [_COST_S["image"] * n_images[cam] for cam in plan.camera_ids]
    cost += [_COST_S["sweep"] * n_sweeps + _COST_S["label"] * sum(frames_of[i] for i in ids) for ids in label_jobs]
    parts = independent_parts(jobs, plan.camera_ids, plan.lidar_ids, plan.options.profile, plan.label_ids)
    return [LogPart([jobs[i] for i in part], sum(cost[i] for i in part)) for part in parts]


def convert_log(
    root_dir: UPath,
    output_dir: UPath,
    log_id: str,
    options: Argoverse2Options,
    pool: JobPool | None = None,
    progress: Progress | None = None,
    reader: Reader | None = None,
) -> LogSummary:
    """Convert one AV2 log into ``output_dir`` (which becomes the sequence directory).

    Args:
        pool: worker processes for the log's independent store parts; None writes them in this process.
        progress: told the number of frames (sweeps + images) to write, then each written frame.
        reader: the log's reader (its owner closes it: the run's log task); None: one for this call.
    """
    return with_reader(_convert_log, root_dir, output_dir, log_id, options, pool, progress, reader=reader)


def _convert_log(
    root_dir: UPath,
    output_dir: UPath,
    log_id: str,
    options: Argoverse2Options,
    pool: JobPool | None,
    progress: Progress | None,
    *,
    reader: Reader,
) -> LogSummary:
    started = time.perf_counter()
    progress = progress or Progress()
    plan = plan_log(root_dir, log_id, options, pool.run if pool else None, reader)
    if (line := reader.not_kept_warning()) is not None:
        plan.warnings.append(line)
    progress.total(plan.n_frames)
    parts = log_jobs(plan, pool.workers if pool else 1)
    output_dir.mkdir(parents=True, exist_ok=True)
    longest_first = sorted(range(len(parts)), key=lambda i: -parts[i].cost_s)
    calls = [(write_part, (plan, output_dir, parts[i].jobs)) for i in longest_first]
    with warnings_kept(plan.warnings):
        done = pool.run(calls, progress) if pool else run_inline(calls, progress)
    results = [done[longest_first.index(i)] for i in range(len(parts))]

    if options.sequence_meta:
        write_sequence_meta(output_dir, log_id, [r.meta for r in results if r.meta is not None])
    summary = LogSummary(log_id=log_id, warnings=list(plan.warnings))  # reads: the parts' (workers')
    if plan.lidar_calibration is not None:
        summary.lidar_model_seconds = max(plan.lidar_calibration.model_seconds.values(), default=0.0)
    for result in results:
        summary.add(result)
    summary.seconds = time.perf_counter() - started
    return summary
