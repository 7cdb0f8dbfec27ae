"""OPV2V / V2XSet, per scenario: write a planned scenario (``plan.py``) through the NCore writer:
a sequence per agent (or one sequence with every agent, ``--layout scenario``) and ``scenario.json``,
written last.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from functools import partial

import numpy as np
from upath import UPath

from ncore_convert import contract
from ncore_convert.converters import consumer
from ncore_convert.converters.common import Counts, LidarStore
from ncore_convert.converters.opencood.labels import TickLabeller, camera_view, tick_boxes
from ncore_convert.converters.opencood.meta import generic_meta, manifest
from ncore_convert.converters.opencood.noise import instance_meta
from ncore_convert.converters.opencood.plan import plan_scenario
from ncore_convert.converters.opencood.records import VEHICLE_CLASS, AgentPlan, Names, OpenCoodOptions, ScenarioPlan
from ncore_convert.errors import SourceError, warnings_kept
from ncore_convert.run.pool import JobPool, Progress, run_inline
from ncore_convert.sources import opencood as src
from ncore_convert.sources.reader import Reader, with_reader
from ncore_convert.transforms import carla
from ncore_convert.transforms.camera.colours import ColourFrame, point_colours
from ncore_convert.transforms.geometry import euler_xyz_from_rotation, invert_se3
from ncore_convert.transforms.lidar.carla import assign_elements
from ncore_convert.transforms.lidar.frames import (
    LidarFrame,
    LidarGeometry,
    lidar_frame,
    point_data_notes,
)
from ncore_convert.transforms.lidar.rays import RayBundle
from ncore_convert.transforms.timebase import NS_PER_US
from ncore_convert.writer import Cuboids, SequenceWriter, write_scenario_manifest, write_sequence_meta

#: What world_global is in the dataset (``--world-global-mode localized``).
DATASET_GLOBAL = "the CARLA map frame made right-handed: (x, y, z)_world_global = (x, -y, z)_carla"


@dataclass
class ScenarioSummary(Counts):
    scenario: str = ""
    agents: list[str] = field(default_factory=list)
    tracks: int = 0
    seconds: float = 0.0
    validation: dict | None = None  #: set by validate.tree.convert_and_validate (None: not validated)

    def line(self) -> str:
        return (
            f"{self.scenario}: {len(self.agents)} agents ({', '.join(self.agents)}), {self.frames} lidar frames,"
            f" {self.points} points, {self.images} images, {self.cuboids} cuboids ({self.tracks} tracks),"
            + (f" {self.camera_labels} camera labels," if self.camera_labels else "")
            + f" {self.seconds:.1f} s"
            + (f", {len(self.warnings)} warning(s)" if self.warnings else "")
        )


def _cuboids(plan: ScenarioPlan, agent: AgentPlan, names: Names) -> Cuboids:
    """The merged labels at the agent's frames, in its rig frame at the frame time."""
    rows = []
    for key, t_us, T_rig_world_global in zip(agent.keys, agent.timestamps_us, agent.T_rig_world_global, strict=True):
        if (boxes := plan.boxes.get(key)) is not None:
            rows.append((boxes, int(t_us), invert_se3(T_rig_world_global) @ boxes.T_box_world_global))
    if not rows:
        empty = np.zeros((0, 3))
        return Cuboids([], [], np.zeros(0, np.int64), empty, empty, empty, reference_frame_id=names.rig)
    T_box_rig = np.concatenate([r[2] for r in rows])
    ids = np.concatenate([r[0].actor_ids for r in rows])
    return Cuboids(
        track_ids=[str(i) for i in ids],
        class_ids=[plan.cuboid_labels.class_map[VEHICLE_CLASS]] * len(ids),
        timestamps_us=np.concatenate([np.full(len(r[0].actor_ids), r[1]) for r in rows]),
        centroids_m=T_box_rig[:, :3, 3],
        dims_m=np.concatenate([r[0].dims_m for r in rows]),
        euler_xyz_rad=euler_xyz_from_rotation(T_box_rig[:, :3, :3]),
        reference_frame_id=names.rig,
    )


