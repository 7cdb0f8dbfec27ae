"""OPV2V / V2XSet, per scenario: read every agent's YAMLs once and decide each agent's trajectory,
calibration and frames, the merged labels, and the noise settings' perturbations.

Frames (docs/opv2v-v2xset.md):
- ``world_global``: the CARLA map frame made right-handed (y mirrored); shared by every agent of
  the scenario, so the agents' sequences co-register.
- ``rig``: the agent's vehicle frame (``true_ego_pos``) made right-handed, placed so that the lidar
  lands exactly on ``lidar_pose`` (the pose OpenCOOD registers point clouds with). For
  infrastructure, ``true_ego_pos`` is the lidar position with zero rotation.
- ``world``: a sequence's first rig pose (``--layout scenario``: the OpenCOOD ego's first pose).
- Time: a frame key is the CARLA frame counter; ``t_us = key * fixed_delta_seconds * 1e6``.
"""

from __future__ import annotations

from dataclasses import replace
from functools import partial

import numpy as np
from upath import UPath

from ncore_convert.converters import consumer
from ncore_convert.converters.common import select_sensors
from ncore_convert.converters.opencood.lidar_model import with_lidar_model
from ncore_convert.converters.opencood.noise import AgentNoise, opencood_loaded, plan_noise
from ncore_convert.converters.opencood.records import VEHICLE_CLASS, AgentPlan, Boxes, OpenCoodOptions, ScenarioPlan
from ncore_convert.errors import SourceError, UsageError, warnings_kept
from ncore_convert.sources import opencood as src
from ncore_convert.sources.reader import Reader, reading
from ncore_convert.sources.store import key as object_key
from ncore_convert.transforms import carla
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.geometry import invert_se3, rigid_mean
from ncore_convert.transforms.objects import classes
from ncore_convert.transforms.objects.dynamic import DynamicBoxes, TrackObservations
from ncore_convert.transforms.timebase import WindowError, in_window

#: A sensor's mounting, re-measured every frame, may move this much before it is reported.
MOUNT_TOLERANCE = (0.02, 0.2)  # metres, degrees


#: Two agents' labels of one actor at one tick further apart than this are reported.
LABEL_TOLERANCE_M = 0.05


def _keys_text(keys: list[str], sep: str = ", ") -> str:
    """The first five items joined, and how many more there are."""
    return sep.join(keys[:5]) + (f" and {len(keys) - 5} more" if len(keys) > 5 else "")


def _files_text(damaged: dict[str, str]) -> str:
    """``file: cause`` of the first five damaged files, and how many more there are."""
    return _keys_text([f"{path}: {cause}" for path, cause in damaged.items()], sep="; ")


def _read_frames(
    agent_dir: UPath, keys: list[str], warnings: list[str], skipped: dict[str, str], listing: dict, reader: Reader
) -> list[src.AgentFrame]:
    """The readable frames (fetched ahead, and kept for the lidar job, which stores their text); an
    unreadable YAML is a warning and ``skipped[key]`` (its cause)."""
    frames = []
    fetched = reader.read_ahead([src.yaml_path(agent_dir, key) for key in keys], listing, keep=True)
    for key, (_, data) in zip(keys, fetched, strict=True):
        try:
            if isinstance(data, SourceError):
                raise data
            frames.append(src.read_agent_frame(agent_dir, key, data))
        except SourceError as err:
            warnings.append(f"{err}; frame skipped")
            skipped[key] = err.cause
    return frames


def _first_readable(reads: list) -> tuple[object | None, dict[str, str]]:
    """The first of a sensor's frames that reads (``reads``: a call per frame, in frame order), and
    the damaged ones before it (file -> cause); (None, every file's cause) when none reads. A
    healthy sensor costs one read."""
    damaged = {}
    for read in reads:
        try:
            return read(), damaged
        except SourceError as err:
            damaged[err.path] = err.cause
    return None, damaged


def _left_out(agent_dir: UPath, sensor: str, what: str, damaged: dict[str, str], warnings: list[str]) -> dict:
    """A sensor none of whose frames reads: one warning naming the files and their causes; its
    ``sensors_not_written`` record."""
    files = _files_text(damaged)
    warnings.append(f"{agent_dir}: {sensor}: no readable {what} of {len(damaged)} ({files}); sensor not written")
    return {"reason": f"no readable {what}", "files": damaged}


