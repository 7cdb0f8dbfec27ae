"""GPS error and communication delay of a scenario's agents under one setting (docs/noise.md): the
models of :mod:`ncore_convert.transforms.noise` applied to the agents of a scenario plan, and the
arrays and metadata the writer stores in the setting's ``PosesComponent`` instance."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ncore_convert.sources import opencood as src
from ncore_convert.transforms import carla, noise
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.noise import NoiseSetting


class AgentMotion(Protocol):
    """What the noise models read of an agent (``plan.AgentPlan`` has it).

    Attributes:
        keys: the agent's frame keys [N]; timestamps_us: their times, int64 [N].
        lidar_pose_carla: the YAMLs' ``lidar_pose`` [N,6] (CARLA: x, y, z m; roll, yaw, pitch deg).
        T_rig_world_global: rig -> world_global [N,4,4]; T_sensor_rig: sensor -> rig [4,4] by sensor id.
    """

    keys: list[str]
    timestamps_us: np.ndarray
    lidar_pose_carla: np.ndarray
    T_rig_world_global: np.ndarray
    T_sensor_rig: dict[str, np.ndarray]


#: What each generic-data array of a noisy poses instance holds (prefixed ``agent<id>_`` in the
#: scenario layout). T = the OpenCOOD ego's frames, N = the agent's frames.
ARRAYS = {
    "pose_noise_timestamps_us": "uint64 [N]: the agent's frame times (those of its rig->world poses)",
    "pose_noise": "float64 [N,6]: the error applied at each frame (layout: pose_noise_layout)",
    "delay_ego_timestamps_us": "uint64 [T]: the ego's frame times (OpenCOOD's timestamp index)",
    "delay_ms": "float64 [T]: the modelled communication delay of the agent's data at each ego frame",
    "delay_source_timestamps_us": "int64 [T]: time of the agent frame used at each ego frame (-1: none)",
    "delay_source_keys": "int64 [T]: CARLA frame key of that agent frame (-1: none)",
    "delay_frames": "int64 [T]: OpenCOOD's time_delay, frames behind in the ego's frame list (opencood model)",
}
POSE_NOISE_LAYOUT = {
    "opencood": "offset added to OpenCOOD's lidar_pose [x, y, z, roll, yaw, pitch] in CARLA's left-handed map"
    " frame, m and deg (only x, y, z and yaw are perturbed)",
    "realistic": "[dx, dy, dz] m along world_global's axes, then [droll, dpitch, dyaw] deg, extrinsic x-y-z"
    " rotation about world_global's axes at the rig origin",
}


@dataclass(frozen=True)
class AgentNoise:
    """One agent under one setting.

    Attributes:
        T_rig_world_global: the perturbed rig poses (rig -> world_global) [N,4,4] at the agent's frames.
        pose_noise: the error applied [N,6] (layout: ``POSE_NOISE_LAYOUT[model]``).
        ego_timestamps_us: the ego's frame times, int64 [T].
        delays: delay and source frame at each ego frame.
        source_keys, source_timestamps_us: CARLA key and time of that source frame, int64 [T] (-1: none).
    """

    T_rig_world_global: np.ndarray
    pose_noise: np.ndarray
    ego_timestamps_us: np.ndarray
    delays: noise.Delays
    source_keys: np.ndarray
    source_timestamps_us: np.ndarray

    def arrays(self, agent_timestamps_us: np.ndarray, prefix: str = "") -> dict[str, np.ndarray]:
        """The generic data of this agent in a noisy poses instance (see ``ARRAYS``);
        ``agent_timestamps_us``: the agent's frame times, int64 [N]."""
        out = {
            "pose_noise_timestamps_us": agent_timestamps_us.astype(np.uint64),
            "pose_noise": self.pose_noise,
            "delay_ego_timestamps_us": self.ego_timestamps_us.astype(np.uint64),
            "delay_ms": self.delays.delay_ms,
            "delay_source_timestamps_us": self.source_timestamps_us,
            "delay_source_keys": self.source_keys,
        }
        if self.delays.delay_frames is not None:
            out["delay_frames"] = self.delays.delay_frames
        return {f"{prefix}{name}": value for name, value in out.items()}


def opencood_loaded(setting: NoiseSetting, agent_folders: list[str]) -> list[str]:
    """The agents a setting perturbs and delays: OpenCOOD's order cut at ``max_cav`` (the ``opencood``
    model, as OpenCOOD loads them), or every agent (``realistic``). The first is OpenCOOD's ego."""
    order = src.opencood_order(agent_folders)
    return order[: setting.max_cav] if setting.model == "opencood" else order


