"""Poses as a written sequence holds them: the one place the read side evaluates NCore's pose graph
(``pose_graph.evaluate_poses(a, b, t)`` returns ``T_a_b`` at ``t``). The validators, the preview and
the read-back views take every sensor, rig and reference-frame pose from here."""

from __future__ import annotations

import numpy as np
from ncore.data.v4 import SequenceLoaderV4

from ncore_convert.contract import WORLD_GLOBAL


def world_global_edge(loader: SequenceLoaderV4) -> np.ndarray:
    """The stored static ``world -> world_global`` edge, float64 [4,4]."""
    return loader.pose_graph.evaluate_poses("world", "world_global", np.zeros(1, dtype=np.uint64))[0].astype(np.float64)


def T_world_dataset_global(loader: SequenceLoaderV4) -> np.ndarray:
    """world -> the dataset's global frame, float64 [4,4]: the ``world -> world_global`` edge, which
    consumers read, unless ``--world-global-mode`` stored something else there (identity, or no edge);
    then the sequence metadata's record of it."""
    record = loader.generic_meta_data.get(WORLD_GLOBAL)
    if isinstance(record, dict) and record.get("mode", "localized") != "localized":
        return np.asarray(record["T_world_dataset_global"], dtype=np.float64)
    return world_global_edge(loader)


def sensor_poses(loader: SequenceLoaderV4, sensor_id: str, target: str, timestamps_us: np.ndarray) -> np.ndarray:
    """``T_sensor_target`` at ``timestamps_us`` (uint64 [T]), float64 [T,4,4]; ``target`` ``world``, or
    ``world_global`` meaning the dataset's global frame (:func:`T_world_dataset_global`)."""
    t_us = np.asarray(timestamps_us, dtype=np.uint64)
    T_sensor_world = loader.pose_graph.evaluate_poses(sensor_id, "world", t_us).astype(np.float64)
    return T_world_dataset_global(loader)[None] @ T_sensor_world if target == "world_global" else T_sensor_world


def lever_arm_m(loader: SequenceLoaderV4, sensor_ids) -> float:
    """The largest distance of the sensors from the rig origin (their static ``T_sensor_rig``), metres."""
    return max(
        float(np.linalg.norm(loader.pose_graph.evaluate_poses(s, "rig", np.zeros(1, dtype=np.uint64))[0][:3, 3]))
        for s in sensor_ids
    )