def _unread_yamls(agent_dir: UPath, skipped: dict[str, str]) -> dict:
    """The ``not_written`` record of an agent none of whose frame YAMLs reads."""
    files = {str(src.yaml_path(agent_dir, key)): cause for key, cause in skipped.items()}
    return {"reason": "no readable frame YAML", "files": files}


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
    dt_s: float,
    warnings: list[str],
    skipped_keys: dict[str, str] | None = None,
    listing: dict | None = None,
    reader: Reader | None = None,
    specs: dict[Pinhole, consumer.CameraSpec] | None = None,
) -> AgentPlan:
    """Trajectory and calibration of one agent from its frames (at least two); ``skipped_keys``:
    the keys whose YAML could not be read, with the cause; ``listing``: the remote files' sizes
    and ETags (the first readable lidar frame and image are fetched by it and kept); ``specs``: the
    scenario's camera specs so far, by pinhole (``consumer.camera_spec``)."""
    listing = {k: v for k, v in (listing or {}).items() if k.startswith(object_key(agent_dir) + "/")}
    keys = [f.path.stem for f in frames]
    lidar_pose_carla = np.array([f.lidar_pose for f in frames], dtype=np.float64)
    T_lidar_world_global = carla.right_handed_pose(lidar_pose_carla)
    T_vehicle_world_global = carla.right_handed_pose(np.array([f.true_ego_pos for f in frames]))
    mounts: dict[str, dict] = {}
    T_lidar_rig = _mount(
        src.LIDAR, invert_se3(T_vehicle_world_global) @ T_lidar_world_global, mounts, warnings, agent_dir
    )
    T_rig_world_global = T_lidar_world_global @ invert_se3(T_lidar_rig)
    lidar_ids = select_sensors(options.lidar_ids, (src.LIDAR,), "lidar")
    T_sensor_rig = {src.LIDAR: T_lidar_rig}
    intrinsics, camera_index, not_written = {}, {}, {}
    if lidar_ids:  # a lidar is written only if one of its frames reads
        first, damaged = _first_readable([partial(src.fetch_points, agent_dir, key, listing, reader) for key in keys])
        if first is None:
            not_written[src.LIDAR] = _left_out(agent_dir, src.LIDAR, "lidar frame", damaged, warnings)
            lidar_ids = []
    for cam in select_sensors(options.camera_ids, src.CAMERAS, "camera"):
        index = src.CAMERAS.index(cam)
        with_cam = [i for i, f in enumerate(frames) if index in f.camera_cords]
        if not with_cam:
            warnings.append(f"{agent_dir}: no calibration for camera{index} ({cam}); camera not written")
            not_written[cam] = {"reason": f"no frame YAML calibrates camera{index}", "files": {}}
            continue
        first, damaged = _first_readable(
            [partial(src.fetch_png, agent_dir, keys[i], index, listing, reader) for i in with_cam]
        )
        if first is None:
            not_written[cam] = _left_out(agent_dir, f"camera{index} ({cam})", "image", damaged, warnings)
            continue
        size = src.png_size(first)
        T_camera_world_global = carla.opencv_camera_pose(np.array([frames[i].camera_cords[index] for i in with_cam]))
        T_sensor_rig[cam] = _mount(
            cam, invert_se3(T_rig_world_global[with_cam]) @ T_camera_world_global, mounts, warnings, agent_dir
        )
        K = frames[with_cam[0]].camera_intrinsic[index]
        if any(not np.allclose(frames[i].camera_intrinsic[index], K, atol=1e-3) for i in with_cam):
            warnings.append(f"{agent_dir}: camera{index} intrinsics change between frames; the first is stored")
        intrinsics[cam], camera_index[cam] = (K, size), index
    # CARLA's K puts the principal point at the image centre (W/2, H/2): the pixel-corner convention
    cameras = {
        cam: consumer.camera_spec(Pinhole((K[0, 0], K[1, 1]), (K[0, 2], K[1, 2]), size), options.camera_model, specs)
        for cam, (K, size) in intrinsics.items()
    }
    return AgentPlan(
        agent_id=agent_dir.name,
        agent_dir=agent_dir,
        keys=keys,
        timestamps_us=src.key_timestamps_us(keys, dt_s),
        lidar_pose_carla=lidar_pose_carla,
        T_rig_world_global=T_rig_world_global,
        T_sensor_rig=T_sensor_rig,
        intrinsics=intrinsics,
        camera_index=camera_index,
        lidar_ids=lidar_ids,
        mounts=mounts,
        skipped_keys=dict(skipped_keys or {}),
        files=listing,
        sensors_not_written=not_written,
        cameras=cameras,
        speed_mps=np.array([f.ego_speed_kmh / 3.6 for f in frames]),
    )


