"""Argoverse 2 Sensor and TbV, per log: read the small inputs, check them, and decide once what every
writing job needs (sensors, ego trajectory, lidar calibration). TbV is a mode of the same plan
(``Argoverse2Options.split`` None).

Frame mapping: AV2 ``egovehicle`` is NCore ``rig``; ``world`` is the city frame re-referenced to the
first ego pose (of the clip window, with one); ``world_global`` is by default the AV2 city frame (static
float64 edge ``T_world_world_global``, the first ego pose in the city; ``--world-global-mode``).
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace

import numpy as np
from upath import UPath

from ncore_convert import contract
from ncore_convert.contract import LidarModelSource, Profile, StoreType
from ncore_convert.converters import consumer
from ncore_convert.converters.argoverse2.inputs import LogInputs, ego_trajectory, read_log_inputs, sensor_time_range_us
from ncore_convert.converters.argoverse2.lidar import LidarCalibration, TriggerTiming, calibrate_lidars
from ncore_convert.converters.argoverse2.masks import EgoMask, plan_ego_masks
from ncore_convert.converters.argoverse2.motion import MOTION_META
from ncore_convert.converters.common import ConsumerOptions, select_sensors
from ncore_convert.errors import SourceError, UsageError, warnings_kept
from ncore_convert.run.pool import Job
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.reader import Reader, reading
from ncore_convert.transforms.camera.ego_mask import EgoBox
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.geometry import Trajectory
from ncore_convert.transforms.lidar import timing as lidar_timing
from ncore_convert.transforms.objects import classes
from ncore_convert.transforms.objects.cores import kind_of
from ncore_convert.transforms.objects.dynamic import DynamicBoxes, SolidBoxes, TrackObservations, static_boxes
from ncore_convert.transforms.timebase import WindowError, floor_us, in_window

#: Below this margin the unit decision is reported as a warning.
UNIT_DECISION_MIN_MARGIN = 2.0


@dataclass(frozen=True)
class Argoverse2Options(ConsumerOptions):
    """Options of the ``argoverse2-v4`` and ``tbv-v4`` commands (sensor selection: None = all available).

    ``split`` is the AV2 Sensor split folder; None for TbV, whose logs sit directly under the root
    and have no per-point times (they are reconstructed, see :mod:`ncore_convert.transforms.lidar.timing`).
    """

    split: str | None
    store_type: StoreType = "itar"
    profile: Profile = "separate-sensors"
    sequence_meta: bool = True
    lidar_model_source: LidarModelSource = "empirical"
    maps: bool = True
    ego_masks: str = "estimate"  #: "estimate", "none", or a folder of <camera_id>.png
    ego_box_m: tuple[float, float, float] = EgoBox().dims_m  #: the nominal ego vehicle (length, width, height)
    camera_ids: tuple[str, ...] | None = None
    lidar_ids: tuple[str, ...] | None = None
    camera_labels: tuple[str, ...] = ()  #: ``contract.CAMERA_LABEL_KINDS`` written per camera frame
    #: where ``dynamic_flag`` comes from: ``annotations``, ``lidar`` (free space, docs/motion.md) or ``both``;
    #: None: ``annotations``, but ``lidar`` for a TbV log (it has no cuboids)
    dynamic_source: str | None = None

    @property
    def tbv(self) -> bool:
        return self.split is None

    def log_dir(self, root_dir: UPath, log_id: str) -> UPath:
        return av2.log_dir(root_dir, self.split, log_id)


def _trigger_timing(inputs: LogInputs) -> TriggerTiming:
    """The camera-trigger grid from every image and pose timestamp, and the ring cameras' extrinsics."""
    candidates = np.concatenate([inputs.pose_timestamps_ns, *inputs.image_timestamps_ns.values()])
    try:
        grid = lidar_timing.trigger_phases_ns(np.setdiff1d(candidates, inputs.sweep_timestamps_ns))
    except lidar_timing.TimingError as err:
        raise SourceError(av2.poses_path(inputs.log_dir), f"cannot time the lidar points: {err}") from None
    rings = [cam for cam in av2.RING_CAMERAS if cam in inputs.T_sensor_ego]
    if not rings:
        raise SourceError(av2.extrinsics_path(inputs.log_dir), "no ring camera extrinsics")
    return TriggerTiming(grid, [inputs.T_sensor_ego[cam] for cam in rings])


