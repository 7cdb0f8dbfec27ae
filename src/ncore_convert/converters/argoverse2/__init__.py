"""Argoverse 2 Sensor (``argoverse2-v4``) and TbV (``tbv-v4``), one log per sequence.

``plan.py`` reads a log's small inputs and decides everything once; ``lidar.py`` splits the units,
derives their models and times their points; ``convert.py`` writes the planned log.
"""

from __future__ import annotations

from upath import UPath

from ncore_convert.converters.argoverse2.convert import LogSummary, convert_log
from ncore_convert.converters.argoverse2.plan import Argoverse2Options
from ncore_convert.converters.common import Dataset, select_sensors
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import tbv

__all__ = ["DATASETS", "Argoverse2Options", "LogSummary", "convert_log"]


def _check_sensors(options: Argoverse2Options) -> None:
    select_sensors(options.camera_ids, av2.RING_CAMERAS if options.tbv else av2.CAMERAS, "camera")
    select_sensors(options.lidar_ids, av2.LIDARS, "lidar")


def _ids_dir(root: UPath, options: Argoverse2Options) -> UPath:
    return root if options.tbv else root / options.split


def _list_logs(root: UPath, options: Argoverse2Options) -> list[str]:
    return tbv.list_log_ids(root) if options.tbv else av2.list_log_ids(root, options.split)


def _log_dir(root: UPath, options: Argoverse2Options, log_id: str) -> UPath:
    return options.log_dir(root, log_id)


_DATASET = Dataset(Argoverse2Options, "log", _ids_dir, _list_logs, _log_dir, _check_sensors, convert_log)
DATASETS = {"argoverse2-v4": _DATASET, "tbv-v4": _DATASET}
