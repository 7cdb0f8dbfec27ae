"""OPV2V / V2XSet -> NCore V4 for one scenario: source readers -> CARLA transforms -> writer.

Frames (README, "OPV2V and V2XSet"):
- ``world_global``: the CARLA map frame made right-handed (y mirrored); shared by every agent of
  the scenario, so the agents' sequences co-register.
- ``rig``: the agent's vehicle frame (``true_ego_pos``) made right-handed, placed so that the lidar
  lands exactly on ``lidar_pose`` (the pose OpenCOOD registers point clouds with). For
  infrastructure, ``true_ego_pos`` is the lidar position with zero rotation.
- ``world``: a sequence's first rig pose (``--layout scenario``: the OpenCOOD ego's first pose).
- Time: a frame key is the CARLA frame counter; ``t_us = key * fixed_delta_seconds * 1e6``.
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import asdict, dataclass, field
from typing import Literal

import numpy as np
import PIL.Image
from upath import UPath

from ncore_convert import __version__, carla
from ncore_convert.converters.common import Tally, select_sensors
from ncore_convert.converters.opencood_noise import AgentNoise, instance_meta, opencood_loaded, plan_noise
from ncore_convert.geometry import euler_xyz_from_rotation, invert_se3, rigid_mean
from ncore_convert.lidar import ray_bundle
from ncore_convert.noise_config import NoiseSetting
from ncore_convert.pool import JobPool, Progress, run_inline
from ncore_convert.sources import opencood as src
from ncore_convert.sources.files import PNG_SIGNATURE, SourceError, require_folder
from ncore_convert.storage import flush_to_disk
from ncore_convert.writer import Cuboids, Profile, SequenceWriter, StoreType, write_sequence_meta

Layout = Literal["agents", "scenario"]
#: sensor metadata: frame key -> why the source frame was not written (unreadable YAML, PCD or image)
SKIPPED_FRAMES = "skipped_frames"
MANIFEST = "scenario.json"
VEHICLE_CLASS = "vehicle"
#: A sensor's mounting, re-measured every frame, may move this much before it is reported.
MOUNT_TOLERANCE = (0.02, 0.2)  # metres, degrees
#: Two agents' labels of one actor at one tick further apart than this are reported.
LABEL_TOLERANCE_M = 0.05


@dataclass(frozen=True)
class OpenCoodOptions:
    """Options of the ``opv2v-v4`` and ``v2xset-v4`` commands (sensor selection: None = all)."""

    dataset: Literal["opv2v", "v2xset"]
    split: str
    layout: Layout = "agents"
    store_type: StoreType = "itar"
    profile: Profile = "separate-sensors"
    sequence_meta: bool = True
    camera_ids: tuple[str, ...] | None = None
    lidar_ids: tuple[str, ...] | None = None
    noise: tuple[NoiseSetting, ...] = ()  #: GPS-error / delay settings, each a further poses instance

    def scenario_dir(self, root_dir: UPath, scenario: str) -> UPath:
        return root_dir / self.split / scenario


@dataclass(frozen=True)
class AgentPlan:
    """One agent's frames and calibration, read and decided once.

    Attributes:
        keys: frame keys with a readable YAML; timestamps_us: their times, int64 [N].
        lidar_pose_carla: the YAMLs' ``lidar_pose`` [N,6] (CARLA: x, y, z m; roll, yaw, pitch deg).
        world_global_SE3_rig: right-handed rig poses [N,4,4], float64.
        T_sensor_rig: sensor -> rig [4,4] (lidar frame right-handed; cameras in OpenCV axes).
        intrinsics: camera id -> (K [3,3], (width, height)); camera_index: camera id -> file index.
        mounts: how much each re-measured mounting moved (metadata).
    """

    agent_id: str
    agent_dir: UPath
    keys: list[str]
    timestamps_us: np.ndarray
    lidar_pose_carla: np.ndarray
    world_global_SE3_rig: np.ndarray
    T_sensor_rig: dict[str, np.ndarray]
    intrinsics: dict[str, tuple[np.ndarray, tuple[int, int]]]
    camera_index: dict[str, int]
    lidar_ids: list[str]
    mounts: dict[str, dict]
    skipped_keys: dict[str, str] = field(default_factory=dict)  #: frame key -> why its YAML was unreadable

    @property
    def kind(self) -> str:
        return src.agent_kind(self.agent_id)

    @property
    def camera_ids(self) -> list[str]:
        return list(self.intrinsics)

    @property
    def n_frames(self) -> int:
        return len(self.keys) * (len(self.lidar_ids) + len(self.camera_ids))


@dataclass(frozen=True)
class Boxes:
    """Merged vehicle labels of one tick: actor ids [M], right-handed world_global_SE3_box [M,4,4]
    and (length, width, height) [M,3]."""

    actor_ids: np.ndarray
    world_global_SE3_box: np.ndarray
    dims_m: np.ndarray


@dataclass(frozen=True)
class ScenarioPlan:
    scenario: str
    options: OpenCoodOptions
    fixed_delta_seconds: float
    ego: str
    ego_keys: list[str]  #: the OpenCOOD ego's YAML keys: OpenCOOD's frame index
    agent_folders: list[str]
    agents: dict[str, AgentPlan]
    boxes: dict[str, Boxes]  #: frame key -> merged labels
    lidar_spec: dict
    warnings: list[str]
    noise: dict[str, dict[str, AgentNoise]]  #: setting name -> agent id -> perturbations

    def sequence_id(self, agent_id: str) -> str:
        return f"{self.scenario}_agent{agent_id}"


@dataclass
class Counts(Tally):
    frames: int = 0  #: lidar frames
    points: int = 0
    points_not_stored: int = 0
    images: int = 0
    cuboids: int = 0
    warnings: list[str] = field(default_factory=list)


@dataclass
class ScenarioSummary(Counts):
    scenario: str = ""
    agents: list[str] = field(default_factory=list)
    tracks: int = 0
    seconds: float = 0.0
    validation: dict | None = None  #: set by validate.convert_and_validate (None: not validated)

    def line(self) -> str:
        return (
            f"{self.scenario}: {len(self.agents)} agents ({', '.join(self.agents)}), {self.frames} lidar frames,"
            f" {self.points} points, {self.images} images, {self.cuboids} cuboids ({self.tracks} tracks),"
            f" {self.seconds:.1f} s" + (f", {len(self.warnings)} warning(s)" if self.warnings else "")
        )


def _keys_text(keys: list[str]) -> str:
    return ", ".join(keys[:5]) + (f" and {len(keys) - 5} more" if len(keys) > 5 else "")


def timestamps_us(keys: list[str], fixed_delta_seconds: float) -> np.ndarray:
    """Frame keys (CARLA frame counters) -> µs since the simulation's frame 0, int64 [N]."""
    return np.round(np.array([int(k) for k in keys], dtype=np.float64) * fixed_delta_seconds * 1e6).astype(np.int64)


