"""How well a converted sequence's structured lidar model reproduces its stored rays.

For every ray, the model ray of its ``model_element`` is compared with the stored direction (both
in the lidar's own frame at the ray's time). Reads through nvidia-ncore's SequenceLoaderV4.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np
from ncore.data.v4 import SequenceLoaderV4
from ncore.impl.data.types import RowOffsetStructuredSpinningLidarModelParameters

from ncore_convert.transforms.lidar.model import SpinningLidarModel, angle_between_rad


@dataclass
class ErrorStats:
    """Angular errors of a set of rays, degrees (far: distance above the far range)."""

    points: int
    mean_deg: float
    far_points: int
    far_mean_deg: float

    @staticmethod
    def of(error_deg: np.ndarray, far: np.ndarray) -> ErrorStats:
        return ErrorStats(
            points=int(len(error_deg)),
            mean_deg=float(error_deg.mean()) if len(error_deg) else float("nan"),
            far_points=int(far.sum()),
            far_mean_deg=float(error_deg[far].mean()) if far.any() else float("nan"),
        )


@dataclass
class LidarModelReport:
    """Model-vs-stored angular error of one lidar. Biases are signed means over far-range rays
    (stored minus model); rows and frames break the errors down."""

    lidar_id: str
    far_range_m: float
    points: int
    mean_deg: float
    median_deg: float
    p95_deg: float
    max_deg: float
    far_points: int
    far_mean_deg: float
    azimuth_bias_deg: float
    elevation_bias_deg: float
    rows: list[dict] = field(default_factory=list)
    frames: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    def lines(self) -> list[str]:
        out = [
            f"{self.lidar_id}: {self.points} rays, angular error mean {self.mean_deg:.4f}°, median"
            f" {self.median_deg:.4f}°, p95 {self.p95_deg:.4f}°, max {self.max_deg:.4f}°",
            f"  far range (> {self.far_range_m:g} m, {self.far_points} rays): mean {self.far_mean_deg:.4f}°;"
            f" bias azimuth {self.azimuth_bias_deg:+.4f}°, elevation {self.elevation_bias_deg:+.4f}°",
            "  row  elevation°   rays     mean°   far mean°",
        ]
        for r in self.rows:
            out.append(f"  {r['row']:3d}  {r['elevation_deg']:9.3f}  {r['points']:6d}  {r['mean_deg']:8.4f}")
            out[-1] += f"  {r['far_mean_deg']:9.4f}"
        out.append("  frame  timestamp_us        rays     mean°   far mean°")
        for f in self.frames:
            out.append(f"  {f['frame']:5d}  {f['timestamp_us']:<18d}  {f['points']:6d}  {f['mean_deg']:8.4f}")
            out[-1] += f"  {f['far_mean_deg']:9.4f}"
        return out


def _model_from_ncore(params: RowOffsetStructuredSpinningLidarModelParameters) -> SpinningLidarModel:
    return SpinningLidarModel(
        spinning_frequency_hz=float(params.spinning_frequency_hz),
        spinning_direction=params.spinning_direction,
        row_elevations_rad=params.row_elevations_rad.astype(np.float64),
        row_azimuth_offsets_rad=params.row_azimuth_offsets_rad.astype(np.float64),
        column_azimuths_rad=params.column_azimuths_rad.astype(np.float64),
        beam_to_row=np.arange(params.n_rows),
    )


def evaluate_lidar_model(loader: SequenceLoaderV4, lidar_id: str, far_range_m: float = 20.0) -> LidarModelReport:
    """Compare every stored ray of ``lidar_id`` with the model ray of its model element.

    Raises ValueError when the lidar has no structured model or its frames carry no model elements.
    """
    sensor = loader.get_lidar_sensor(lidar_id)
    params = sensor.model_parameters
    if not isinstance(params, RowOffsetStructuredSpinningLidarModelParameters):
        raise ValueError(f"{lidar_id}: no row-offset structured lidar model stored (found {type(params).__name__})")
    model = _model_from_ncore(params)
    errors, far_masks, rows, az_bias, el_bias, frames = [], [], [], [], [], []
    for i in range(sensor.frames_count):
        elements = sensor.get_frame_ray_bundle_model_element(i)
        if elements is None:
            raise ValueError(f"{lidar_id}: frame {i} has no model_element")
        direction = sensor.get_frame_ray_bundle_direction(i).astype(np.float64)
        distance = np.asarray(sensor.get_frame_ray_bundle_return_distance_m(i, return_index=0)).reshape(-1)
        model_ray = model.element_directions(elements)
        error = np.degrees(angle_between_rad(model_ray, direction))
        far = distance > far_range_m
        stored, modelled = direction[far], model_ray[far]
        az = np.arctan2(stored[:, 1], stored[:, 0]) - np.arctan2(modelled[:, 1], modelled[:, 0])
        el = np.arcsin(np.clip(stored[:, 2], -1, 1)) - np.arcsin(np.clip(modelled[:, 2], -1, 1))
        az_bias.append(np.degrees((az + np.pi) % (2 * np.pi) - np.pi))
        el_bias.append(np.degrees(el))
        stats = ErrorStats.of(error, far)
        frames.append({"frame": i, "timestamp_us": int(sensor.frames_timestamps_us[i, 1]), **asdict(stats)})
        errors.append(error)
        far_masks.append(far)
        rows.append(elements[:, 0].astype(np.int64))
    error, far, row = np.concatenate(errors), np.concatenate(far_masks), np.concatenate(rows)
    row_stats = []
    for r in range(params.n_rows):
        m = row == r
        elevation_deg = float(np.degrees(params.row_elevations_rad[r]))
        row_stats.append({"row": r, "elevation_deg": elevation_deg, **asdict(ErrorStats.of(error[m], far[m]))})
    overall = ErrorStats.of(error, far)
    return LidarModelReport(
        lidar_id=lidar_id,
        far_range_m=far_range_m,
        points=overall.points,
        mean_deg=overall.mean_deg,
        median_deg=float(np.median(error)),
        p95_deg=float(np.percentile(error, 95)),
        max_deg=float(error.max()),
        far_points=overall.far_points,
        far_mean_deg=overall.far_mean_deg,
        azimuth_bias_deg=float(np.concatenate(az_bias).mean()),
        elevation_bias_deg=float(np.concatenate(el_bias).mean()),
        rows=row_stats,
        frames=frames,
    )