def merge_boxes(frames: dict[str, list[src.AgentFrame]], warnings: list[str]) -> dict[str, Boxes]:
    """Per frame key: the union of every agent's labelled vehicles by actor id (first agent in id
    order wins; disagreements are reported), plus each CAV's own box, which its YAML lacks (from
    ``true_ego_pos`` and the logreplay CAV model, unless another agent labelled it)."""
    merged: dict[str, dict[int, tuple[np.ndarray, np.ndarray, float]]] = {}
    disagreements: dict[str, int] = {}
    for agent_id in sorted(frames, key=int):
        for frame in frames[agent_id]:
            v = frame.vehicles
            key = frame.path.stem
            if len(v):
                T_box_world_global, dims = carla.boxes_world_right_handed(v.location, v.angle, v.center, v.extent)
                tick = merged.setdefault(key, {})
                speeds = v.speed_kmh / 3.6
                for actor, pose, dim, speed in zip(v.actor_ids.tolist(), T_box_world_global, dims, speeds, strict=True):
                    if actor not in tick:
                        tick[actor] = (pose, dim, float(speed))
                    elif np.linalg.norm(tick[actor][0][:3, 3] - pose[:3, 3]) > LABEL_TOLERANCE_M:
                        disagreements[key] = disagreements.get(key, 0) + 1
    for agent_id in frames:
        if src.is_infrastructure(agent_id):
            continue
        for frame in frames[agent_id]:
            tick = merged.setdefault(frame.path.stem, {})
            if int(agent_id) not in tick:
                pose, dims = carla.boxes_world_right_handed(
                    frame.true_ego_pos[None, :3],
                    frame.true_ego_pos[None, 3:],
                    np.array([src.CAV_BOX_CENTER_M]),
                    np.array([src.CAV_BOX_EXTENT_M]),
                )
                tick[int(agent_id)] = (pose[0], dims[0], frame.ego_speed_kmh / 3.6)
    if disagreements:
        warnings.append(
            f"agents label the same actor more than {LABEL_TOLERANCE_M} m apart at key(s)"
            f" {_keys_text(sorted(disagreements, key=int))}; the lowest agent id's label is kept"
        )
    out = {}
    for key, tick in merged.items():
        ids = np.array(sorted(tick), dtype=np.int64)
        out[key] = Boxes(ids, *(np.array([tick[i][k] for i in ids]) for k in range(3)))
    return out


def plan_scenario(
    root_dir: UPath, scenario: str, options: OpenCoodOptions, reader: Reader | None = None
) -> ScenarioPlan:
    """Read a scenario's YAMLs once through the scenario's ``reader`` (one made for the plan if
    None); decide every agent's trajectory, calibration and the labels. An error raised here carries
    the warnings so far (``errors.warnings_kept``)."""
    warnings: list[str] = []
    with warnings_kept(warnings), reading(reader) as scenario_reader:
        return _plan_scenario(root_dir, scenario, options, warnings, scenario_reader)