def _read_frames(
    agent_dir: UPath, keys: list[str], warnings: list[str], skipped: dict[str, str]
) -> list[src.AgentFrame]:
    """The readable frames; an unreadable YAML is a warning and ``skipped[key]`` (its cause)."""
    frames = []
    for key in keys:
        try:
            frames.append(src.read_agent_frame(agent_dir, key))
        except SourceError as err:
            warnings.append(f"{err}; frame skipped")
            skipped[key] = err.cause
    return frames


def _image_size(path: UPath) -> tuple[int, int] | None:
    """(width, height) of a PNG from its header, or None if it is missing or not a PNG."""
    try:
        with path.open("rb") as f:
            head = f.read(64)
        if not head.startswith(PNG_SIGNATURE):
            return None
        return PIL.Image.open(io.BytesIO(head)).size
    except (OSError, PIL.UnidentifiedImageError):
        return None


def _mount(name: str, samples: np.ndarray, mounts: dict, warnings: list[str], where: UPath) -> np.ndarray:
    T, moved_m, moved_deg = rigid_mean(samples)
    mounts[name] = {
        "frames": len(samples),
        "max_deviation_m": round(moved_m, 6),
        "max_deviation_deg": round(moved_deg, 6),
    }
    if moved_m > MOUNT_TOLERANCE[0] or moved_deg > MOUNT_TOLERANCE[1]:
        warnings.append(
            f"{where}: the {name} mounting moves by up to {moved_m:.3f} m / {moved_deg:.2f} deg between frames;"
            " its mean is stored"
        )
    return T