@dataclass(frozen=True)
class LogPlan:
    """Everything the writing jobs of one log need, read and decided once (picklable).

    Attributes:
        T_rig_world: stored (float32-rounded) ego trajectory, µs.
        lidar_calibration: unit split and models (None without lidars).
        T_world_world_global: what the static ``world -> world_global`` edge holds (None: no edge,
            ``--world-global-mode none``); the city frame is in ``generic_meta`` in every mode.
        window_us: the clip window (inclusive µs), None for the whole log.
        cameras: how each camera is stored (model type, f-theta fit).
        cuboid_labels: class names, label source and dynamic tracks (None without annotations).
        dynamic_boxes: the dynamic tracks' boxes in ``world`` (None: no ``dynamic_flag`` from them).
        solids: every track's box in ``world``: occluders for ``--lidar-rgb`` and depth labels, and
            what the box labels show (None: none of them, or no annotations).
        ego_masks: each camera's ego mask (``--ego-masks``).
        dynamic_source: where ``dynamic_flag`` comes from (``Argoverse2Options.dynamic_source``, resolved).
        parked_boxes: the standing tracks' boxes, where no point is flagged from the lidar (``both``).
    """

    inputs: LogInputs
    options: Argoverse2Options
    log_id: str
    camera_ids: list[str]
    lidar_ids: list[str]
    T_rig_world: Trajectory
    T_world_world_global: np.ndarray | None
    lidar_calibration: LidarCalibration | None
    generic_meta: dict
    warnings: list[str]
    window_us: tuple[int, int] | None = None
    cameras: dict[str, consumer.CameraSpec] | None = None
    cuboid_labels: consumer.CuboidLabels | None = None
    dynamic_boxes: DynamicBoxes | None = None
    solids: SolidBoxes | None = None
    ego_masks: dict[str, EgoMask] | None = None
    dynamic_source: str = "annotations"
    parked_boxes: tuple[DynamicBoxes, np.ndarray, np.ndarray] | None = None

    @property
    def stored_flag_boxes(self) -> DynamicBoxes | None:
        """The boxes whose points the stored ``dynamic_flag`` flags (None with ``--dynamic-source lidar``:
        the lidar's alone). The camera-label jobs keep ``dynamic_boxes`` whatever the source."""
        return None if self.dynamic_source == "lidar" else self.dynamic_boxes

    @property
    def moves_from_lidar(self) -> bool:
        """Whether ``dynamic_flag`` takes what the lidar itself saw move (``--dynamic-source lidar|both``)."""
        return self.dynamic_source in ("lidar", "both") and bool(self.lidar_ids)

    @property
    def label_movers_from_lidar(self) -> bool:
        """Whether the camera labels take their movers from what the lidar itself saw move (no annotated
        movers, flags from the lidar: TbV); else from the annotated movers (``dynamic_boxes``)."""
        return self.dynamic_boxes is None and self.moves_from_lidar

    @property
    def sweep_timestamps_ns(self) -> np.ndarray:
        return self.inputs.sweep_timestamps_ns if self.lidar_ids else np.zeros(0, dtype=np.int64)

    @property
    def label_kinds(self) -> tuple[str, ...]:
        """The ``--camera-labels`` kinds written: depth needs the lidars, the masks the annotated boxes
        (``dynamic`` without them: the movers the lidar itself found)."""
        return tuple(
            kind
            for kind in self.options.camera_labels
            if (
                self.solids is not None or (kind == "dynamic" and self.label_movers_from_lidar)
                if kind in contract.BOX_LABEL_KINDS
                else bool(self.lidar_ids)
            )
        )

    @property
    def label_ids(self) -> list[str]:
        """Every camera label component written (``contract.camera_label_id``)."""
        return [contract.camera_label_id(kind, cam) for cam in self.camera_ids for kind in self.label_kinds]

    @property
    def n_frames(self) -> int:
        return len(self.sweep_timestamps_ns) + sum(len(self.inputs.image_timestamps_ns[c]) for c in self.camera_ids)


def plan_log(
    root_dir: UPath,
    log_id: str,
    options: Argoverse2Options,
    run_jobs: Callable[[list[Job]], list] | None = None,
    reader: Reader | None = None,
) -> LogPlan:
    """Read a log's small inputs through the log's ``reader`` (one made for the plan if None), check
    them, and make the per-log decisions (trajectory, unit split); ``run_jobs`` runs the ego-mask
    estimates (``plan_ego_masks``), in the background of the rest. An error raised here carries the
    warnings so far (``errors.warnings_kept``)."""
    warnings: list[str] = []
    with warnings_kept(warnings), reading(reader) as log_reader:
        return _plan_log(root_dir, log_id, options, run_jobs, warnings, log_reader)


