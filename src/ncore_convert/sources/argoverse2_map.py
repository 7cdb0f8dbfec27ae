"""A log's HD map as stored (AV2 Sensor and TbV share the format): the vector map, the ground-height
raster and its Sim(2) to the city frame, read and checked, not interpreted."""

from __future__ import annotations

import io
import json
from dataclasses import dataclass

import numpy as np
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.files import read_bytes

VECTOR_MAP_KEYS = ("pedestrian_crossings", "lane_segments", "drivable_areas")


@dataclass(frozen=True)
class LogMap:
    """A log's HD map files as stored, all in the city frame.

    Attributes:
        vector_map_json: bytes of ``log_map_archive_*.json`` (lane segments, drivable areas,
            pedestrian crossings; points in city metres).
        ground_height_m: ``*_ground_height_surface____*.npy``, float16 [H,W], city z in metres,
            NaN outside the region of interest.
        img_Sim2_city: ``*___img_Sim2_city.json``: {"R": [4] row-major 2x2, "t": [2], "s": float};
            p_img = s * (R @ p_city_xy + t); raster cell = (row, col) = (int(p_img.y), int(p_img.x)).
        file_names: the three file names (vector map, raster, Sim(2)), which carry the city code.
    """

    vector_map_json: bytes
    ground_height_m: np.ndarray
    img_Sim2_city: dict
    file_names: tuple[str, str, str]


def _one(map_dir: UPath, pattern: str) -> UPath:
    found = sorted(map_dir.glob(pattern))
    if len(found) != 1:
        raise SourceError(map_dir, f"expected exactly one {pattern}, found {len(found)}")
    return found[0]


def read_log_map(log_dir: UPath) -> LogMap | None:
    """The log's HD map (None when the log has no ``map`` folder). Raises SourceError on bad files."""
    map_dir = log_dir / "map"
    if not map_dir.is_dir():
        return None
    vector_path = _one(map_dir, "log_map_archive_*.json")
    raster_path = _one(map_dir, "*_ground_height_surface____*.npy")
    sim2_path = _one(map_dir, "*___img_Sim2_city.json")
    vector_json = read_bytes(vector_path)
    try:
        vector = json.loads(vector_json)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SourceError(vector_path, f"not JSON ({err})") from None
    if not isinstance(vector, dict) or any(key not in vector for key in VECTOR_MAP_KEYS):
        raise SourceError(vector_path, f"a vector map needs the keys {list(VECTOR_MAP_KEYS)}")
    try:
        raster = np.load(io.BytesIO(read_bytes(raster_path)), allow_pickle=False)
    except (ValueError, OSError) as err:
        raise SourceError(raster_path, f"not a .npy array ({err})") from None
    if raster.dtype != np.float16 or raster.ndim != 2:
        raise SourceError(raster_path, f"expected a 2-D float16 raster, got {raster.dtype} {raster.shape}")
    try:
        sim2 = json.loads(read_bytes(sim2_path))
        ok = len(sim2["R"]) == 4 and len(sim2["t"]) == 2 and float(sim2["s"]) > 0
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as err:
        raise SourceError(sim2_path, f"not a Sim(2) JSON with R, t, s ({err})") from None
    if not ok:
        raise SourceError(sim2_path, "Sim(2) needs R with 4 values, t with 2 and s > 0")
    return LogMap(vector_json, raster, sim2, (vector_path.name, raster_path.name, sim2_path.name))