def plan_agent(
    agent_dir: UPath,
    frames: list[src.AgentFrame],
    options: OpenCoodOptions,
    dt: float,
    warnings: list[str],
    skipped_keys: dict[str, str] | None = None,
) -> AgentPlan:
    """Trajectory and calibration of one agent from its frames (at least two); ``skipped_keys``:
    the keys whose YAML could not be read, with the cause."""
    keys = [f.path.stem for f in frames]
    lidar_pose_carla = np.array([f.lidar_pose for f in frames], dtype=np.float64)
    world_global_SE3_lidar = carla.world_SE3_right_handed(lidar_pose_carla)
    world_global_SE3_vehicle = carla.world_SE3_right_handed(np.array([f.true_ego_pos for f in frames]))
    mounts: dict[str, dict] = {}
    T_lidar_rig = _mount(
        src.LIDAR, invert_se3(world_global_SE3_vehicle) @ world_global_SE3_lidar, mounts, warnings, agent_dir
    )
    world_global_SE3_rig = world_global_SE3_lidar @ invert_se3(T_lidar_rig)
    lidar_ids = select_sensors(options.lidar_ids, (src.LIDAR,), "lidar")
    T_sensor_rig = {src.LIDAR: T_lidar_rig}
    intrinsics, camera_index = {}, {}
    for cam in select_sensors(options.camera_ids, src.CAMERAS, "camera"):
        index = src.CAMERAS.index(cam)
        with_cam = [i for i, f in enumerate(frames) if index in f.camera_cords]
        size = next((s for i in with_cam if (s := _image_size(src.camera_path(agent_dir, keys[i], index)))), None)
        if not with_cam or size is None:
            warnings.append(f"{agent_dir}: no {'calibration' if not with_cam else 'readable image'} for camera{index}"
                            f" ({cam}); camera not written")  # fmt: skip
            continue
        world_global_SE3_cam = carla.world_SE3_camera_opencv(
            np.array([frames[i].camera_cords[index] for i in with_cam])
        )
        T_sensor_rig[cam] = _mount(
            cam, invert_se3(world_global_SE3_rig[with_cam]) @ world_global_SE3_cam, mounts, warnings, agent_dir
        )
        K = frames[with_cam[0]].camera_intrinsic[index]
        if any(not np.allclose(frames[i].camera_intrinsic[index], K, atol=1e-3) for i in with_cam):
            warnings.append(f"{agent_dir}: camera{index} intrinsics change between frames; the first is stored")
        intrinsics[cam], camera_index[cam] = (K, size), index
    return AgentPlan(
        agent_id=agent_dir.name,
        agent_dir=agent_dir,
        keys=keys,
        timestamps_us=timestamps_us(keys, dt),
        lidar_pose_carla=lidar_pose_carla,
        world_global_SE3_rig=world_global_SE3_rig,
        T_sensor_rig=T_sensor_rig,
        intrinsics=intrinsics,
        camera_index=camera_index,
        lidar_ids=lidar_ids,
        mounts=mounts,
        skipped_keys=dict(skipped_keys or {}),
    )