def _write_base(
    writer: SequenceWriter,
    plan: ScenarioPlan,
    agent: AgentPlan,
    names: Names,
    T_world_dataset_global: np.ndarray,
    world_global_edge: np.ndarray | None,
    interval_us: tuple[int, int],
) -> None:
    """The agent's trajectory (and ``world_global_edge``, world -> world_global, unless None), its
    perturbed trajectory and delays in each noise setting's poses instance, and its camera models
    and sensor extrinsics. ``T_world_dataset_global``: world -> the right-handed CARLA map frame;
    ``interval_us``: the sequence's inclusive interval (a trajectory that does not span it is an
    agent with fewer frames than the others)."""
    T_world_global_world = invert_se3(T_world_dataset_global)
    times_us, T_rig_world = agent.pose_samples(T_world_global_world @ agent.T_rig_world_global)
    covers = agent.pose_span_us == interval_us
    writer.store_trajectory(times_us, T_rig_world, world_global_edge, rig_frame=names.rig, covers_sequence=covers)
    for name, per_agent in plan.noise.items():
        noisy = per_agent[agent.agent_id]
        times_us, T_rig_world = agent.pose_samples(T_world_global_world @ noisy.T_rig_world_global)
        writer.store_trajectory(times_us, T_rig_world, None, rig_frame=names.rig, instance=name, covers_sequence=covers)
        writer.store_pose_data(name, noisy.arrays(agent.timestamps_us, names.prefix))
    for sensor in agent.lidar_ids + agent.camera_ids:
        writer.store_extrinsic(names.sensor(sensor), agent.T_sensor_rig[sensor], rig_frame=names.rig)
    for cam, spec in agent.cameras.items():
        writer.store_camera(names.sensor(cam), spec.pinhole, spec.model, spec.ftheta)
    if agent.lidar_model is not None:
        writer.store_lidar_model(names.sensor(src.LIDAR), agent.lidar_model)


#: Which pixel a point's ``rgb`` is (``transforms.lidar.frames.point_data_notes``).
COLOURS_TAKEN_FROM = (
    "pixel it projects to in the agent's own cameras at the same tick (occlusion by a depth buffer of the frame's"
    " points and by the tick's labelled vehicles)"
)


def _colour_frames(
    plan: ScenarioPlan, agent: AgentPlan, frame: int, key: str, t_us: int, reader: Reader
) -> list[ColourFrame]:
    """The agent's camera images of tick ``key`` (frame index ``frame``) as colour sources: every
    point and picture of a CARLA tick is taken at the tick, and so are the tick's labelled vehicles
    (the agent's own excepted), solid occluders. An unreadable image is left out (the camera stream
    reports it)."""
    _, T_box, half = tick_boxes(plan, agent, key)
    out = []
    for cam in agent.camera_ids:
        try:
            data = src.fetch_png(agent.agent_dir, key, agent.camera_index[cam], agent.files, reader)
        except SourceError:
            continue
        view = camera_view(agent, frame, t_us, cam, T_box, half)
        out.append(ColourFrame.of(view, lambda data=data: src.decode_png_rgb(data)))
    return out


def _source_points(xyz: np.ndarray, intensity: np.ndarray, rays: RayBundle) -> dict[str, np.ndarray]:
    """What the rays alone do not give back of a PCD (float32 points [N,3], right-handed, and their
    intensities [N]): the source points of the few inexact rays, and the points that are not rays
    (zero range, non-finite), each only when there are some."""
    out = {}
    if len(rays.inexact):
        out[contract.SOURCE_XYZ_INDEX] = rays.inexact.astype(np.uint32)
        out[contract.SOURCE_XYZ] = xyz[rays.source_index[rays.inexact]]
    if len(rays.source_index) < len(xyz):
        unstored = np.setdiff1d(np.arange(len(xyz)), rays.source_index)
        out[contract.UNSTORED_INDEX] = unstored.astype(np.uint32)
        out[contract.UNSTORED_XYZ] = xyz[unstored]
        out[contract.UNSTORED_INTENSITY] = intensity[unstored]
    return out


def _label_kinds(plan: ScenarioPlan, agent: AgentPlan) -> tuple[str, ...]:
    """The ``--camera-labels`` kinds written for ``agent``'s cameras: depth needs its lidar."""
    return tuple(kind for kind in plan.options.camera_labels if kind != "depth" or agent.lidar_ids)


def _pictured(agent: AgentPlan, key: str, reader: Reader) -> list[str]:
    """The agent's cameras whose picture of tick ``key`` is readable (those get a frame, and labels)."""
    out = []
    for cam in agent.camera_ids:
        try:
            src.fetch_png(agent.agent_dir, key, agent.camera_index[cam], agent.files, reader)
        except SourceError:
            continue
        out.append(cam)
    return out