def _plan_scenario(
    root_dir: UPath, scenario: str, options: OpenCoodOptions, warnings: list[str], reader: Reader
) -> ScenarioPlan:
    scenario_dir = options.scenario_dir(root_dir, scenario)
    reader.require_folder(scenario_dir, "scenario folder")
    protocol = src.read_protocol(scenario_dir, reader)
    dt_s = protocol.fixed_delta_seconds
    folders = src.list_agents(scenario_dir, reader)
    files: dict = {}  # the remote agent folders' sizes and ETags, from one listing each
    keys = {a: src.list_frame_keys(scenario_dir / a, files, reader) for a in folders}
    all_keys = sorted(set().union(*keys.values()), key=int)
    if not all_keys:
        raise SourceError(scenario_dir, "no frame YAMLs (<key>.yaml) in any agent folder")
    if protocol.text is None:
        warnings.append(
            f"{src.protocol_path(scenario_dir)}: not found; CARLA tick {dt_s} s assumed (OPV2V and"
            " V2XSet's), lidar models from the points"
        )
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
        agent_frames = _read_frames(scenario_dir / agent, keys[agent], warnings, skipped_keys[agent], files, reader)
        if not agent_frames:
            warnings.append(f"{scenario_dir / agent}: no readable frame; agent not written")
            continue
        frames[agent] = agent_frames
    if not frames:
        raise SourceError(scenario_dir, "no agent has a readable frame")
    specs: dict[Pinhole, consumer.CameraSpec] = {}  # one f-theta fit per distinct pinhole of the scenario
    agents = {
        a: plan_agent(scenario_dir / a, f, options, dt_s, warnings, skipped_keys[a], files, reader, specs)
        for a, f in frames.items()
    }
    left_out = {a: {"agent": _unread_yamls(scenario_dir / a, skipped_keys[a])} for a in folders if a not in frames}
    for agent_id, agent in list(agents.items()):
        if agent.sensors_not_written and not agent.lidar_ids and not agent.camera_ids:
            warnings.append(f"{scenario_dir / agent_id}: no sensor with a readable frame; agent not written")
            left_out[agent_id] = agent.sensors_not_written
            del agents[agent_id]
    if not agents:
        damaged = {f: c for record in left_out.values() for r in record.values() for f, c in r["files"].items()}
        raise SourceError(
            next(iter(damaged), scenario_dir),
            f"no agent has a sensor with a readable frame (damaged: {_files_text(damaged)})",
        )
    agents = {a: with_lidar_model(agent, protocol, options, scenario, warnings, reader) for a, agent in agents.items()}
    ego = src.opencood_ego(folders)
    ego_times_us = src.key_timestamps_us(keys[ego], dt_s)
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
    plan = ScenarioPlan(
        scenario=scenario,
        options=options,
        fixed_delta_seconds=dt_s,
        ego=ego,
        ego_keys=keys[ego],
        agent_folders=folders,
        agents=agents,
        boxes=merge_boxes(frames, warnings),
        lidar_specs={a: protocol.lidar_of(a) for a in agents},
        protocol_text=protocol.text,
        warnings=warnings,
        noise=noise,
        agents_not_written=left_out,
        reading=reader.shared(),
    )
    try:
        window_us = consumer.clip_window(options, [a.timestamps_us for a in agents.values()])
    except WindowError as err:
        raise UsageError(f"{scenario_dir}: {err}") from None
    if window_us is not None:
        plan = _clipped(plan, window_us, scenario_dir)
    return _with_labels(plan, scenario_dir)