def merge_boxes(frames: dict[str, list[src.AgentFrame]], warnings: list[str]) -> dict[str, Boxes]:
    """Per frame key: the union of every agent's labelled vehicles by actor id (first agent in id
    order wins; disagreements are reported), plus each CAV's own box, which its YAML lacks (from
    ``true_ego_pos`` and the logreplay CAV model, unless another agent labelled it)."""
    merged: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {}
    disagreements: dict[str, int] = {}
    for agent_id in sorted(frames, key=int):
        for frame in frames[agent_id]:
            v = frame.vehicles
            key = frame.path.stem
            if len(v):
                poses, dims = carla.boxes_world_right_handed(v.location, v.angle, v.center, v.extent)
                tick = merged.setdefault(key, {})
                for actor, pose, dim in zip(v.actor_ids.tolist(), poses, dims, strict=True):
                    if actor not in tick:
                        tick[actor] = (pose, dim)
                    elif np.linalg.norm(tick[actor][0][:3, 3] - pose[:3, 3]) > LABEL_TOLERANCE_M:
                        disagreements[key] = disagreements.get(key, 0) + 1
    for agent_id in frames:
        if src.is_infrastructure(agent_id):
            continue
        for frame in frames[agent_id]:
            tick = merged.setdefault(frame.path.stem, {})
            if int(agent_id) not in tick:
                pose, dims = carla.boxes_world_right_handed(
                    frame.true_ego_pos[None, :3], frame.true_ego_pos[None, 3:],
                    np.array([src.CAV_BOX_CENTER_M]), np.array([src.CAV_BOX_EXTENT_M]),
                )  # fmt: skip
                tick[int(agent_id)] = (pose[0], dims[0])
    if disagreements:
        warnings.append(
            f"agents label the same actor more than {LABEL_TOLERANCE_M} m apart at key(s)"
            f" {_keys_text(sorted(disagreements, key=int))}; the lowest agent id's label is kept"
        )
    out = {}
    for key, tick in merged.items():
        ids = np.array(sorted(tick), dtype=np.int64)
        out[key] = Boxes(ids, np.array([tick[i][0] for i in ids]), np.array([tick[i][1] for i in ids]))
    return out


def plan_scenario(root_dir: UPath, scenario: str, options: OpenCoodOptions) -> ScenarioPlan:
    """Read a scenario's YAMLs once; decide every agent's trajectory, calibration and the labels."""
    scenario_dir = options.scenario_dir(root_dir, scenario)
    require_folder(scenario_dir, "scenario folder")
    protocol = src.read_protocol(scenario_dir)
    dt = protocol.fixed_delta_seconds
    folders = src.list_agents(scenario_dir)
    keys = {a: src.list_frame_keys(scenario_dir / a) for a in folders}
    all_keys = sorted(set().union(*keys.values()), key=int)
    if not all_keys:
        raise SourceError(scenario_dir, "no frame YAMLs (<key>.yaml) in any agent folder")
    warnings: list[str] = []
    steps = np.diff([int(k) for k in all_keys])
    if len(steps) and np.any(steps != np.median(steps)):
        warnings.append(f"{scenario_dir}: frame keys do not step uniformly (steps {sorted(set(steps.tolist()))})")
    frames, skipped_keys = {}, {}
    for agent in folders:
        missing = sorted(set(all_keys) - set(keys[agent]), key=int)
        if missing:
            warnings.append(
                f"{scenario_dir / agent}: no frame for key(s) {_keys_text(missing)} that other agents have;"
                " skipped for this agent"
            )
        skipped_keys[agent] = {}
        agent_frames = _read_frames(scenario_dir / agent, keys[agent], warnings, skipped_keys[agent])
        if len(agent_frames) < 2:
            warnings.append(f"{scenario_dir / agent}: fewer than 2 readable frames; agent not written")
            continue
        frames[agent] = agent_frames
    if not frames:
        raise SourceError(scenario_dir, "no agent has 2 or more readable frames")
    agents = {a: plan_agent(scenario_dir / a, f, options, dt, warnings, skipped_keys[a]) for a, f in frames.items()}
    ego = src.opencood_ego(folders)
    ego_times_us = timestamps_us(keys[ego], dt)
    noise = {s.name: plan_noise(s, scenario, agents, folders, keys[ego], ego_times_us) for s in options.noise}
    for setting in options.noise:
        loaded = opencood_loaded(setting, folders)
        for agent_id, agent_noise in noise[setting.name].items():
            unsent = int(np.sum(agent_noise.source_keys < 0))
            if agent_id not in loaded:
                warnings.append(
                    f"{scenario_dir / agent_id}: noise setting {setting.name}: past max_cav ({setting.max_cav}),"
                    " so OpenCOOD does not load this agent; no delay data"
                )
            elif unsent and agent_id != ego:
                warnings.append(
                    f"{scenario_dir / agent_id}: noise setting {setting.name}: no frame of this agent to send at"
                    f" {unsent} ego frame(s) (delay_source_keys = -1)"
                )
    return ScenarioPlan(
        scenario=scenario,
        options=options,
        fixed_delta_seconds=dt,
        ego=ego,
        ego_keys=keys[ego],
        agent_folders=folders,
        agents=agents,
        boxes=merge_boxes(frames, warnings),
        lidar_spec=protocol.cav_lidar,
        warnings=warnings,
        noise=noise,
    )


