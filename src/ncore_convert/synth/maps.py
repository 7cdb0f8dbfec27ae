"""A synthetic per-log HD map in the AV2 map format (vector map, ground-height raster, Sim(2)).

Lanes follow the ego path; the raster holds the scene's flat ground within the region of interest
(here: 20 m of the path) and NaN elsewhere, at AV2's 30 cm resolution.
"""

from __future__ import annotations

import io
import json

import numpy as np
from scipy.spatial import cKDTree
from upath import UPath

from ncore_convert.synth.scene import GROUND_Z_M, Scene

CITIES = ("ATX", "DTW", "MIA", "PAO", "PIT", "WDC")
RESOLUTION_M = 0.3
ROI_M = 20.0
LANE_HALF_WIDTH_M = 1.75
SEGMENT_LENGTH_M = 20.0


def _point(xy: np.ndarray) -> dict:
    return {"x": round(float(xy[0]), 2), "y": round(float(xy[1]), 2), "z": round(GROUND_Z_M, 2)}


def vector_map(path_xy: np.ndarray, heading_rad: np.ndarray) -> dict:
    """Lane segments along the path (one lane, split every SEGMENT_LENGTH_M), the drivable area
    around it and one pedestrian crossing; keys and field order as in AV2's map archives."""
    left = np.stack([-np.sin(heading_rad), np.cos(heading_rad)], axis=1)
    step = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path_xy, axis=0), axis=1))]
    cuts = np.searchsorted(step, np.arange(0.0, step[-1] + SEGMENT_LENGTH_M, SEGMENT_LENGTH_M))
    cuts = np.unique(np.clip(cuts, 0, len(path_xy) - 1))
    lanes = {}
    for k, (a, b) in enumerate(zip(cuts[:-1], cuts[1:], strict=True)):
        seg_id = 1000 + k
        lanes[str(seg_id)] = {
            "id": seg_id,
            "is_intersection": False,
            "lane_type": "VEHICLE",
            "left_lane_boundary": [_point(p) for p in path_xy[a : b + 1] + LANE_HALF_WIDTH_M * left[a : b + 1]],
            "left_lane_mark_type": "DASHED_WHITE",
            "right_lane_boundary": [_point(p) for p in path_xy[a : b + 1] - LANE_HALF_WIDTH_M * left[a : b + 1]],
            "right_lane_mark_type": "SOLID_WHITE",
            "successors": [seg_id + 1] if b != cuts[-1] else [],
            "predecessors": [seg_id - 1] if k else [],
            "right_neighbor_id": None,
            "left_neighbor_id": None,
        }
    boundary = np.r_[path_xy + 8.0 * left, (path_xy - 8.0 * left)[::-1]]
    mid = len(path_xy) // 2
    crossing = [path_xy[mid] + s * 8.0 * left[mid] for s in (-1, 1)]
    along = np.array([np.cos(heading_rad[mid]), np.sin(heading_rad[mid])]) * 2.0
    return {
        "pedestrian_crossings": {
            "1": {"edge1": [_point(p) for p in crossing], "edge2": [_point(p + along) for p in crossing], "id": 1}
        },
        "lane_segments": lanes,
        "drivable_areas": {"2": {"area_boundary": [_point(p) for p in boundary[::4]], "id": 2}},
    }


def ground_raster(path_xy: np.ndarray) -> tuple[np.ndarray, dict]:
    """Ground height (float16 [H,W], NaN beyond ROI_M of the path) and its img_Sim2_city."""
    lo = np.floor((path_xy.min(axis=0) - ROI_M - 1.0) / RESOLUTION_M) * RESOLUTION_M
    hi = path_xy.max(axis=0) + ROI_M + 1.0
    shape = np.ceil((hi - lo) / RESOLUTION_M).astype(int)[::-1]  # rows (y), cols (x)
    rows, cols = np.mgrid[0 : shape[0], 0 : shape[1]]
    cell_xy = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=1) * RESOLUTION_M + lo
    distance, _ = cKDTree(path_xy).query(cell_xy, distance_upper_bound=ROI_M)
    raster = np.full(shape, np.nan, dtype=np.float16)
    raster.ravel()[np.isfinite(distance)] = np.float16(GROUND_Z_M)
    sim2 = {"R": [1.0, 0.0, 0.0, 1.0], "t": [float(-lo[0]), float(-lo[1])], "s": 1.0 / RESOLUTION_M}
    return raster, sim2


def write_map(log_dir: UPath, log_id: str, scene: Scene, seconds: float, rng: np.random.Generator) -> None:
    """Write ``<log_dir>/map/`` with the three AV2 map files for the ego path (and 2 s beyond)."""
    t_s = np.arange(-1.0, seconds + 2.0, 0.1)
    T = scene.ego.T_ego_city(t_s)
    path_xy, heading = T[:, :2, 3], np.arctan2(T[:, 1, 0], T[:, 0, 0])
    city = str(rng.choice(CITIES))
    map_dir = log_dir / "map"
    map_dir.mkdir(parents=True, exist_ok=True)
    (map_dir / f"log_map_archive_{log_id}____{city}_city_{int(rng.integers(10_000, 99_999))}.json").write_text(
        json.dumps(vector_map(path_xy, heading))
    )
    raster, sim2 = ground_raster(path_xy)
    buffer = io.BytesIO()
    np.save(buffer, raster, allow_pickle=False)
    (map_dir / f"{log_id}_ground_height_surface____{city}.npy").write_bytes(buffer.getvalue())
    (map_dir / f"{log_id}___img_Sim2_city.json").write_text(json.dumps(sim2))
