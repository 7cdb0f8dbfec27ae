"""OPV2V / V2XSet: the records a scenario's plan is made of (the command's options, each agent's plan,
the merged labels per tick, the scenario plan), read by the planner and the writer."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from upath import UPath

from ncore_convert.contract import Layout, LidarModelSource, Profile, StoreType
from ncore_convert.converters import consumer
from ncore_convert.converters.common import ConsumerOptions
from ncore_convert.converters.opencood.noise import AgentNoise
from ncore_convert.sources import opencood as src
from ncore_convert.sources.reader import ReadSettings
from ncore_convert.transforms.geometry import ONE_TICK_STEP_US, one_tick_trajectory
from ncore_convert.transforms.lidar.model import SpinningLidarModel
from ncore_convert.transforms.noise import NoiseSetting
from ncore_convert.transforms.objects.dynamic import DynamicBoxes

#: The source class of every OPV2V / V2XSet label (the YAMLs list vehicles only).
VEHICLE_CLASS = "vehicle"


@dataclass(frozen=True)
class OpenCoodOptions(ConsumerOptions):
    """Options of the ``opv2v-v4`` and ``v2xset-v4`` commands (sensor selection: None = all)."""

    dataset: Literal["opv2v", "v2xset"]
    split: str
    layout: Layout = "agents"
    lidar_model_source: LidarModelSource = "empirical"
    store_type: StoreType = "itar"
    profile: Profile = "separate-sensors"
    sequence_meta: bool = True
    camera_ids: tuple[str, ...] | None = None
    lidar_ids: tuple[str, ...] | None = None
    noise: tuple[NoiseSetting, ...] = ()  #: GPS-error / delay settings, each a further poses instance
    camera_labels: tuple[str, ...] = ()  #: ``contract.CAMERA_LABEL_KINDS`` written per camera frame

    def scenario_dir(self, root_dir: UPath, scenario: str) -> UPath:
        return src.scenario_dir(root_dir, self.split, scenario)


@dataclass(frozen=True)
class AgentPlan:
    """One agent's frames and calibration, read and decided once.

    Attributes:
        keys: frame keys with a readable YAML; timestamps_us: their times, int64 [N].
        lidar_pose_carla: the YAMLs' ``lidar_pose`` [N,6] (CARLA: x, y, z m; roll, yaw, pitch deg).
        T_rig_world_global: right-handed rig poses (rig -> world_global) [N,4,4], float64.
        T_sensor_rig: sensor -> rig [4,4] (lidar frame right-handed; cameras in OpenCV axes).
        intrinsics: camera id -> (K [3,3], (width, height)); camera_index: camera id -> file index.
        mounts: how much each re-measured mounting moved (metadata).
        cameras: how each camera is stored (``--camera-model``).
    """

    agent_id: str
    agent_dir: UPath
    keys: list[str]
    timestamps_us: np.ndarray
    lidar_pose_carla: np.ndarray
    T_rig_world_global: np.ndarray
    T_sensor_rig: dict[str, np.ndarray]
    intrinsics: dict[str, tuple[np.ndarray, tuple[int, int]]]
    camera_index: dict[str, int]
    lidar_ids: list[str]
    mounts: dict[str, dict]
    skipped_keys: dict[str, str] = field(default_factory=dict)  #: frame key -> why its YAML was unreadable
    #: sensor id -> why it is not written, {"reason", "files": {file: cause}} (``contract.SENSORS_NOT_WRITTEN``)
    sensors_not_written: dict[str, dict] = field(default_factory=dict)
    cameras: dict[str, consumer.CameraSpec] = field(default_factory=dict)
    lidar_model: SpinningLidarModel | None = None  #: the CARLA lidar's structured model (None: raw rays only)
    lidar_model_meta: dict = field(default_factory=dict)  #: how it was derived, or why there is none
    speed_mps: np.ndarray = field(default_factory=lambda: np.zeros(0))  #: the YAMLs' ego_speed [N], m/s (NaN: none)
    files: dict = field(default_factory=dict)  #: remote files' sizes and ETags from the folder's listing

    @property
    def kind(self) -> str:
        return src.agent_kind(self.agent_id)

    @property
    def camera_ids(self) -> list[str]:
        return list(self.intrinsics)

    @property
    def n_frames(self) -> int:
        return len(self.keys) * (len(self.lidar_ids) + len(self.camera_ids))

    def pose_samples(self, T_rig_x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The trajectory to store from per-frame rig poses ``T_rig_x`` [N,4,4]: (timestamps_us
        int64 [M], poses [M,4,4]); a one-tick agent's single pose is followed 1 µs later by its
        extrapolation at the tick's ego_speed (``transforms.geometry.one_tick_trajectory``, as NCore
        needs two poses)."""
        if len(self.keys) > 1:
            return self.timestamps_us, T_rig_x
        return one_tick_trajectory(int(self.timestamps_us[0]), T_rig_x[0], float(self.speed_mps[0]))

    @property
    def pose_span_us(self) -> tuple[int, int]:
        """First and last time of :meth:`pose_samples` (µs): a one-tick agent's poses end 1 µs after its tick."""
        end_us = int(self.timestamps_us[-1]) + (ONE_TICK_STEP_US if len(self.keys) == 1 else 0)
        return int(self.timestamps_us[0]), end_us


@dataclass(frozen=True)
class Boxes:
    """Merged vehicle labels of one tick: actor ids [M], right-handed ``T_box_world_global`` [M,4,4],
    (length, width, height) [M,3] and CARLA's speed [M] (m/s, NaN where the YAML has none)."""

    actor_ids: np.ndarray
    T_box_world_global: np.ndarray
    dims_m: np.ndarray
    speeds_mps: np.ndarray


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
    lidar_specs: dict[str, dict]  #: agent id -> its data_protocol.yaml lidar block
    protocol_text: str | None  #: data_protocol.yaml as it is (None: the scenario has none)
    warnings: list[str]
    noise: dict[str, dict[str, AgentNoise]]  #: setting name -> agent id -> perturbations
    window_us: tuple[int, int] | None = None  #: the clip window (inclusive µs), None for the whole scenario
    #: agent id -> what was left out and why, ``{"agent" or sensor id: {"reason", "files"}}``, for the
    #: agents not written
    agents_not_written: dict[str, dict] = field(default_factory=dict)
    cuboid_labels: consumer.CuboidLabels | None = None  #: class names, label source, dynamic tracks
    dynamic_boxes: DynamicBoxes | None = None  #: the dynamic tracks' boxes in world_global
    reading: ReadSettings = field(default_factory=ReadSettings)  #: for the readers of the scenario's jobs

    def sequence_id(self, agent_id: str) -> str:
        return f"{self.scenario}_agent{agent_id}"


@dataclass(frozen=True)
class Names:
    """Frame and sensor names of one agent in a sequence (prefixed in the scenario layout)."""

    prefix: str = ""

    @property
    def rig(self) -> str:
        return f"{self.prefix}rig"

    def sensor(self, sensor_id: str) -> str:
        return f"{self.prefix}{sensor_id}"