def _plan_log(
    root_dir: UPath,
    log_id: str,
    options: Argoverse2Options,
    run_jobs: Callable[[list[Job]], list] | None,
    warnings: list[str],
    reader: Reader,
) -> LogPlan:
    log_dir = options.log_dir(root_dir, log_id)
    reader.require_folder(log_dir, "log directory")
    lidar_ids = select_sensors(options.lidar_ids, av2.LIDARS, "lidar")
    intrinsics = None
    if options.tbv:  # the cameras are those of the log's calibration
        intrinsics = av2.read_intrinsics(log_dir, reader=reader)
        try:
            camera_ids = select_sensors(options.camera_ids, tuple(intrinsics), "camera")
        except ValueError as err:
            raise SourceError(av2.intrinsics_path(log_dir), str(err)) from None
    else:
        camera_ids = select_sensors(options.camera_ids, av2.CAMERAS, "camera")
    inputs = read_log_inputs(log_dir, camera_ids, reader, intrinsics)

    for sensor in av2.LIDARS + tuple(camera_ids):
        if sensor not in inputs.T_sensor_ego:
            raise SourceError(av2.extrinsics_path(log_dir), f"no extrinsic for {sensor!r}")
    for cam in camera_ids:
        if cam not in inputs.intrinsics:
            raise SourceError(av2.intrinsics_path(log_dir), f"no intrinsics for {cam!r}")
    camera_ids, lidar_ids = _with_frames(inputs, camera_ids, lidar_ids, warnings)
    window_us = _window(options, inputs, camera_ids, lidar_ids)
    if window_us is not None:
        inputs = _clipped(inputs, window_us)
        if lidar_ids and not len(inputs.sweep_timestamps_ns):
            seconds = (window_us[1] - window_us[0]) / 1e6
            raise UsageError(
                f"{log_dir}: the clip window [{window_us[0]}, {window_us[1]}] us ({seconds:.3f} s) holds no lidar"
                " sweep (one every 100 ms); widen --duration-sec, or convert no lidar (--no-lidars)"
            )
        camera_ids, lidar_ids = _with_frames(inputs, camera_ids, lidar_ids, warnings, " in the clip window")
    if "depth" in options.camera_labels and camera_ids and not lidar_ids:
        warnings.append(
            f"{log_dir}: no depth labels written: they are made from the lidar points, and no lidar is converted"
        )
    from_boxes = [kind for kind in options.camera_labels if kind in contract.BOX_LABEL_KINDS]
    if from_boxes and camera_ids and inputs.annotations is None:
        warnings.append(
            f"{log_dir / 'annotations.feather'}: none; no {', '.join(from_boxes)} labels written (made from the boxes)"
        )

    camera_inputs = {
        cam: (inputs.image_timestamps_ns[cam], camera_pinhole(inputs.intrinsics[cam]), inputs.T_sensor_ego[cam])
        for cam in camera_ids
    }
    mask_warnings: list[str] = []
    # The ego-mask estimates need only the cameras: they run (on run_jobs) while the rest is planned
    # here, and are collected last, so their warnings come last as before.
    with ThreadPoolExecutor(1) as background:
        masks = background.submit(
            plan_ego_masks,
            log_dir,
            options.ego_masks,
            camera_inputs,
            mask_warnings,
            EgoBox(*options.ego_box_m),
            run_jobs,
            inputs.files,
            reader,
        )
        plan = _plan_rest(log_dir, log_id, options, inputs, camera_ids, lidar_ids, window_us, warnings, reader)
        ego_masks = masks.result()
    warnings.extend(mask_warnings)
    return replace(plan, ego_masks=ego_masks)


