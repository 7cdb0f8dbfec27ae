"""A converted cooperative scenario (OPV2V, V2XSet) read back as OpenCOOD reads its raw files.

OpenCOOD and the frameworks built on it read ``<scenario>/<agent>/<key>.pcd|.yaml``. This view gives
the same values from the NCore sequences of a ``scenario.json`` (either layout), per frame key and
agent, in CARLA's conventions (left-handed frames; poses ``[x, y, z, roll, yaw, pitch]`` in metres
and degrees):

- :meth:`OpenCoodScenario.lidar_points`: what OpenCOOD's PCD reader returns, ``[N,4]`` x, y, z,
  intensity in the agent's lidar frame, in the PCD's point order (points at zero range were not
  stored by the converter and are not returned);
- :meth:`OpenCoodScenario.lidar_pose`: the YAML's ``lidar_pose``, from the sequence's pose graph
  (the ground truth, or the poses instance of a stored noise setting: OpenCOOD's ``loc_err``);
- :meth:`OpenCoodScenario.params`: the frame's whole YAML (the converter stores its text with the
  lidar frame), with that ``lidar_pose`` under a noise setting;
- :meth:`OpenCoodScenario.images`: the camera PNGs as they were;
- :meth:`OpenCoodScenario.delayed_key`: the frame OpenCOOD's ``async`` reads for an agent at an
  ego frame, from the noise setting's stored delays;
- :attr:`OpenCoodScenario.protocol_text`: ``data_protocol.yaml`` as it was;
- :meth:`OpenCoodScenario.base_data`: all of that per agent at an ego frame, as OpenCOOD's base
  dataset builds it (``views.opencood_torch`` wraps it as a torch ``Dataset``);
- :meth:`OpenCoodScenario.cooperative_points`: the ego-frame cloud of OpenCOOD's early fusion.

It reads NCore only (through ``validate.readback``) and imports nothing of the converters.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from ncore.data.v4 import PosesComponent
from upath import UPath

from ncore_convert.contract import (
    CARLA_FRAME,
    DEFAULT_INSTANCE,
    OPENCOOD_PROTOCOL,
    OPENCOOD_YAML,
    PCD_LAYOUT,
    SOURCE_XYZ,
    SOURCE_XYZ_INDEX,
    UNSTORED_INDEX,
    UNSTORED_INTENSITY,
    UNSTORED_XYZ,
    ManifestAgent,
    ScenarioManifest,
)
from ncore_convert.sources.opencood import CAMERAS, LIDAR, opencood_order, parse_yaml
from ncore_convert.transforms import carla
from ncore_convert.validate.poses import sensor_poses
from ncore_convert.validate.readback import OpenSequence, open_sequence, read_manifest


@dataclass
class OpenCoodScenario:
    """The converted scenario of ``manifest_path`` (its ``scenario.json``), read with the poses of
    ``poses`` (None: the ground truth; else a noise setting's name in the manifest)."""

    manifest_path: UPath
    poses: str | None = None
    _sequences: dict[str, OpenSequence] = field(default_factory=dict, repr=False)
    _keys: dict[str, dict[str, int]] = field(default_factory=dict, repr=False)  #: agent -> key -> lidar frame
    _lidars: dict[str, object] = field(default_factory=dict, repr=False)  #: agent -> its lidar sensor (opened once)
    #: agent -> the setting's (ego frame times us [T], delayed source keys [T]), read once
    _delays: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False)

    @classmethod
    def open(cls, manifest_path: UPath | str, poses: str | None = None) -> OpenCoodScenario:
        scenario = cls(UPath(manifest_path), poses)
        scenario._poses_instance  # noqa: B018 - an unknown setting is an error now, not at the first read
        return scenario

    @cached_property
    def manifest(self) -> ScenarioManifest:
        return read_manifest(self.manifest_path)

    @cached_property
    def _poses_instance(self) -> str:
        """The poses component instance the view reads (ValueError naming the stored settings)."""
        if self.poses is None:
            return DEFAULT_INSTANCE
        for setting in self.manifest.noise_settings:
            if setting.name == self.poses:
                return setting.poses_instance
        known = ", ".join(n.name for n in self.manifest.noise_settings) or "none"
        raise ValueError(f"{self.manifest_path}: no noise setting {self.poses!r} (stored: {known})")

    @property
    def ego_agent_id(self) -> str:
        """The agent OpenCOOD takes as its ego (its folder name)."""
        return str(self.manifest.ego_agent_id)

    @property
    def agent_ids(self) -> list[str]:
        """The written agents' folder names, in the manifest's order."""
        return [str(a.agent_id) for a in self.manifest.agents if a.written]

    def has_lidar(self, agent_id: str) -> bool:
        """Whether the agent's lidar was written (the conversion leaves out a lidar none of whose
        frames read)."""
        return self._name(agent_id, LIDAR) in self._sequence(agent_id).loader.lidar_ids

    def left_out(self) -> list[str]:
        """What the conversion left out of the scenario and why, a line per agent or sensor (the
        manifest's ``not_written``)."""
        lines = []
        for agent in self.manifest.agents:
            for sensor, record in (agent.not_written or {}).items():
                files = record.get("files") or {}
                example = f"; {len(files)} file(s): {next(iter(files))}, ..." if files else ""
                what = "the agent" if sensor == "agent" else sensor
                lines.append(f"agent {agent.agent_id}: {what} not written ({record.get('reason')}{example})")
            if not agent.written and not agent.not_written:
                lines.append(f"agent {agent.agent_id}: not written")
        return lines

    def keys(self, agent_id: str) -> list[str]:
        """The agent's frame keys (6-digit CARLA frame counters) that have a lidar frame."""
        return list(self._lidar_keys(agent_id))

    def lidar_points(self, agent_id: str, key: str) -> np.ndarray:
        """The frame's points as OpenCOOD's PCD reader returns them: float32 [N,4], x, y, z in the
        agent's CARLA (left-handed) lidar frame in metres, and intensity in [0, 1]."""
        lidar = self._lidar(agent_id)
        frame = self._frame(agent_id, key)
        direction = lidar.get_frame_ray_bundle_direction(frame)
        distance_m = lidar.get_frame_ray_bundle_return_distance_m(frame)
        xyz = direction * distance_m[:, None]  # float32 x float32: the converter chose both so this is the source
        names = set(lidar.get_frame_generic_data_names(frame))
        if SOURCE_XYZ_INDEX in names:  # the few rays with no exact direction and distance
            xyz[lidar.get_frame_generic_data(frame, SOURCE_XYZ_INDEX)] = lidar.get_frame_generic_data(frame, SOURCE_XYZ)
        points = np.concatenate([xyz, lidar.get_frame_ray_bundle_return_intensity(frame)[:, None]], axis=1)
        if UNSTORED_INDEX in names:  # the points that are not rays, back at their places in the file
            where = lidar.get_frame_generic_data(frame, UNSTORED_INDEX).astype(np.int64)
            intensity = lidar.get_frame_generic_data(frame, UNSTORED_INTENSITY)[:, None]
            unstored = np.concatenate([lidar.get_frame_generic_data(frame, UNSTORED_XYZ), intensity], axis=1)
            points = np.insert(points, where - np.arange(len(where)), unstored, axis=0)
        points[:, :3] = carla.points_right_handed(points[:, :3])
        return points.astype(np.float32, copy=False)

    def lidar_pose(self, agent_id: str, key: str) -> np.ndarray:
        """The YAML's ``lidar_pose`` of the frame: the lidar's CARLA world pose, float64 [6]
        (x, y, z m; roll, yaw, pitch deg), under this view's poses."""
        opened = self._sequence(agent_id)
        lidar_id = self._name(agent_id, LIDAR)
        t_us = self._lidar(agent_id).frames_timestamps_us[self._frame(agent_id, key), 1:2]
        T_lidar_world_global = sensor_poses(opened.loader, lidar_id, "world_global", t_us)[0]
        return carla.carla_pose_from_matrix(carla.mirror_transform(T_lidar_world_global))

    def params(self, agent_id: str, key: str) -> dict:
        """The frame's YAML as OpenCOOD loads it (a dict; ``vehicles`` keyed by actor id), with
        ``lidar_pose`` the noise setting's (:meth:`lidar_pose`) when the view has one."""
        params = parse_yaml(self.stored_yaml_text(agent_id, key), f"{self.manifest_path} agent {agent_id} frame {key}")
        if self.poses is not None:
            params["lidar_pose"] = [float(v) for v in self.lidar_pose(agent_id, key)]
        return params

    def pcd_layout(self, agent_id: str, key: str) -> str:
        """The frame's PCD layout as the converter read it, e.g. ``"x y z rgb ascii"`` (conversions
        before it was stored: OPV2V's own, that one)."""
        meta = self._lidar(agent_id).get_frame_generic_meta_data(self._frame(agent_id, key))
        return meta.get(PCD_LAYOUT, "x y z rgb ascii")

    def stored_yaml_text(self, agent_id: str, key: str) -> str:
        """The frame's ``<key>.yaml`` as the converter read it."""
        return self._lidar(agent_id).get_frame_generic_meta_data(self._frame(agent_id, key))[OPENCOOD_YAML]

    def images(self, agent_id: str, key: str) -> dict[int, bytes]:
        """The frame's camera PNGs by OpenCOOD camera index (``<key>_camera<index>.png``), as stored."""
        opened = self._sequence(agent_id)
        t_us = self._lidar(agent_id).frames_timestamps_us[self._frame(agent_id, key), 1]
        out = {}
        for index, camera in enumerate(CAMERAS):
            name = self._name(agent_id, camera)
            if name not in opened.loader.camera_ids:
                continue
            sensor = opened.loader.get_camera_sensor(name)
            frames = np.flatnonzero(sensor.frames_timestamps_us[:, 1] == t_us)
            if len(frames):
                out[index] = sensor.get_frame_data(int(frames[0])).get_encoded_image_data()
        return out

    def delayed_key(self, agent_id: str, ego_key: str) -> str | None:
        """The agent's key that OpenCOOD's ``async`` reads at the ego's frame ``ego_key`` under this
        view's noise setting (``ego_key`` itself without one; None where the setting has no data
        from the agent for that frame)."""
        if self.poses is None:
            return ego_key
        if agent_id not in self._delays:
            data = self._sequence(agent_id).reader.open_component_readers(PosesComponent.Reader)[self._poses_instance]
            prefix = self.manifest.prefix_of(self._agent(agent_id)) or ""
            self._delays[agent_id] = (
                data.get_generic_data(f"{prefix}delay_ego_timestamps_us"),
                data.get_generic_data(f"{prefix}delay_source_keys"),
            )
        ego_times_us, source_keys = self._delays[agent_id]
        t_us = self._lidar(self.ego_agent_id).frames_timestamps_us[self._frame(self.ego_agent_id, ego_key), 1]
        where = np.flatnonzero(ego_times_us == t_us)
        if not len(where):
            raise KeyError(f"{self.manifest_path}: noise setting {self.poses!r} has no delay at ego frame {ego_key}")
        source = int(source_keys[where[0]])
        return None if source < 0 else f"{source:06d}"

    def base_data(self, ego_key: str) -> dict[str, dict]:
        """What OpenCOOD's ``BaseDataset.retrieve_base_data`` builds at the ego's frame ``ego_key``,
        per agent in OpenCOOD's order: ``ego`` (bool), ``time_delay`` (frames behind, from the
        setting's delays), ``params`` (the delayed frame's YAML, :meth:`params`), ``lidar_np``
        (:meth:`lidar_points` of that frame) and ``camera_png`` (its PNGs by camera index). Agents
        with no frame to send at ``ego_key`` are left out."""
        ego_keys = self.keys(self.ego_agent_id)
        return {
            agent_id: {
                "ego": agent_id == self.ego_agent_id,
                "time_delay": ego_keys.index(ego_key) - ego_keys.index(key) if key in ego_keys else 0,
                "params": self.params(agent_id, key),
                "lidar_np": self.lidar_points(agent_id, key),
                "camera_png": self.images(agent_id, key),
            }
            for agent_id, key in self._sent_frames(ego_key)
        }

    def _sent_frames(self, ego_key: str) -> list[tuple[str, str]]:
        """(agent, the key it sends at ``ego_key``) in OpenCOOD's order, for the agents that send one."""
        pairs = [(agent_id, self.delayed_key(agent_id, ego_key)) for agent_id in self.opencood_order]
        return [(agent_id, key) for agent_id, key in pairs if key is not None and key in self._lidar_keys(agent_id)]

    def cooperative_points(self, ego_key: str, comm_range_m: float = 70.0) -> np.ndarray:
        """The ego frame ``ego_key``'s cooperative cloud as OpenCOOD's early fusion builds it: every
        agent within ``comm_range_m`` of the ego (horizontal distance of the ``lidar_pose``s) with
        its points (the delayed frame under a noise setting) moved into the ego's CARLA lidar frame by
        ``inv(T(ego lidar_pose)) · T(agent lidar_pose)``, the ego first, then OpenCOOD's order;
        float32 [N,4] (x, y, z m; intensity)."""
        ego_pose = self.lidar_pose(self.ego_agent_id, ego_key)
        T_world_ego = np.linalg.inv(carla.carla_pose_matrix(ego_pose))
        parts = []
        for agent_id, key in self._sent_frames(ego_key):  # base_data without the PNGs
            pose = np.asarray(self.params(agent_id, key)["lidar_pose"], dtype=np.float64)
            if np.hypot(pose[0] - ego_pose[0], pose[1] - ego_pose[1]) > comm_range_m:
                continue
            points = self.lidar_points(agent_id, key)
            T = T_world_ego @ carla.carla_pose_matrix(pose)
            xyz = points[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
            parts.append(np.concatenate([xyz, points[:, 3:4]], axis=1).astype(np.float32))
        return np.concatenate(parts) if parts else np.zeros((0, 4), dtype=np.float32)

    @property
    def opencood_order(self) -> list[str]:
        """The written agents in the order OpenCOOD loads them (its ego first)."""
        return opencood_order(self.agent_ids)

    @property
    def protocol_text(self) -> str | None:
        """The scenario's ``data_protocol.yaml``, as it was (None: the scenario had none)."""
        return self._sequence(self.agent_ids[0]).loader.generic_meta_data[OPENCOOD_PROTOCOL]

    # -- where an agent's data is

    def _lidar(self, agent_id: str):
        if agent_id not in self._lidars:  # opening one decodes its model parameters (about 1 ms)
            self._lidars[agent_id] = self._sequence(agent_id).loader.get_lidar_sensor(self._name(agent_id, LIDAR))
        return self._lidars[agent_id]

    def _agent(self, agent_id: str) -> ManifestAgent:
        for agent in self.manifest.agents:
            if str(agent.agent_id) == str(agent_id) and agent.written:
                return agent
        raise KeyError(f"{self.manifest_path}: no written agent {agent_id!r} (agents: {', '.join(self.agent_ids)})")

    def _name(self, agent_id: str, sensor_id: str) -> str:
        return f"{self.manifest.prefix_of(self._agent(agent_id)) or ''}{sensor_id}"

    def _sequence(self, agent_id: str) -> OpenSequence:
        path = self.manifest.sequence_of(self._agent(agent_id))
        if path not in self._sequences:
            self._sequences[path] = open_sequence(self.manifest_path.parent / path, self._poses_instance)
        return self._sequences[path]

    def _lidar_keys(self, agent_id: str) -> dict[str, int]:
        """key -> frame index of the agent's lidar."""
        if agent_id not in self._keys:
            lidar = self._lidar(agent_id)
            self._keys[agent_id] = {
                f"{int(lidar.get_frame_generic_meta_data(i)[CARLA_FRAME]):06d}": i for i in range(lidar.frames_count)
            }
        return self._keys[agent_id]

    def _frame(self, agent_id: str, key: str) -> int:
        try:
            return self._lidar_keys(agent_id)[key]
        except KeyError:
            raise KeyError(f"{self.manifest_path}: agent {agent_id} has no lidar frame {key!r}") from None