def _write_sensors(
    writer: SequenceWriter,
    plan: ScenarioPlan,
    agent: AgentPlan,
    names: Names,
    counts: Counts,
    progress: Progress,
    reader: Reader,
    labeller: TickLabeller | None = None,
) -> None:
    """Stream the agent's lidar frames and images, one frame at a time; skip (and report) missing
    files; with ``labeller``, each camera frame's labels alongside, with the lidar frame of its tick
    (an agent without a lidar: box labels with the image)."""
    depth = labeller is not None and "depth" in labeller.kinds
    boxes = labeller is not None and bool(labeller.kinds & set(contract.BOX_LABEL_KINDS))
    if agent.lidar_ids:
        coloured = bool(plan.options.lidar_rgb and agent.camera_ids)  # its points get rgb
        meta = {
            "agent_id": agent.agent_id,
            "carla_lidar": plan.lidar_specs[agent.agent_id],
            **agent.lidar_model_meta,
            "point_timing": "CARLA ray-cast lidar: every point of a frame is measured at the frame's tick",
            "mounting": agent.mounts[src.LIDAR],
            **point_data_notes(
                plan.dynamic_boxes,
                "no labelled vehicles",
                plan.options.lidar_rgb,
                bool(agent.camera_ids),
                COLOURS_TAKEN_FROM,
            ),
        }
        T_lidar_rig = agent.T_sensor_rig[src.LIDAR]
        # CARLA's points are in the lidar's frame at the tick already: the source's exact float32 values
        model = agent.lidar_model
        geometry = LidarGeometry(
            exact=True,
            elements=None if model is None else lambda rays, rows: (assign_elements(model, rays.direction), {}),
            row_steps_rad=None if model is None else model.row_steps_rad(),
        )
        lidar = LidarStore(writer.add_lidar(names.sensor(src.LIDAR), meta), coloured)
        skipped = dict(agent.skipped_keys)
        paths = [
            p for key in agent.keys for p in (src.pcd_path(agent.agent_dir, key), src.yaml_path(agent.agent_dir, key))
        ]
        if boxes:  # a first pass: the vehicles' shapes from every tick
            labeller.gather_ticks(reader)
        fetched = reader.read_ahead(paths, agent.files, keep=True)  # each tick's PCD and YAML, in turn
        for frame, (key, t_us) in enumerate(zip(agent.keys, agent.timestamps_us, strict=True)):
            (_, pcd), (yaml_file, yaml) = next(fetched), next(fetched)
            try:
                for data in (pcd, yaml):
                    if isinstance(data, SourceError):
                        raise data
                sweep = src.read_points(agent.agent_dir, key, pcd)
                yaml_text = src.read_text(yaml_file, yaml)
            except SourceError as err:
                counts.warnings.append(f"{err}; lidar frame skipped")
                skipped[key] = err.cause
                if depth or boxes:  # the tick's pictures still get labels (depth: empty), saying why
                    pictured = _pictured(agent, key, reader)
                    if depth:
                        labeller.store_depth(frame, key, int(t_us), pictured, None, f"lidar frame: {err}")
                    for cam in pictured if boxes else ():
                        labeller.store_boxes(frame, key, int(t_us), cam, None, f"lidar frame: {err}")
                progress(1)
                continue
            xyz = carla.points_right_handed(sweep.xyz_m)  # float32: the mirror is exact
            lidar_frame_in = LidarFrame(
                xyz,
                np.full(len(xyz), int(t_us) * NS_PER_US, dtype=np.int64),  # every point at the tick
                sweep.intensity,
                int(t_us) * NS_PER_US,
                {src.LIDAR: np.arange(len(xyz))},
                agent.T_rig_world_global[frame] @ T_lidar_rig,
            )
            colouring = None
            if coloured:
                colouring = partial(point_colours, frames=_colour_frames(plan, agent, frame, key, int(t_us), reader))
            stored, points = lidar_frame(lidar_frame_in, {src.LIDAR: geometry}, plan.dynamic_boxes, colouring)
            if depth or boxes:
                pictured = _pictured(agent, key, reader)
                if depth:
                    labeller.store_depth(frame, key, int(t_us), pictured, points)
                for cam in pictured if boxes else ():
                    labeller.store_boxes(frame, key, int(t_us), cam, points)
            own = stored[src.LIDAR]
            rays = own.rays
            generic = {
                contract.DYNAMIC_FLAG: own.generic[contract.DYNAMIC_FLAG],
                **_source_points(xyz, sweep.intensity, rays),
            }
            if contract.LIDAR_RGB in own.generic:
                generic[contract.LIDAR_RGB] = own.generic[contract.LIDAR_RGB]
            lidar.store(
                own,
                {
                    contract.CARLA_FRAME: int(key),
                    contract.POINTS_NOT_STORED: rays.n_zero_range + rays.n_non_finite,
                    contract.OPENCOOD_YAML: yaml_text,
                    contract.PCD_LAYOUT: sweep.layout,
                },
                generic,
            )
            counts.frames += 1
            progress(1)
        lidar.finish(
            {**meta, contract.SKIPPED_FRAMES: skipped},
            counts,
            str(agent.agent_dir),
            "kept in their frames' generic data for the OpenCOOD read-back",
        )
    for cam in agent.camera_ids:
        index = agent.camera_index[cam]
        meta = {
            "agent_id": agent.agent_id,
            "opencood_camera": f"camera{index}",
            "mounting": agent.mounts[cam],
            "camera_model": agent.cameras[cam].meta(),
        }
        stream = writer.add_camera(names.sensor(cam), meta)
        skipped = {}
        paths = [src.camera_path(agent.agent_dir, key, index) for key in agent.keys]
        # kept when the lidar job (labels, colours) reads the pictures too
        fetched = reader.read_ahead(paths, agent.files, keep=bool(boxes or plan.options.lidar_rgb))
        for frame, (key, t_us, (_, image)) in enumerate(zip(agent.keys, agent.timestamps_us, fetched, strict=True)):
            try:
                if isinstance(image, SourceError):
                    raise image
                data = src.read_png(agent.agent_dir, key, index, image)
            except SourceError as err:
                skipped[key] = err.cause
                counts.warnings.append(f"{err}; image skipped")
            else:
                stream.store_frame(data, "png", (int(t_us), int(t_us)))
                counts.images += 1
                if boxes and not agent.lidar_ids:  # with a lidar, labelled with its frames
                    labeller.store_boxes(frame, key, int(t_us), cam, None, "the agent has no lidar")
            progress(1)
        stream.set_meta({**meta, contract.SKIPPED_FRAMES: {**agent.skipped_keys, **skipped}})