def _plan_rest(
    log_dir: UPath,
    log_id: str,
    options: Argoverse2Options,
    inputs: LogInputs,
    camera_ids: list[str],
    lidar_ids: list[str],
    window_us: tuple[int, int] | None,
    warnings: list[str],
    reader: Reader,
) -> LogPlan:
    """The plan's decisions after the sensors and the window (all but the ego masks)."""
    needed_us = sensor_time_range_us(inputs, camera_ids, bool(lidar_ids), not options.tbv, reader)
    T_rig_world, T_world_city = ego_trajectory(inputs, needed_us, warnings, cut=window_us is not None)
    T_world_world_global, world_global_meta = consumer.world_global(
        T_world_city, options.world_global_mode, "the Argoverse 2 city frame"
    )
    lidar_calibration = None
    if lidar_ids:
        T_lidar_rig = {unit: inputs.T_sensor_ego[unit] for unit in av2.LIDARS}
        model_units = lidar_ids if options.lidar_model_source == "empirical" else []
        timing = _trigger_timing(inputs) if options.tbv else None
        lidar_calibration = calibrate_lidars(
            log_dir, inputs.sweep_timestamps_ns, T_rig_world, T_lidar_rig, model_units, timing, inputs.files, reader
        )
        split = lidar_calibration.unit_split
        if split.margin < UNIT_DECISION_MIN_MARGIN:
            warnings.append(
                f"{log_dir}: up/down lidar decision has a low margin {split.margin:.2f}"
                f" (laser_number < 32 -> {split.low_half_unit})"
            )
    generic_meta = {
        contract.SOURCE_DATASET: contract.ARGOVERSE2_TBV if options.tbv else contract.ARGOVERSE2_SENSOR,
        contract.AV2_SPLIT: options.split,
        contract.AV2_LOG_ID: log_id,
        contract.CONVERTER: contract.converter_meta(asdict(options)),
        contract.WORLD_GLOBAL: world_global_meta,
    }
    if window_us is not None:
        generic_meta[contract.CLIP] = consumer.clip_meta(options, window_us)
    cuboid_labels, dynamic_boxes, solids = _cuboid_labels(inputs, options, T_rig_world, bool(lidar_ids))
    if cuboid_labels is not None:
        warnings.extend(cuboid_labels.warnings)
    tbv_unlabelled = options.tbv and inputs.annotations is None
    dynamic_source = options.dynamic_source or ("lidar" if tbv_unlabelled else "annotations")
    parked_boxes = None
    if dynamic_source == "both" and cuboid_labels is not None and dynamic_boxes is not None:
        static = cuboid_labels.static_poses  # the standing tracks' annotations, and their median boxes
        observations = _observations(inputs, T_rig_world)
        parked_boxes = (DynamicBoxes.select(observations, set(static)), *static_boxes(static))
    if lidar_ids:
        generic_meta[contract.DYNAMIC_FLAG_SOURCE] = _flag_source_meta(dynamic_source, dynamic_boxes is not None)
    cameras = {
        cam: consumer.camera_spec(camera_pinhole(inputs.intrinsics[cam]), options.camera_model) for cam in camera_ids
    }
    return LogPlan(
        inputs=inputs,
        options=options,
        log_id=log_id,
        camera_ids=camera_ids,
        lidar_ids=lidar_ids,
        T_rig_world=T_rig_world,
        T_world_world_global=T_world_world_global,
        lidar_calibration=lidar_calibration,
        generic_meta=generic_meta,
        warnings=warnings,
        window_us=window_us,
        cameras=cameras,
        cuboid_labels=cuboid_labels,
        dynamic_boxes=dynamic_boxes,
        solids=solids,
        dynamic_source=dynamic_source,
        parked_boxes=parked_boxes,
    )


def _flag_source_meta(dynamic_source: str, annotated: bool) -> dict:
    """What the sequence metadata says of where ``dynamic_flag`` comes from."""
    from_boxes = annotated and dynamic_source in ("annotations", "both")
    meta: dict = {
        "source": " and ".join(
            name
            for name, used in (("annotations", from_boxes), ("lidar free space", dynamic_source != "annotations"))
            if used
        )
        or "none (no annotations)"
    }
    if dynamic_source != "annotations":
        meta["lidar free space"] = MOTION_META
        if dynamic_source == "both":
            meta["both"] = (
                "an annotated mover is always flagged; the lidar adds movers outside the annotations,"
                " never in a standing track's box"
            )
    return meta