@dataclass(frozen=True)
class Names:
    """Frame and sensor names of one agent in a sequence (prefixed in the scenario layout)."""

    prefix: str = ""

    @property
    def rig(self) -> str:
        return f"{self.prefix}rig"

    def sensor(self, sensor_id: str) -> str:
        return f"{self.prefix}{sensor_id}"


def _generic_meta(plan: ScenarioPlan, agent_ids: list[str]) -> dict:
    return {
        "source_dataset": plan.options.dataset,
        "opencood_split": plan.options.split,
        "scenario": plan.scenario,
        "agents": {a: {"kind": plan.agents[a].kind, "opencood_ego": a == plan.ego} for a in agent_ids},
        "carla_fixed_delta_seconds": plan.fixed_delta_seconds,
        "time_base": "t_us = CARLA frame key * fixed_delta_seconds * 1e6 (frame keys are CARLA frame counters)",
        "world_global": "the CARLA map frame made right-handed: (x, y, z)_world_global = (x, -y, z)_carla",
        "noise_settings": {s.name: s.as_dict() for s in plan.options.noise},
        "converter": {"name": "ncore-convert", "version": __version__, "options": _options_meta(plan.options)},
    }


def _options_meta(options: OpenCoodOptions) -> dict:
    """The conversion options as metadata (the noise settings are listed on their own)."""
    out = asdict(options)
    out["noise"] = [s.name for s in options.noise]
    return out


def _cuboids(plan: ScenarioPlan, agent: AgentPlan, names: Names) -> Cuboids:
    """The merged labels at the agent's frames, in its rig frame at the frame time."""
    rows = []
    for key, t_us, world_global_SE3_rig in zip(
        agent.keys, agent.timestamps_us, agent.world_global_SE3_rig, strict=True
    ):
        if (boxes := plan.boxes.get(key)) is not None:
            rows.append((boxes, int(t_us), invert_se3(world_global_SE3_rig) @ boxes.world_global_SE3_box))
    if not rows:
        return Cuboids([], [], np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), names.rig)
    rig_SE3_box = np.concatenate([r[2] for r in rows])
    ids = np.concatenate([r[0].actor_ids for r in rows])
    return Cuboids(
        track_ids=[str(i) for i in ids],
        class_ids=[VEHICLE_CLASS] * len(ids),
        timestamps_us=np.concatenate([np.full(len(r[0].actor_ids), r[1]) for r in rows]),
        centroids_m=rig_SE3_box[:, :3, 3],
        dims_m=np.concatenate([r[0].dims_m for r in rows]),
        euler_xyz_rad=euler_xyz_from_rotation(rig_SE3_box[:, :3, :3]),
        reference_frame_id=names.rig,
    )


def _write_base(
    writer: SequenceWriter,
    plan: ScenarioPlan,
    agent: AgentPlan,
    names: Names,
    world_global_SE3_world: np.ndarray,
    first: bool,
) -> None:
    """The agent's trajectory (and, for the first agent of a sequence, world -> world_global), its
    perturbed trajectory and delays in each noise setting's poses instance, and its camera models
    and sensor extrinsics."""
    world_SE3_world_global = invert_se3(world_global_SE3_world)
    T_rig_world = world_SE3_world_global @ agent.world_global_SE3_rig
    writer.store_trajectory(agent.timestamps_us, T_rig_world, world_global_SE3_world if first else None, names.rig)
    for name, per_agent in plan.noise.items():
        noisy = per_agent[agent.agent_id]
        T_rig_world = world_SE3_world_global @ noisy.world_global_SE3_rig
        writer.store_trajectory(agent.timestamps_us, T_rig_world, None, names.rig, instance=name)
        writer.store_pose_data(name, noisy.arrays(agent, names.prefix))
    for sensor in agent.lidar_ids + agent.camera_ids:
        writer.store_extrinsic(names.sensor(sensor), agent.T_sensor_rig[sensor], names.rig)
    for cam, (K, size) in agent.intrinsics.items():
        # CARLA's K puts the principal point at the image centre (W/2, H/2): the pixel-corner convention
        writer.store_pinhole_camera(names.sensor(cam), (K[0, 0], K[1, 1]), (K[0, 2], K[1, 2]), size)


