"""Cuboid class names and label sources, as NCore's consumers expect them (docs/consumers.md).

NCore's own converters write lowercase class names (the Argoverse 2 converter maps AV2's categories
with the table below); instant-nurec and 3DGRUT recognise dynamic classes by those names. The
dataset's own name of every track stays recoverable: the writer stores it per track in the cuboids
component's metadata (``contract.SOURCE_CLASS_BY_TRACK``).
"""

from __future__ import annotations

from ncore_convert.contract import ClassNames, CuboidLabelSource

#: Argoverse 2 category -> NCore class name (NCore's Argoverse 2 converter, v19.5).
AV2_TO_NCORE = {
    "REGULAR_VEHICLE": "car",
    "LARGE_VEHICLE": "truck",
    "BOX_TRUCK": "truck",
    "TRUCK": "truck",
    "TRUCK_CAB": "truck",
    "VEHICULAR_TRAILER": "trailer",
    "MESSAGE_BOARD_TRAILER": "trailer",
    "TRAFFIC_LIGHT_TRAILER": "trailer",
    "SCHOOL_BUS": "bus",
    "ARTICULATED_BUS": "bus",
    "BUS": "bus",
    "RAILED_VEHICLE": "vehicle",
    "MOTORCYCLE": "motorcycle",
    "MOTORCYCLIST": "motorcyclist",
    "BICYCLE": "bicycle",
    "BICYCLIST": "bicyclist",
    "BOLLARD": "bollard",
    "WHEELED_DEVICE": "wheeled_device",
    "WHEELED_RIDER": "wheeled_rider",
    "PEDESTRIAN": "pedestrian",
    "OFFICIAL_SIGNALER": "pedestrian",
    "STROLLER": "stroller",
    "WHEELCHAIR": "wheelchair",
    "DOG": "animal",
    "ANIMAL": "animal",
    "CONSTRUCTION_CONE": "traffic_cone",
    "CONSTRUCTION_BARREL": "barrier",
    "STOP_SIGN": "stop_sign",
    "SIGN": "sign",
    "MOBILE_PEDESTRIAN_CROSSING_SIGN": "sign",
}

#: OPV2V / V2XSet label every actor as a vehicle; CARLA's vehicles are cars.
OPENCOOD_TO_NCORE = {"vehicle": "car"}

#: NCore classes that are dynamic whatever their speed (they move on their own at any moment).
ALWAYS_DYNAMIC = frozenset(
    {"pedestrian", "bicyclist", "motorcyclist", "wheeled_rider", "stroller", "wheelchair", "animal"}
)
#: NCore classes that never move: never dynamic, whatever their boxes do.
ALWAYS_STATIC = frozenset({"sign", "stop_sign", "traffic_cone", "barrier", "bollard"})

#: ``--cuboid-label-source`` -> NCore ``LabelSource`` member name (``auto``: the dataset's honest one).
LABEL_SOURCES = {"external": "EXTERNAL", "gt-synthetic": "GT_SYNTHETIC", "autolabel": "AUTOLABEL"}


def label_source(option: CuboidLabelSource, dataset_default: str) -> str:
    """The NCore ``LabelSource`` name for ``--cuboid-label-source`` (``dataset_default`` for auto)."""
    return dataset_default if option == "auto" else LABEL_SOURCES[option]


def ncore_classes(source_names: list[str], table: dict[str, str]) -> tuple[list[str], list[str]]:
    """Map dataset class names to NCore's; a name outside ``table`` is kept as it is.

    Returns:
        the NCore (or kept) name of each input, and the sorted names that had no mapping.
    """
    mapped = [table.get(name, name) for name in source_names]
    return mapped, sorted({name for name in source_names if name not in table})


def output_classes(
    source_names: list[str], table: dict[str, str], mode: ClassNames
) -> tuple[list[str], list[str], list[str]]:
    """The class names written for ``--class-names`` ``mode``, the NCore names (which the dynamic rule
    reads, whatever is written), and the source names outside the table."""
    mapped, unmapped = ncore_classes(source_names, table)
    return (mapped if mode == "ncore" else list(source_names)), mapped, unmapped
