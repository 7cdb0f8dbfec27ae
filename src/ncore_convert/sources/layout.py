"""What a dataset folder holds, told from a listing or two: an Argoverse 2 log, a split or dataset
root of logs, an OPV2V/V2XSet scenario, split or root. The command line uses it to name the fix
when ``--root-dir`` is not what the command reads (the split folder given as the root, another
dataset's tree); the readers themselves know only their own layout.

Every function lists at most three folders (local: ``os.scandir``; remote: one request each).
"""

from __future__ import annotations

import re

from upath import UPath

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import opencood as ocd
from ncore_convert.sources.reader import Reader, reading

_TBV_LOG = re.compile(r"__[A-Za-z]+_\d{4}$")  #: TbV log ids end in ``__<Season>_<Year>``

#: What :func:`kind_of` tells apart.
AV2_LOG, AV2_LOGS, AV2_SPLITS = "an Argoverse 2 log", "a folder of Argoverse 2 logs", "an Argoverse 2 Sensor root"
SCENARIO, SCENARIOS, OPENCOOD_SPLITS = (
    "an OPV2V/V2XSet scenario",
    "an OPV2V/V2XSet split folder",
    "an OPV2V/V2XSet root",
)


def _is_av2_log(folder: UPath, r: Reader) -> bool:
    """The poses table every Argoverse 2 (Sensor or TbV) log folder holds."""
    return av2.poses_path(folder).name in r.file_names(folder)


def _is_scenario(folder: UPath, r: Reader) -> bool:
    """Agent folders (CARLA actor ids) or the scenario's protocol file (not every scenario has one)."""
    agents = r.folder_names(folder, None)
    has_protocol = ocd.protocol_path(folder).name in r.file_names(folder)
    return (bool(agents) and all(ocd.is_agent_id(a) for a in agents)) or has_protocol


def kind_of(folder: UPath, reader: Reader | None = None) -> tuple[str | None, str | None]:
    """What ``folder`` is (one of the module's kinds; None: nothing recognised, missing, empty or
    another layout), told from it and its first subfolders; and the name of its first subfolder."""
    folder = UPath(folder)
    with reading(reader) as r:
        if _is_av2_log(folder, r):
            return AV2_LOG, None
        if _is_scenario(folder, r):
            return SCENARIO, None
        children = r.folder_names(folder, None)
        if not children:
            return None, None
        first = folder / children[0]
        if _is_av2_log(first, r):
            return AV2_LOGS, children[0]
        if _is_scenario(first, r):
            return SCENARIOS, children[0]
        grandchildren = r.folder_names(first, None)
        if grandchildren and _is_av2_log(first / grandchildren[0], r):
            return AV2_SPLITS, children[0]
        if grandchildren and _is_scenario(first / grandchildren[0], r):
            return OPENCOOD_SPLITS, children[0]
    return None, children[0]


def is_tbv_log_id(name: str) -> bool:
    """A TbV log id (``<hash>__<Season>_<Year>``), not an Argoverse 2 Sensor one (a UUID)."""
    return bool(_TBV_LOG.search(name))
