"""A converted cooperative scenario (OPV2V, V2XSet) read back as OpenCOOD reads its raw files.

OpenCOOD and the frameworks built on it read ``<scenario>/<agent>/<key>.pcd|.yaml``. This view gives
the same values from the NCore sequences of a ``scenario.json`` (either layout), per frame key and
agent, in CARLA's conventions (left-handed frames; poses ``[x, y, z, roll, yaw, pitch]`` in metres
and degrees):

- :meth:`OpenCoodScenario.lidar_points`: what OpenCOOD's PCD reader returns, ``[N,4]`` x, y, z,
  intensity in the agent's lidar frame, in the PCD's point order (points at zero range were not
  stored by the converter and are not returned);
- :meth:`OpenCoodScenario.lidar_pose`: the YAML's ``lidar_pose``, from the sequence's pose graph
  (the ground truth, or the poses instance of a stored noise setting: OpenCOOD's ``loc_err``).

It reads NCore only (through ``validate.readback``) and imports nothing of the converters.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from upath import UPath

from ncore_convert.contract import CARLA_FRAME, DEFAULT_INSTANCE, ManifestAgent, ScenarioManifest
from ncore_convert.sources.opencood import LIDAR
from ncore_convert.transforms import carla
from ncore_convert.validate.readback import OpenSequence, open_sequence, read_manifest, sensor_poses

@dataclass
class OpenCoodScenario:
    """The converted scenario of ``manifest_path`` (its ``scenario.json``), read with the poses of
    ``poses`` (None: the ground truth; else a noise setting's name in the manifest)."""

    manifest_path: UPath
    poses: str | None = None
    _sequences: dict[str, OpenSequence] = field(default_factory=dict, repr=False)
    _keys: dict[str, dict[str, int]] = field(default_factory=dict, repr=False)  #: agent -> key -> lidar frame

    @classmethod
    def open(cls, manifest_path: UPath | str, poses: str | None = None) -> OpenCoodScenario:
        scenario = cls(UPath(manifest_path), poses)
        if poses is not None and poses not in {n.name for n in scenario.manifest.noise_settings}:
            known = ", ".join(n.name for n in scenario.manifest.noise_settings) or "none"
            raise ValueError(f"{manifest_path}: no noise setting {poses!r} (stored: {known})")
        return scenario

    @cached_property
    def manifest(self) -> ScenarioManifest:
        return read_manifest(self.manifest_path)

    @property
    def ego_agent_id(self) -> str:
        """The agent OpenCOOD takes as its ego (its folder name)."""
        return str(self.manifest.ego_agent_id)

    @property
    def agent_ids(self) -> list[str]:
        """The written agents' folder names, in the manifest's order."""
        return [str(a.agent_id) for a in self.manifest.agents if a.written]

    def keys(self, agent_id: str) -> list[str]:
        """The agent's frame keys (6-digit CARLA frame counters) that have a lidar frame."""
        return list(self._lidar_keys(agent_id))

    def lidar_points(self, agent_id: str, key: str) -> np.ndarray:
        """The frame's points as OpenCOOD's PCD reader returns them: float32 [N,4], x, y, z in the
        agent's CARLA (left-handed) lidar frame in metres, and intensity in [0, 1]."""
        lidar = self._sequence(agent_id).loader.get_lidar_sensor(self._name(agent_id, LIDAR))
        frame = self._frame(agent_id, key)
        direction = lidar.get_frame_ray_bundle_direction(frame).astype(np.float64)
        distance_m = lidar.get_frame_ray_bundle_return_distance_m(frame).astype(np.float64)
        xyz_carla = carla.points_right_handed(direction * distance_m[:, None])
        intensity = lidar.get_frame_ray_bundle_return_intensity(frame)
        return np.concatenate([xyz_carla, intensity[:, None]], axis=1).astype(np.float32)

    def lidar_pose(self, agent_id: str, key: str) -> np.ndarray:
        """The YAML's ``lidar_pose`` of the frame: the lidar's CARLA world pose, float64 [6]
        (x, y, z m; roll, yaw, pitch deg), under this view's poses."""
        opened = self._sequence(agent_id)
        lidar_id = self._name(agent_id, LIDAR)
        t_us = opened.loader.get_lidar_sensor(lidar_id).frames_timestamps_us[self._frame(agent_id, key), 1:2]
        T_lidar_world_global = sensor_poses(opened.loader, lidar_id, "world_global", t_us)[0]
        return carla.carla_pose_from_matrix(carla.mirror_transform(T_lidar_world_global))

    # -- where an agent's data is

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
            instance = DEFAULT_INSTANCE
            if self.poses is not None:
                instance = next(n.poses_instance for n in self.manifest.noise_settings if n.name == self.poses)
            self._sequences[path] = open_sequence(self.manifest_path.parent / path, instance)
        return self._sequences[path]

    def _lidar_keys(self, agent_id: str) -> dict[str, int]:
        """key -> frame index of the agent's lidar."""
        if agent_id not in self._keys:
            lidar = self._sequence(agent_id).loader.get_lidar_sensor(self._name(agent_id, LIDAR))
            self._keys[agent_id] = {
                f"{int(lidar.get_frame_generic_meta_data(i)[CARLA_FRAME]):06d}": i for i in range(lidar.frames_count)
            }
        return self._keys[agent_id]

    def _frame(self, agent_id: str, key: str) -> int:
        try:
            return self._lidar_keys(agent_id)[key]
        except KeyError:
            raise KeyError(f"{self.manifest_path}: agent {agent_id} has no lidar frame {key!r}") from None