def _write_sensors(
    writer: SequenceWriter, plan: ScenarioPlan, agent: AgentPlan, names: Names, counts: Counts, progress: Progress
) -> None:
    """Stream the agent's lidar frames and images, one frame at a time; skip (and report) missing files."""
    if agent.lidar_ids:
        meta = {"agent_id": agent.agent_id, "carla_lidar": plan.lidar_spec,
                "point_timing": "CARLA ray-cast lidar: every point of a frame is measured at the frame's tick",
                "mounting": agent.mounts[src.LIDAR]}  # fmt: skip
        lidar = writer.add_lidar(names.sensor(src.LIDAR), meta)
        not_stored = 0
        skipped = dict(agent.skipped_keys)
        for key, t_us in zip(agent.keys, agent.timestamps_us, strict=True):
            try:
                xyz_carla, intensity_u8 = src.read_points(agent.agent_dir, key)
            except SourceError as err:
                counts.warnings.append(f"{err}; lidar frame skipped")
                skipped[key] = err.cause
                progress(1)
                continue
            xyz = carla.points_right_handed(xyz_carla.astype(np.float64))
            rays = ray_bundle(xyz, np.full(len(xyz), int(t_us) * 1000, dtype=np.int64), intensity_u8, int(t_us))
            lidar.store_frame(
                rays, {"carla_frame": int(key), "points_not_stored": rays.n_zero_range + rays.n_non_finite}
            )
            counts.frames += 1
            counts.points += len(rays)
            not_stored += rays.n_zero_range + rays.n_non_finite
            progress(1)
        lidar.set_meta({**meta, SKIPPED_FRAMES: skipped})
        counts.points_not_stored += not_stored
        if not_stored:
            counts.warnings.append(
                f"{agent.agent_dir}: {not_stored} lidar points at zero range or with non-finite coordinates not stored"
            )
    for cam in agent.camera_ids:
        index = agent.camera_index[cam]
        meta = {"agent_id": agent.agent_id, "opencood_camera": f"camera{index}", "mounting": agent.mounts[cam]}
        stream = writer.add_camera(names.sensor(cam), meta)
        skipped = {}
        for key, t_us in zip(agent.keys, agent.timestamps_us, strict=True):
            try:
                data = src.read_png(agent.agent_dir, key, index)
            except SourceError as err:
                skipped[key] = err.cause
                counts.warnings.append(f"{err}; image skipped")
            else:
                stream.store_frame(data, "png", (int(t_us), int(t_us)))
                counts.images += 1
            progress(1)
        stream.set_meta({**meta, SKIPPED_FRAMES: {**agent.skipped_keys, **skipped}})


def _write(plan: ScenarioPlan, agent_ids: list[str], out_dir: UPath, sequence_id: str, progress: Progress) -> Counts:
    """One sequence holding ``agent_ids`` (one agent, or all of them prefixed), written by one writer."""
    counts = Counts()
    agents = [plan.agents[a] for a in agent_ids]
    prefixed = len(agent_ids) > 1 or plan.options.layout == "scenario"
    names = {a.agent_id: Names(f"agent{a.agent_id}_" if prefixed else "") for a in agents}
    reference = plan.agents[plan.ego] if plan.ego in agent_ids else agents[0]
    writer = SequenceWriter(
        output_dir=out_dir,
        sequence_id=sequence_id,
        interval_us=(min(int(a.timestamps_us[0]) for a in agents), max(int(a.timestamps_us[-1]) for a in agents)),
        generic_meta_data=_generic_meta(plan, agent_ids),
        camera_ids=[names[a.agent_id].sensor(c) for a in agents for c in a.camera_ids],
        lidar_ids=[names[a.agent_id].sensor(s) for a in agents for s in a.lidar_ids],
        store_type=plan.options.store_type,
        profile=plan.options.profile,
        poses_meta={"calibration_type": "carla-sensor-transforms", "egomotion_type": "carla-ground-truth-lidar_pose"},
        extra_pose_instances={s.name: instance_meta(s, plan.agent_folders) for s in plan.options.noise},
    )
    world_global_SE3_world = reference.world_global_SE3_rig[0]
    for i, agent in enumerate(agents):
        _write_base(writer, plan, agent, names[agent.agent_id], world_global_SE3_world, first=i == 0)
    cuboids = _cuboids(plan, reference, names[reference.agent_id])
    writer.store_cuboids(cuboids, source="GT_SYNTHETIC")
    counts.cuboids = len(cuboids)
    for agent in agents:
        _write_sensors(writer, plan, agent, names[agent.agent_id], counts, progress)
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


