"""A log's HD map as stored (AV2 Sensor and TbV share the format): the vector map, the ground-height
raster and its Sim(2) to the city frame, read and checked, not interpreted."""

from __future__ import annotations

import fnmatch
import io
import json
from dataclasses import dataclass

import numpy as np
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.reader import Reader, reading

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


def _one(map_dir: UPath, names: list[str], pattern: str) -> UPath:
    found = sorted(name for name in names if fnmatch.fnmatchcase(name, pattern))
    if len(found) != 1:
        raise SourceError(map_dir, f"expected exactly one {pattern}, found {len(found)}")
    return map_dir / found[0]


def read_log_map(log_dir: UPath, reader: Reader | None = None) -> LogMap | None:
    """The log's HD map (None when the log has no ``map`` folder): one listing of the folder and
    one read per file, through ``reader``. Raises SourceError on bad files."""
    map_dir = log_dir / "map"
    with reading(reader) as r:
        listing: dict = {}
        names = r.file_names(map_dir, listing)
        if not names:
            return None
        vector_path = _one(map_dir, names, "log_map_archive_*.json")
        raster_path = _one(map_dir, names, "*_ground_height_surface____*.npy")
        sim2_path = _one(map_dir, names, "*___img_Sim2_city.json")
        vector_json, raster_npy, sim2_json = (r.read(p, listing) for p in (vector_path, raster_path, sim2_path))
    return _checked_map(vector_path, vector_json, raster_path, raster_npy, sim2_path, sim2_json)


def _checked_map(
    vector_path: UPath, vector_json: bytes, raster_path: UPath, raster_npy: bytes, sim2_path: UPath, sim2_json: bytes
) -> LogMap:
    try:
        vector = json.loads(vector_json)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SourceError(vector_path, f"not JSON ({err})") from None
    if not isinstance(vector, dict) or any(key not in vector for key in VECTOR_MAP_KEYS):
        raise SourceError(vector_path, f"a vector map needs the keys {list(VECTOR_MAP_KEYS)}")
    try:
        raster = np.load(io.BytesIO(raster_npy), allow_pickle=False)
    except (ValueError, OSError) as err:
        raise SourceError(raster_path, f"not a .npy array ({err})") from None
    if raster.dtype != np.float16 or raster.ndim != 2:
        raise SourceError(raster_path, f"expected a 2-D float16 raster, got {raster.dtype} {raster.shape}")
    try:
        sim2 = json.loads(sim2_json)
        ok = len(sim2["R"]) == 4 and len(sim2["t"]) == 2 and float(sim2["s"]) > 0
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as err:
        raise SourceError(sim2_path, f"not a Sim(2) JSON with R, t, s ({err})") from None
    if not ok:
        raise SourceError(sim2_path, "Sim(2) needs R with 4 values, t with 2 and s > 0")
    return LogMap(vector_json, raster, sim2, (vector_path.name, raster_path.name, sim2_path.name))