def _write(plan: ScenarioPlan, agent_ids: list[str], out_dir: UPath, sequence_id: str, progress: Progress) -> Counts:
    """One sequence holding ``agent_ids`` (one agent, or all of them prefixed), written by one writer
    (runs in a worker, reading with a reader of its own that shares the scenario's spool)."""
    counts = Counts()
    with warnings_kept(counts.warnings), Reader(plan.reading) as reader:
        _write_sequence(plan, agent_ids, out_dir, sequence_id, progress, counts, reader)
        if (line := reader.not_kept_warning()) is not None:
            counts.warnings.append(line)
        counts.reads = asdict(reader.counts)
    return counts


def _write_sequence(
    plan: ScenarioPlan,
    agent_ids: list[str],
    out_dir: UPath,
    sequence_id: str,
    progress: Progress,
    counts: Counts,
    reader: Reader,
) -> Counts:
    agents = [plan.agents[a] for a in agent_ids]
    prefixed = len(agent_ids) > 1 or plan.options.layout == "scenario"
    names = {a.agent_id: Names(contract.agent_prefix(a.agent_id) if prefixed else "") for a in agents}
    reference = plan.agents[plan.ego] if plan.ego in agent_ids else agents[0]
    T_world_dataset_global = reference.T_rig_world_global[0]  # world is the reference rig's first pose
    world_global_edge, world_global_meta = consumer.world_global(
        T_world_dataset_global, plan.options.world_global_mode, DATASET_GLOBAL
    )
    interval_us = (min(a.pose_span_us[0] for a in agents), max(a.pose_span_us[1] for a in agents))
    label_kinds = {a.agent_id: _label_kinds(plan, a) for a in agents}
    label_ids = [
        contract.camera_label_id(kind, names[a.agent_id].sensor(cam))
        for a in agents
        for cam in a.camera_ids
        for kind in label_kinds[a.agent_id]
    ]
    writer = SequenceWriter(
        output_dir=out_dir,
        sequence_id=sequence_id,
        interval_us=interval_us,
        generic_meta_data=generic_meta(plan, agent_ids, names, world_global_meta),
        camera_ids=[names[a.agent_id].sensor(c) for a in agents for c in a.camera_ids],
        lidar_ids=[names[a.agent_id].sensor(s) for a in agents for s in a.lidar_ids],
        store_type=plan.options.store_type,
        profile=plan.options.profile,
        poses_meta={"calibration_type": "carla-sensor-transforms", "egomotion_type": "carla-ground-truth-lidar_pose"},
        extra_pose_instances={s.name: instance_meta(s, plan.agent_folders) for s in plan.options.noise},
        label_ids=label_ids,
    )
    for i, agent in enumerate(agents):
        edge = world_global_edge if i == 0 else None  # one static edge per sequence
        _write_base(writer, plan, agent, names[agent.agent_id], T_world_dataset_global, edge, interval_us)
    cuboids = _cuboids(plan, reference, names[reference.agent_id])
    writer.store_cuboids(cuboids, plan.cuboid_labels.label_source, plan.cuboid_labels.meta)
    counts.cuboids = len(cuboids)
    for agent in agents:
        name = names[agent.agent_id]
        labeller = None
        if label_kinds[agent.agent_id] and agent.camera_ids:
            labeller = TickLabeller(plan, agent, label_kinds[agent.agent_id], writer, name.sensor)
        _write_sensors(writer, plan, agent, name, counts, progress, reader, labeller)
        if labeller is not None:
            labeller.finish()
            counts.camera_labels += labeller.labels
            counts.label_seconds += labeller.seconds
    meta = writer.finalize(with_meta=plan.options.sequence_meta)
    if meta is not None:
        write_sequence_meta(out_dir, sequence_id, [meta])
    return counts


