"""The per-point data of a lidar frame, whatever the dataset: each stored ray's ``dynamic_flag`` and
``rgb``, from its point where the lidar saw it (in a fixed frame) at its own time.

Every converter hands its frames' stored rays here: AV2/TbV both units of a sweep together (each
unit's points may hide the other's from a camera), OPV2V/V2XSet an agent's one lidar. The flags come
first: a point on a moving object takes its colour only from a camera frame close to its time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ncore_convert.contract import DYNAMIC_FLAG, LIDAR_RGB
from ncore_convert.transforms.dynamic import DynamicBoxes, dynamic_flags

#: ``(xyz_fixed_m [N,3], timestamps_us int64 [N], dynamic bool [N]) -> (rgb uint8 [N,3], coloured bool [N])``
Colouring = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass
class PointData:
    """What :func:`point_data` made of one frame.

    Attributes:
        generic: lidar -> its rays' per-point generic data (``dynamic_flag`` int8 [N] with boxes,
            ``rgb`` uint8 [N,3] with a colouring).
        coloured: lidar -> how many of its points a camera coloured.
        flag_seconds, colour_seconds: the time each took (benchmark figures).
    """

    generic: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    coloured: dict[str, int] = field(default_factory=dict)
    flag_seconds: float = 0.0
    colour_seconds: float = 0.0


def point_data(
    xyz_fixed_m: dict[str, np.ndarray],
    timestamps_us: dict[str, np.ndarray],
    boxes: DynamicBoxes | None,
    colouring: Colouring | None,
) -> PointData:
    """Each stored ray's ``dynamic_flag`` (with ``boxes``) and ``rgb`` (with a ``colouring``), per lidar.

    Args:
        xyz_fixed_m: lidar -> its rays' points where the lidar saw them, in the boxes' and cameras'
            fixed frame, float64 [N,3] (one row per stored ray, in ray order).
        timestamps_us: lidar -> each ray's own time, µs [N].
        boxes: the dynamic tracks (None: no ``dynamic_flag``).
        colouring: colours the frame's points of all lidars together (None: no ``rgb``).
    """
    out = PointData({lidar: {} for lidar in xyz_fixed_m})
    lidars = list(xyz_fixed_m)
    if not lidars:
        return out
    xyz = np.concatenate([xyz_fixed_m[lidar] for lidar in lidars])
    times_us = np.concatenate([np.asarray(timestamps_us[lidar]).astype(np.int64) for lidar in lidars])
    bounds = np.cumsum([0] + [len(xyz_fixed_m[lidar]) for lidar in lidars])
    parts = list(zip(lidars, bounds[:-1], bounds[1:], strict=True))
    dynamic = np.zeros(len(xyz), bool)
    if boxes is not None:
        started = time.perf_counter()
        flags = dynamic_flags(xyz, times_us, boxes)
        out.flag_seconds = time.perf_counter() - started
        dynamic = flags == 1
        for lidar, a, b in parts:
            out.generic[lidar][DYNAMIC_FLAG] = flags[a:b]
    if colouring is not None:
        started = time.perf_counter()
        rgb, coloured = colouring(xyz, times_us, dynamic)
        out.colour_seconds = time.perf_counter() - started
        for lidar, a, b in parts:
            out.generic[lidar][LIDAR_RGB] = rgb[a:b]
            out.coloured[lidar] = int(coloured[a:b].sum())
    return out