def _with_frames(
    inputs: LogInputs, camera_ids: list[str], lidar_ids: list[str], warnings: list[str], where: str = ""
) -> tuple[list[str], list[str]]:
    """The cameras and lidars that have frames (``where``: e.g. in the clip window); the others are
    reported and not written."""
    sensors_dir = inputs.log_dir / "sensors"
    empty = [cam for cam in camera_ids if len(inputs.image_timestamps_ns[cam]) == 0]
    if empty:
        warnings.append(f"{sensors_dir / 'cameras'}: no images for {', '.join(empty)}{where}; cameras not written")
    if lidar_ids and len(inputs.sweep_timestamps_ns) == 0:
        warnings.append(f"{sensors_dir / 'lidar'}: no sweeps{where}; lidars not written")
        lidar_ids = []
    return [cam for cam in camera_ids if cam not in empty], lidar_ids


def camera_pinhole(intr: av2.CameraIntrinsics) -> Pinhole:
    """An AV2 camera as an NCore pinhole: the principal point moves to the pixel-corner convention."""
    return Pinhole((intr.fx_px, intr.fy_px), (intr.cx_px + 0.5, intr.cy_px + 0.5), (intr.width_px, intr.height_px))


def _window(
    options: Argoverse2Options, inputs: LogInputs, camera_ids: list[str], lidar_ids: list[str]
) -> tuple[int, int] | None:
    """The clip window over the log's sweep and image times; UsageError naming the log's duration."""
    reference = [floor_us(inputs.sweep_timestamps_ns)] if lidar_ids else []
    reference += [floor_us(inputs.image_timestamps_ns[cam]) for cam in camera_ids]
    try:
        return consumer.clip_window(options, reference)
    except WindowError as err:
        raise UsageError(f"{inputs.log_dir}: {err}") from None


def _clipped(inputs: LogInputs, window_us: tuple[int, int]) -> LogInputs:
    """The sweeps, images and annotations whose (floored µs) timestamps lie in the window."""
    annotations = inputs.annotations
    if annotations is not None:
        annotations = annotations.subset(in_window(floor_us(annotations.timestamps_ns), window_us))
    return replace(
        inputs,
        sweep_timestamps_ns=inputs.sweep_timestamps_ns[in_window(floor_us(inputs.sweep_timestamps_ns), window_us)],
        image_timestamps_ns={
            cam: stamps[in_window(floor_us(stamps), window_us)] for cam, stamps in inputs.image_timestamps_ns.items()
        },
        annotations=annotations,
    )


def _observations(inputs: LogInputs, T_rig_world: Trajectory) -> TrackObservations:
    """The annotations' boxes in ``world``."""
    annotations = inputs.annotations
    T_rig_world_at = T_rig_world.interpolate(T_rig_world.relative_seconds(annotations.timestamps_ns))
    T_box_world = T_rig_world_at @ annotations.T_object_ego
    return TrackObservations(
        annotations.track_uuids,
        floor_us(annotations.timestamps_ns),
        T_box_world[:, :3, 3],
        T_box_world[:, :3, :3],
        annotations.dims_m,
    )


def _cuboid_labels(
    inputs: LogInputs, options: Argoverse2Options, T_rig_world: Trajectory, with_lidar: bool
) -> tuple[consumer.CuboidLabels | None, DynamicBoxes | None, SolidBoxes | None]:
    """Class names, label source and dynamic tracks of the annotations (all None without), the
    dynamic tracks' boxes in ``world`` for ``dynamic_flag``, and every track's as occluders for
    ``--lidar-rgb`` (None without lidars, or without colouring)."""
    annotations = inputs.annotations
    if annotations is None:
        return None, None, None
    observations = _observations(inputs, T_rig_world)
    cuboid_labels = consumer.cuboid_labels(
        observations,
        annotations.categories,
        classes.AV2_TO_NCORE,
        options.class_names,
        options.cuboid_label_source,
        "EXTERNAL",
        "world",
        str(inputs.log_dir / "annotations.feather"),
    )
    solids = None
    from_boxes = any(kind in contract.BOX_LABEL_KINDS for kind in options.camera_labels)
    if from_boxes or (with_lidar and (options.lidar_rgb or "depth" in options.camera_labels)):
        kinds = {
            str(track): kind_of(classes.AV2_TO_NCORE.get(category, ""))
            for track, category in zip(annotations.track_uuids, annotations.categories, strict=True)
        }
        solids = SolidBoxes.select(observations, cuboid_labels.static_poses, cuboid_labels.dynamic, kinds)
    if not with_lidar:
        return cuboid_labels, None, solids
    return cuboid_labels, DynamicBoxes.select(observations, cuboid_labels.dynamic), solids
