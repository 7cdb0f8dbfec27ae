"""The names the writer side writes and the read side reads back: one definition for both.

Converters put these keys and files into a sequence; ``validate``, ``preview`` and the CLI find
them again. Nothing here reads or writes files; see ``writer/`` for where they are written.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Literal

from ncore_convert import __version__

#: Names from the data that become output paths (log ids, sensor names): one path component, no
#: separators, not hidden, not "." or "..", at most 128 characters.
SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")

# --- conversion options that name what is written (the CLI's choices come from these) ---
StoreType = Literal["itar", "directory"]
Profile = Literal["default", "separate-sensors", "separate-all"]
LidarModelSource = Literal["empirical", "none"]
Layout = Literal["agents", "scenario"]  #: OpenCOOD: a sequence per agent, or one sequence per scenario
CameraModel = Literal["ideal-pinhole", "opencv-pinhole", "ftheta"]  #: how a pinhole camera is stored
ClassNames = Literal["ncore", "source"]  #: cuboid class names: NCore's lowercase names, or the dataset's own
CuboidLabelSource = Literal["auto", "external", "gt-synthetic", "autolabel"]  #: the observations' LabelSource
WorldGlobalMode = Literal["none", "identity", "localized"]  #: what ``world -> world_global`` holds
Preset = Literal["ncore", "3dgut", "3dgrt", "nurec", "instant-nurec"]  #: ``--preset``: a consumer's options
#: ``--preset`` -> the consumer options it sets (docs/consumers.md says why); explicit flags override
#: them. ``ncore`` sets nothing: the defaults, which match NCore's own AV2 converter.
PRESETS: dict[str, dict[str, object]] = {
    "ncore": {},
    "3dgut": {"camera_model": "opencv-pinhole", "world_global_mode": "identity", "lidar_rgb": True},
    "3dgrt": {"camera_model": "opencv-pinhole", "world_global_mode": "identity", "lidar_rgb": True},
    "nurec": {"camera_model": "opencv-pinhole", "world_global_mode": "identity", "lidar_rgb": True},
    "instant-nurec": {"camera_model": "ftheta", "cuboid_label_source": "autolabel"},
}
#: ``--ego-box-m``'s default: the nominal ego vehicle's (length, width, height) in metres, AV2's car
#: (a Ford Fusion Hybrid; ``transforms.camera.ego_mask.EgoBox``).
EGO_BOX_M = (4.9, 1.9, 1.5)
# --- the noise settings' vocabularies (OpenCOOD's wild_setting; ``transforms.noise``) ---
NoiseModel = Literal["opencood", "realistic"]
AsyncMode = Literal["sim", "real"]
GpsProcess = Literal["white", "gauss_markov"]
GpsDof = Literal["6dof", "xy_yaw"]
#: The consumer options a preset may set, and their values under none (``converters.common.ConsumerOptions``).
PRESET_DEFAULTS: dict[str, object] = {
    "camera_model": "ideal-pinhole",
    "cuboid_label_source": "auto",
    "world_global_mode": "localized",
    "lidar_rgb": False,
}

# --- dataset ids: the sequence metadata's ``source_dataset`` ---
ARGOVERSE2_SENSOR = "argoverse2-sensor"
ARGOVERSE2_TBV = "argoverse2-tbv"
OPV2V = "opv2v"
V2XSET = "v2xset"
ARGOVERSE2_DATASETS = (ARGOVERSE2_SENSOR, ARGOVERSE2_TBV)
OPENCOOD_DATASETS = (OPV2V, V2XSET)

# --- keys of the sequence's generic metadata ---
SOURCE_DATASET = "source_dataset"
CONVERTER = "converter"  #: converter_meta(): {"name", "version", "options"}
AV2_SPLIT = "argoverse2_split"  #: None for TbV (logs directly under the root)
AV2_LOG_ID = "argoverse2_log_id"
OPENCOOD_SPLIT = "opencood_split"
SCENARIO = "scenario"
AGENTS = "agents"  #: agent id -> {"kind", "opencood_ego"}

WORLD_GLOBAL = "world_global"  #: {"mode", "T_world_dataset_global" (4x4, float64 rows), "dataset_global"}
CLIP = "clip"  #: {"seek_sec", "duration_sec", "start_us", "end_us"}: the window the sequence was cut to

# --- keys of cuboid component metadata ---
#: track id -> the dataset's own class name, when ``class_names`` is "ncore" (recoverable without the source)
SOURCE_CLASS_BY_TRACK = "source_class_by_track"
#: track id -> {"net_m", "peak_deviation_m"[, "max_speed_mps"]} of the tracks judged dynamic (the rule
#: behind ``dynamic_flag``)
DYNAMIC_TRACKS = "dynamic_tracks"
#: {"frame", "convention", "tracks": track id -> {"centroid", "dim", "rot"}}: each static track's median box
STATIC_POSES = "static_poses"

# --- camera masks ---
EGO_MASK = "ego"  #: the camera mask of the ego vehicle's pixels (non-zero = ego), as 3DGRUT and NuRec read it
#: ``validate``: a present ego mask covering more of its image than this is implausible
EGO_MASK_MAX_FRACTION = 0.5

# --- per-frame lidar generic data ---
DYNAMIC_FLAG = "dynamic_flag"  #: int8 [N]: 1 = the point lies in a dynamic track's box grown by 0.5 m
#: sequence metadata: where ``dynamic_flag`` comes from (annotations, lidar free space) and how
DYNAMIC_FLAG_SOURCE = "dynamic_flag_source"
#: int8 [N], with flags from the lidar: 1 = whether the point moved could not be judged (its ``dynamic_flag`` is 0)
DYNAMIC_UNKNOWN = "dynamic_flag_unknown"
LIDAR_RGB = "rgb"  #: uint8 [N,3]: the point's colour from the cameras (3DGRUT's ``lidar_color_generic_data_name``)
#: uint32 [K], present when K > 0: the rays whose float32 ``direction * distance`` is not the source file's point
#: (OpenCOOD: the few with no unit direction and distance that multiply to it; transforms.lidar.rays.exact_rays)
SOURCE_XYZ_INDEX = "source_xyz_index"
#: float32 [K,3]: those rays' points as the source file has them, in the (right-handed) sensor frame, metres
SOURCE_XYZ = "source_xyz"
#: OpenCOOD, present when K > 0: the source points that are not rays (zero range, a non-finite
#: coordinate): their positions in the file (uint32 [K]), x, y, z as the file has them (float32 [K,3],
#: right-handed sensor frame) and intensities (float32 [K]), so that the file's every point comes back
UNSTORED_INDEX = "unstored_points_index"
UNSTORED_XYZ = "unstored_points_xyz"
UNSTORED_INTENSITY = "unstored_points_intensity"

#: sequence metadata: sensor id -> why it was not written, {"reason", "files": {file: cause}} (every
#: source frame of it unreadable, or none in the clip window)
SENSORS_NOT_WRITTEN = "sensors_not_written"

# --- keys of sensor metadata ---
#: sensor metadata: frame key -> why the source frame was not written (unreadable YAML, PCD or image)
SKIPPED_FRAMES = "skipped_frames"
#: lidar metadata (AV2: per cause; OpenCOOD: per frame) of points that have no unit direction
POINTS_NOT_STORED = "points_not_stored"
#: OpenCOOD lidar frame metadata: the frame's CARLA frame counter (its OpenCOOD key, as an int)
CARLA_FRAME = "carla_frame"
#: OpenCOOD lidar frame metadata: the agent-frame's ``<key>.yaml`` text as it is (the OpenCOOD view
#: and export read it back)
OPENCOOD_YAML = "opencood_yaml"
#: OpenCOOD lidar frame metadata: the PCD's layout, e.g. ``"x y z rgb ascii"`` (the export writes it back so)
PCD_LAYOUT = "pcd_layout"
#: OpenCOOD sequence metadata: the scenario's ``data_protocol.yaml`` text as it is (None: it had none)
OPENCOOD_PROTOCOL = "opencood_data_protocol"

# --- component instances ---
#: The instance name every component is written under, and the one ``SequenceLoaderV4`` opens by default.
DEFAULT_INSTANCE = "default"
#: ``--camera-labels`` kinds, each one NCore camera-labels component per camera, named by NCore's
#: convention ``category.qualifier@camera_id``: ``depth`` -> ``depth.z@<camera>`` (z-depth in metres
#: from the lidar points the camera sees, 0 = no measurement); ``dynamic`` -> ``mask.dynamic@<camera>``
#: (1 where a moving object shows, else 0); ``instance`` -> ``segmentation.instance@<camera>``
#: (the per-sequence instance index of the object each pixel shows, 0 = none).
CAMERA_LABEL_KINDS = ("depth", "dynamic", "instance")
CAMERA_LABEL_QUALIFIED = {"depth": "depth.z", "dynamic": "mask.dynamic", "instance": "segmentation.instance"}
#: The kinds made from the annotated boxes (the others from the lidar points).
BOX_LABEL_KINDS = ("dynamic", "instance")
#: ``mask.dynamic``'s component metadata ``generator`` when it is made from the movers the lidar itself
#: found (TbV: no boxes), not from annotated boxes
MOVER_MASK_GENERATOR = "ncore-convert transforms.camera.mover_mask"


def camera_label_id(kind: str, camera_id: str) -> str:
    """The component instance name of a camera label (``depth.z@ring_front_center``)."""
    return f"{CAMERA_LABEL_QUALIFIED[kind]}@{camera_id}"


# --- the HD map, stored as generic data of the poses component ---
MAP_VECTOR_JSON = "hd_map_vector_json"
MAP_GROUND_HEIGHT = "hd_map_ground_height_m"
MAP_META = "hd_map"

# --- cooperative scenarios ---
MANIFEST = "scenario.json"


def converter_meta(options: dict[str, Any]) -> dict[str, Any]:
    """The sequence metadata's ``converter`` record: this tool, its version and the conversion options."""
    return {"name": "ncore-convert", "version": __version__, "options": options}


