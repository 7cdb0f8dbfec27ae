"""OPV2V (``opv2v-v4``) and V2XSet (``v2xset-v4``), one scenario at a time.

``plan.py`` reads every agent's YAMLs once and decides trajectories, calibration and labels;
``noise.py`` applies the GPS-error and delay settings to the planned agents; ``convert.py`` writes
the sequences and ``scenario.json``.
"""

from __future__ import annotations

from upath import UPath

from ncore_convert.converters.common import Dataset, select_sensors
from ncore_convert.converters.opencood.convert import ScenarioSummary, convert_scenario
from ncore_convert.converters.opencood.records import AgentPlan, OpenCoodOptions
from ncore_convert.sources import opencood as src

__all__ = ["DATASETS", "AgentPlan", "OpenCoodOptions", "ScenarioSummary", "convert_scenario"]


def _check_sensors(options: OpenCoodOptions) -> None:
    select_sensors(options.camera_ids, src.CAMERAS, "camera")
    select_sensors(options.lidar_ids, (src.LIDAR,), "lidar")


def _ids_dir(root: UPath, options: OpenCoodOptions) -> UPath:
    return root / options.split


def _list_scenarios(root: UPath, options: OpenCoodOptions) -> list[str]:
    return src.list_scenarios(root, options.split)


def _scenario_dir(root: UPath, options: OpenCoodOptions, scenario: str) -> UPath:
    return options.scenario_dir(root, scenario)


_DATASET = Dataset(
    OpenCoodOptions, "scenario", _ids_dir, _list_scenarios, _scenario_dir, _check_sensors, convert_scenario
)
DATASETS = {"opv2v-v4": _DATASET, "v2xset-v4": _DATASET}