def manifest(plan: ScenarioPlan) -> dict:
    """``scenario.json``: how the scenario's agents and sequences relate."""
    agents = []
    for agent_id in plan.agent_folders:
        agent = plan.agents.get(agent_id)
        entry = {"agent_id": int(agent_id), "kind": src.agent_kind(agent_id),
                 "opencood_ego": agent_id == plan.ego, "written": agent is not None}  # fmt: skip
        if agent is not None:
            entry["frames"] = len(agent.keys)
            entry["sensors"] = agent.lidar_ids + agent.camera_ids
            if plan.options.layout == "agents":
                entry["sequence"] = f"{agent_id}/{plan.sequence_id(agent_id)}.json"
            else:
                entry["frame_prefix"] = f"agent{agent_id}_"
        agents.append(entry)
    return {
        "scenario": plan.scenario,
        "dataset": plan.options.dataset,
        "split": plan.options.split,
        "layout": plan.options.layout,
        "sequence": f"{plan.scenario}.json" if plan.options.layout == "scenario" else None,
        "world_global": "CARLA map frame, right-handed: (x, y, z)_world_global = (x, -y, z)_carla (all agents)",
        "fixed_delta_seconds": plan.fixed_delta_seconds,
        "time_base": "t_us = CARLA frame key * fixed_delta_seconds * 1e6",
        "ego": {"agent_id": int(plan.ego), "rule": "OpenCOOD: first agent folder by string sort, infrastructure last"},
        "agents": agents,
        "noise_settings": [
            {"name": s.name, "model": s.model, "seed": s.seed, "poses_instance": s.name} for s in plan.options.noise
        ],
        "labels": "union of every agent's vehicle labels per tick (each agent labels vehicles it hit with >= 1"
        " semantic-lidar ray within 120 m) plus the CAVs' own boxes; not complete scene ground truth",
    }


def convert_scenario(
    root_dir: UPath,
    output_dir: UPath,
    scenario: str,
    options: OpenCoodOptions,
    pool: JobPool | None = None,
    progress: Progress | None = None,
) -> ScenarioSummary:
    """Convert one scenario into ``output_dir``: a sequence per agent in ``<agent_id>/`` (or one
    sequence, ``--layout scenario``) and ``scenario.json``, written last.

    Args:
        pool: worker processes for the agents' sequences; None writes them in this process.
        progress: told the number of frames (lidar frames + images) to write, then each written frame.
    """
    started = time.perf_counter()
    progress = progress or Progress()
    plan = plan_scenario(root_dir, scenario, options)
    progress.total(sum(a.n_frames for a in plan.agents.values()))
    output_dir.mkdir(parents=True, exist_ok=True)
    if options.layout == "scenario":
        calls = [(write_scenario_sequence, (plan, output_dir))]
    else:
        longest_first = sorted(plan.agents, key=lambda a: -plan.agents[a].n_frames)
        calls = [(write_agent, (plan, a, output_dir)) for a in longest_first]
    results = pool.run(calls, progress) if pool else run_inline(calls, progress)
    (output_dir / MANIFEST).write_text(json.dumps(manifest(plan), indent=2))
    flush_to_disk(output_dir / MANIFEST)
    summary = ScenarioSummary(scenario=scenario, agents=list(plan.agents), warnings=list(plan.warnings))
    for result in results:
        summary.add(result)
    summary.tracks = len({int(i) for b in plan.boxes.values() for i in b.actor_ids})
    summary.seconds = time.perf_counter() - started
    return summary