def agent_prefix(agent_id: str | int) -> str:
    """The prefix of an agent's frames and sensors in a sequence that holds several agents."""
    return f"agent{agent_id}_"


@dataclass(frozen=True)
class ManifestAgent:
    """One agent folder of a scenario; the optional fields are set for written agents only, and
    ``sequence`` (agents layout) or ``frame_prefix`` (scenario layout) by the layout."""

    agent_id: int
    kind: str
    opencood_ego: bool
    written: bool
    frames: int | None = None
    sensors: list[str] | None = None
    sequence: str | None = None  #: ``<agent_id>/<sequence_id>.json``, relative to the manifest
    frame_prefix: str | None = None
    #: what of the agent was left out and why: sensor id (or ``"agent"``) -> {"reason", "files"}
    not_written: dict[str, dict] | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "agent_id": self.agent_id,
            "kind": self.kind,
            "opencood_ego": self.opencood_ego,
            "written": self.written,
        }
        for name in ("frames", "sensors", "sequence", "frame_prefix", "not_written"):
            if (value := getattr(self, name)) is not None:
                out[name] = value
        return out


@dataclass(frozen=True)
class ManifestNoise:
    """A noise setting of the scenario and the poses instance that holds it."""

    name: str
    model: str
    seed: int
    poses_instance: str