def _sources(agent: AgentMotion, source_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keys = np.array([int(k) for k in agent.keys], dtype=np.int64)
    found = source_index != noise.NO_SOURCE
    index = np.where(found, source_index, 0)
    return (
        np.where(found, keys[index], noise.NO_SOURCE),
        np.where(found, agent.timestamps_us[index], noise.NO_SOURCE).astype(np.int64),
    )


def _opencood(
    setting: NoiseSetting, agents: dict[str, AgentMotion], loaded: list[str], ego_keys: list[str]
) -> dict[str, tuple[np.ndarray, np.ndarray, noise.Delays]]:
    """Per agent: (T_rig_world_global, pose_noise, delays) under OpenCOOD's semantics."""
    ego = loaded[0]
    schedule = noise.opencood_delays(setting, len(ego_keys), loaded, ego)
    offset = noise.opencood_loc_offset(setting)
    out = {}
    for agent_id, agent in agents.items():
        n = len(agent.keys)
        pose_noise = np.zeros((n, 6)) if agent_id == ego or agent_id not in loaded else np.tile(offset, (n, 1))
        T_lidar_world_global = carla.right_handed_pose(agent.lidar_pose_carla + pose_noise)
        T_rig_world_global = T_lidar_world_global @ invert_se3(agent.T_sensor_rig[src.LIDAR])
        if agent_id in loaded:
            delay_ms, frames = schedule[agent_id]
            index_in_agent = {k: i for i, k in enumerate(agent.keys)}
            source = [index_in_agent.get(ego_keys[i - d], noise.NO_SOURCE) for i, d in enumerate(frames.tolist())]
            delays = noise.Delays(delay_ms, np.array(source, dtype=np.int64), frames)
        else:  # OpenCOOD does not load agents past max_cav
            t = len(ego_keys)
            delays = noise.Delays(np.zeros(t), np.full(t, noise.NO_SOURCE), np.zeros(t, dtype=np.int64))
        out[agent_id] = (T_rig_world_global, pose_noise, delays)
    return out


def _realistic(
    setting: NoiseSetting, scenario: str, agents: dict[str, AgentMotion], ego: str, ego_timestamps_us: np.ndarray
) -> dict[str, tuple[np.ndarray, np.ndarray, noise.Delays]]:
    out = {}
    for agent_id, agent in agents.items():
        pose_rng, delay_rng = noise.agent_rngs(setting, scenario, agent_id)
        pose_noise = noise.realistic_pose_noise(setting, pose_rng, agent.timestamps_us)
        if agent_id == ego:
            if not setting.perturb_ego:
                pose_noise = np.zeros_like(pose_noise)
            delay_ms = np.zeros(len(ego_timestamps_us))
        else:
            delay_ms = noise.realistic_delays_ms(setting, delay_rng, len(ego_timestamps_us))
        source = noise.latest_source(agent.timestamps_us, ego_timestamps_us, delay_ms)
        T_rig_world_global = noise.perturb_poses(agent.T_rig_world_global, pose_noise)
        out[agent_id] = (T_rig_world_global, pose_noise, noise.Delays(delay_ms, source))
    return out


def plan_noise(
    setting: NoiseSetting,
    scenario: str,
    agents: dict[str, AgentMotion],
    agent_folders: list[str],
    ego_keys: list[str],
    ego_timestamps_us: np.ndarray,
) -> dict[str, AgentNoise]:
    """Every written agent's perturbed trajectory and delays under ``setting``.

    Args:
        agent_folders: all agent folders of the scenario (OpenCOOD's order and ego come from them).
        ego_keys: the OpenCOOD ego's frame keys (its YAML files), which index OpenCOOD's frames;
        ego_timestamps_us: their times, int64 [T].
    """
    loaded = opencood_loaded(setting, agent_folders)
    if setting.model == "opencood":
        models = _opencood(setting, agents, loaded, ego_keys)
    else:
        models = _realistic(setting, scenario, agents, loaded[0], ego_timestamps_us)
    out = {}
    for agent_id, (T_rig_world_global, pose_noise, delays) in models.items():
        keys, times = _sources(agents[agent_id], delays.source_index)
        out[agent_id] = AgentNoise(T_rig_world_global, pose_noise, ego_timestamps_us, delays, keys, times)
    return out


def instance_meta(setting: NoiseSetting, agent_folders: list[str]) -> dict:
    """The generic metadata of a setting's poses instance: the full setting, model, seed and layout."""
    meta = {
        "calibration_type": "carla-sensor-transforms",
        "egomotion_type": f"carla-ground-truth-lidar_pose with simulated GPS error ({setting.model} model)",
        "noise_setting": setting.as_dict(),
        "noise_model": setting.model,
        "noise_seed": setting.seed,
        "opencood_ego": int(src.opencood_ego(agent_folders)),
        "pose_noise_layout": POSE_NOISE_LAYOUT[setting.model],
        "generic_data": {k: v for k, v in ARRAYS.items() if k != "delay_frames" or setting.model == "opencood"},
    }
    if setting.model == "opencood":
        meta["agents_loaded_by_opencood"] = [int(a) for a in opencood_loaded(setting, agent_folders)]
        meta["generator_state"] = (
            "numpy legacy RandomState seeded with the seed at the scenario's first frame; real-mode draws"
            " follow OpenCOOD's order (per ego frame, per non-ego agent), and add_loc_noise re-seeds it"
        )
    return meta