def _clipped(plan: ScenarioPlan, window_us: tuple[int, int], scenario_dir: UPath) -> ScenarioPlan:
    """The plan cut to the frames whose tick lies in ``window_us``: every agent's frames, the labels
    and each noise setting's per-frame data (planned on the whole scenario, so the draws are those of
    the uncut scenario). Agents left with fewer than 2 frames are not written (a warning)."""
    agents, warnings, left_out = {}, list(plan.warnings), dict(plan.agents_not_written)

    def inside(key: str) -> bool:
        return bool(in_window(src.key_timestamps_us([key], plan.fixed_delta_seconds), window_us)[0])

    for agent_id, agent in plan.agents.items():
        keep = in_window(agent.timestamps_us, window_us)
        if not keep.any():
            warnings.append(f"{scenario_dir / agent_id}: no frame in the clip window; agent not written")
            left_out[agent_id] = {"agent": {"reason": "no frame in the clip window", "files": {}}}
            continue
        rows = np.flatnonzero(keep)
        kept_keys = [agent.keys[i] for i in rows]
        agents[agent_id] = replace(
            agent,
            keys=kept_keys,
            timestamps_us=agent.timestamps_us[rows],
            lidar_pose_carla=agent.lidar_pose_carla[rows],
            T_rig_world_global=agent.T_rig_world_global[rows],
            speed_mps=agent.speed_mps[rows],
            skipped_keys={k: v for k, v in agent.skipped_keys.items() if inside(k)},
        )
    if not agents:
        duration_s = (
            max(int(a.timestamps_us[-1]) for a in plan.agents.values())
            - min(int(a.timestamps_us[0]) for a in plan.agents.values())
        ) / 1e6
        raise UsageError(
            f"{scenario_dir}: the clip window holds no frame of any agent (the scenario lasts {duration_s:.3f} s)"
        )
    ego_keep = in_window(src.key_timestamps_us(plan.ego_keys, plan.fixed_delta_seconds), window_us)
    noise = {
        name: {
            a: _clipped_noise(n, in_window(plan.agents[a].timestamps_us, window_us), ego_keep)
            for a, n in per_agent.items()
            if a in agents
        }
        for name, per_agent in plan.noise.items()
    }
    boxes = {key: b for key, b in plan.boxes.items() if inside(key)}
    return replace(
        plan,
        agents=agents,
        warnings=warnings,
        noise=noise,
        boxes=boxes,
        window_us=window_us,
        agents_not_written=left_out,
        ego_keys=[k for k, keep in zip(plan.ego_keys, ego_keep, strict=True) if keep],
    )


def _clipped_noise(agent_noise: AgentNoise, agent_keep: np.ndarray, ego_keep: np.ndarray) -> AgentNoise:
    """An agent's noise at the kept frames: rows per agent frame by ``agent_keep``, per ego frame by ``ego_keep``."""
    delays = agent_noise.delays
    return replace(
        agent_noise,
        T_rig_world_global=agent_noise.T_rig_world_global[agent_keep],
        pose_noise=agent_noise.pose_noise[agent_keep],
        ego_timestamps_us=agent_noise.ego_timestamps_us[ego_keep],
        delays=replace(
            delays,
            delay_ms=delays.delay_ms[ego_keep],
            source_index=delays.source_index[ego_keep],
            delay_frames=None if delays.delay_frames is None else delays.delay_frames[ego_keep],
        ),
        source_keys=agent_noise.source_keys[ego_keep],
        source_timestamps_us=agent_noise.source_timestamps_us[ego_keep],
    )


def _with_labels(plan: ScenarioPlan, scenario_dir: UPath) -> ScenarioPlan:
    """The merged labels' class names, label source and dynamic tracks, decided once per scenario from
    every tick's boxes in world_global, and the dynamic tracks' boxes for ``dynamic_flag``."""
    keys = sorted(plan.boxes, key=int)
    ticks_us = src.key_timestamps_us(keys, plan.fixed_delta_seconds)
    boxes = [plan.boxes[k] for k in keys]
    counts = [len(b.actor_ids) for b in boxes]
    track_ids = [str(i) for b in boxes for i in b.actor_ids]
    T_box = np.concatenate([b.T_box_world_global for b in boxes]) if boxes else np.zeros((0, 4, 4))
    stamps = np.repeat(ticks_us, counts)
    dims = np.concatenate([b.dims_m for b in boxes]) if boxes else np.zeros((0, 3))
    speeds = np.concatenate([b.speeds_mps for b in boxes]) if boxes else np.zeros(0)
    observations = TrackObservations(track_ids, stamps, T_box[:, :3, 3], T_box[:, :3, :3], dims, speeds)
    cuboid_labels = consumer.cuboid_labels(
        observations,
        [VEHICLE_CLASS] * len(track_ids),
        classes.OPENCOOD_TO_NCORE,
        plan.options.class_names,
        plan.options.cuboid_label_source,
        "GT_SYNTHETIC",
        "world_global",
        str(scenario_dir),
    )
    dynamic_boxes = DynamicBoxes.select(observations, cuboid_labels.dynamic)
    return replace(
        plan, cuboid_labels=cuboid_labels, dynamic_boxes=dynamic_boxes, warnings=plan.warnings + cuboid_labels.warnings
    )