@dataclass(frozen=True)
class ScenarioManifest:
    """``scenario.json``: how a cooperative scenario's agents and sequences relate."""

    scenario: str
    dataset: str
    split: str
    layout: Layout
    sequence: str | None  #: the one sequence meta of the scenario layout, relative to the manifest
    world_global: str
    fixed_delta_seconds: float
    time_base: str
    ego_agent_id: int
    ego_rule: str
    agents: list[ManifestAgent]
    noise_settings: list[ManifestNoise]
    labels: str

    def sequence_of(self, agent: ManifestAgent) -> str:
        """The sequence meta holding ``agent``, relative to the manifest."""
        return self.sequence if self.layout == "scenario" else agent.sequence

    def prefix_of(self, agent: ManifestAgent) -> str:
        """The prefix of ``agent``'s frame and sensor names in its sequence."""
        return agent.frame_prefix if self.layout == "scenario" else ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario": self.scenario,
            "dataset": self.dataset,
            "split": self.split,
            "layout": self.layout,
            "sequence": self.sequence,
            "world_global": self.world_global,
            "fixed_delta_seconds": self.fixed_delta_seconds,
            "time_base": self.time_base,
            "ego": {"agent_id": self.ego_agent_id, "rule": self.ego_rule},
            "agents": [a.to_dict() for a in self.agents],
            "noise_settings": [vars(n).copy() for n in self.noise_settings],
            "labels": self.labels,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ScenarioManifest:
        return cls(
            scenario=data["scenario"],
            dataset=data["dataset"],
            split=data["split"],
            layout=data["layout"],
            sequence=data.get("sequence"),
            world_global=data.get("world_global", ""),
            fixed_delta_seconds=data["fixed_delta_seconds"],
            time_base=data.get("time_base", ""),
            ego_agent_id=data["ego"]["agent_id"],
            ego_rule=data["ego"].get("rule", ""),
            agents=[ManifestAgent(**a) for a in data["agents"]],
            noise_settings=[ManifestNoise(**n) for n in data.get("noise_settings", [])],
            labels=data.get("labels", ""),
        )