def write_agent(plan: ScenarioPlan, agent_id: str, scenario_out: UPath, progress: Progress) -> Counts:
    """Job: the agent's own sequence in ``<scenario_out>/<agent_id>/`` (runs in a worker)."""
    return _write(plan, [agent_id], scenario_out / agent_id, plan.sequence_id(agent_id), progress)


def write_scenario_sequence(plan: ScenarioPlan, scenario_out: UPath, progress: Progress) -> Counts:
    """Job: one sequence with every agent (``--layout scenario``) in ``scenario_out``."""
    return _write(plan, list(plan.agents), scenario_out, plan.scenario, progress)


def convert_scenario(
    root_dir: UPath,
    output_dir: UPath,
    scenario: str,
    options: OpenCoodOptions,
    pool: JobPool | None = None,
    progress: Progress | None = None,
    reader: Reader | None = None,
) -> ScenarioSummary:
    """Convert one scenario into ``output_dir``: a sequence per agent in ``<agent_id>/`` (or one
    sequence, ``--layout scenario``) and ``scenario.json``, written last.

    Args:
        pool: worker processes for the agents' sequences; None writes them in this process.
        progress: told the number of frames (lidar frames + images) to write, then each written frame.
        reader: the scenario's reader (its owner closes it: the run's task); None: one for this call.
    """
    return with_reader(_convert_scenario, root_dir, output_dir, scenario, options, pool, progress, reader=reader)


def _convert_scenario(
    root_dir: UPath,
    output_dir: UPath,
    scenario: str,
    options: OpenCoodOptions,
    pool: JobPool | None,
    progress: Progress | None,
    *,
    reader: Reader,
) -> ScenarioSummary:
    started = time.perf_counter()
    progress = progress or Progress()
    plan = plan_scenario(root_dir, scenario, options, reader)
    progress.total(sum(a.n_frames for a in plan.agents.values()))
    output_dir.mkdir(parents=True, exist_ok=True)
    if options.layout == "scenario":
        calls = [(write_scenario_sequence, (plan, output_dir))]
    else:
        longest_first = sorted(plan.agents, key=lambda a: -plan.agents[a].n_frames)
        calls = [(write_agent, (plan, a, output_dir)) for a in longest_first]
    with warnings_kept(plan.warnings):
        results = pool.run(calls, progress) if pool else run_inline(calls, progress)
    write_scenario_manifest(output_dir, manifest(plan))
    summary = ScenarioSummary(scenario=scenario, agents=list(plan.agents), warnings=list(plan.warnings))
    for result in results:
        summary.add(result)
    summary.tracks = len({int(i) for b in plan.boxes.values() for i in b.actor_ids})
    summary.seconds = time.perf_counter() - started
    return summary
