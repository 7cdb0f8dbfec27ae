"""CARLA's ray-cast lidar as a structured spinning-lidar model, from ``data_protocol.yaml``.

CARLA (``RayCastLidar``) fires, at every tick of ``fixed_delta_seconds``, ``channels`` lasers at
elevations spaced uniformly from ``upper_fov`` down to ``lower_fov``; each laser measures
``round(points_per_second * dt / channels)`` azimuths (rounded half away from zero) spaced evenly
over the tick's sweep of ``360 * rotation_frequency * dt`` degrees, starting where the last tick
ended. Range noise (``noise_stddev``) moves points along their rays; drop-off removes points, which
leaves holes in the grid, not new rays. Points are in the lidar's own left-handed frame; the
converter mirrors y (``transforms.carla``), so azimuths change sign and the spin is clockwise.

The model (NCore's row-offset spinning model, no row offsets): row r has the elevation of laser r;
column j the j-th azimuth of a tick, stepping clockwise from column 0 at the tick's first azimuth
``phase``. One tick is one revolution in OPV2V and V2XSet (20 Hz at a 0.05 s tick), so the grid is
the same in every frame; the phase is measured from the data.

Angles in radians unless named ``_deg``; directions are unit vectors in the right-handed lidar frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ncore_convert.transforms.lidar.model import SpinningLidarModel, circular_mean, wrap_angle

#: Keys of a ``sensing.perception.lidar`` block the model needs.
PROTOCOL_KEYS = ("channels", "upper_fov", "lower_fov", "rotation_frequency", "points_per_second")


@dataclass(frozen=True)
class CarlaLidarSpec:
    """A CARLA ray-cast lidar as the protocol declares it, with the world tick ``fixed_delta_seconds``."""

    channels: int
    upper_fov_deg: float
    lower_fov_deg: float
    rotation_frequency_hz: float
    points_per_second: float
    fixed_delta_seconds: float

    @classmethod
    def from_protocol(cls, block: dict, fixed_delta_seconds: float) -> CarlaLidarSpec:
        """From a ``lidar`` block; ValueError naming a missing or non-numeric key."""
        missing = [key for key in PROTOCOL_KEYS if key not in block]
        if missing:
            raise ValueError(f"lidar block lacks {', '.join(missing)}")
        try:
            return cls(
                int(block["channels"]),
                float(block["upper_fov"]),
                float(block["lower_fov"]),
                float(block["rotation_frequency"]),
                float(block["points_per_second"]),
                float(fixed_delta_seconds),
            )
        except (TypeError, ValueError) as err:
            raise ValueError(f"lidar block has a non-numeric value ({err})") from None

    @property
    def points_per_channel(self) -> int:
        """Azimuths per laser per tick: CARLA rounds ``pps * dt / channels`` half away from zero."""
        return int(math.floor(self.points_per_second * self.fixed_delta_seconds / self.channels + 0.5))

    @property
    def tick_sweep_deg(self) -> float:
        return 360.0 * self.rotation_frequency_hz * self.fixed_delta_seconds

    @property
    def row_elevations_rad(self) -> np.ndarray:
        return np.radians(np.linspace(self.upper_fov_deg, self.lower_fov_deg, self.channels))


def model(spec: CarlaLidarSpec, phase_rad: float) -> SpinningLidarModel:
    """The structured model of ``spec`` with column 0 at the right-handed azimuth ``phase_rad``
    (ValueError unless a tick sweeps exactly one revolution)."""
    if not math.isclose(spec.tick_sweep_deg, 360.0, abs_tol=1e-6):
        raise ValueError(f"a tick sweeps {spec.tick_sweep_deg:g} deg, not one revolution")
    n = spec.points_per_channel
    columns = phase_rad - np.arange(n) * (2.0 * np.pi / n)  # clockwise in the right-handed frame
    return SpinningLidarModel(
        spinning_frequency_hz=spec.rotation_frequency_hz,
        spinning_direction="cw",
        row_elevations_rad=spec.row_elevations_rad,
        row_azimuth_offsets_rad=np.zeros(spec.channels),
        column_azimuths_rad=wrap_angle(columns),
        beam_to_row=np.arange(spec.channels),
    )


def nearest_rows(direction: np.ndarray, row_elevations_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each ray's nearest laser (row) and its elevation residual, rad.

    Args:
        direction: unit rays [N,3]; row_elevations_rad: [R], descending.
    """
    elevation = np.arcsin(np.clip(direction[:, 2].astype(np.float64), -1.0, 1.0))
    if len(row_elevations_rad) == 1:
        return np.zeros(len(elevation), dtype=np.int64), elevation - row_elevations_rad[0]
    ascending = row_elevations_rad[::-1]
    i = np.clip(np.searchsorted(ascending, elevation), 1, len(ascending) - 1)
    nearer_low = np.abs(elevation - ascending[i - 1]) < np.abs(elevation - ascending[i])
    row = (len(ascending) - 1 - np.where(nearer_low, i - 1, i)).astype(np.int64)
    return row, elevation - row_elevations_rad[row]


def grid_phase(direction: np.ndarray, spec: CarlaLidarSpec) -> tuple[float, np.ndarray]:
    """The azimuth grid's phase (rad, right-handed: column 0 is the grid azimuth nearest to -180 deg
    in CARLA's left-handed frame) and each ray's residual from the grid, in columns [N]."""
    step = 2.0 * np.pi / spec.points_per_channel
    azimuth_lh = -np.arctan2(direction[:, 1], direction[:, 0]).astype(np.float64)
    progress = (azimuth_lh + np.pi) / step
    offset = circular_mean(2.0 * np.pi * progress) / (2.0 * np.pi)  # columns, in (-1/2, 1/2]
    residual = progress - offset - np.round(progress - offset)
    phase_lh = -np.pi + offset * step
    return float(wrap_angle(-phase_lh)), residual


@dataclass(frozen=True)
class DataFit:
    """How a lidar's returns fit a protocol's model.

    Attributes:
        ring_residual_deg: 99th percentile of |elevation - nearest row|, degrees.
        column_residual: 99th percentile of |azimuth - nearest column|, in columns.
        phase_spread_columns: how far the frames' grid phases lie apart, columns.
        phase_rad: the grid phase (right-handed azimuth of column 0), circular mean over the frames.
    """

    ring_residual_deg: float
    column_residual: float
    phase_spread_columns: float
    phase_rad: float


def fit_to_data(frames: list[np.ndarray], spec: CarlaLidarSpec) -> DataFit:
    """Compare a few frames' unit rays (right-handed, [N,3] each) with the protocol's grid."""
    rings, columns, phases = [], [], []
    for direction in frames:
        _, residual = nearest_rows(direction, spec.row_elevations_rad)
        phase, column_residual = grid_phase(direction, spec)
        rings.append(np.abs(residual))
        columns.append(np.abs(column_residual))
        phases.append(phase)
    step = 2.0 * np.pi / spec.points_per_channel
    mean_phase = circular_mean(np.array(phases))
    spread = float(np.abs(wrap_angle(np.array(phases) - mean_phase)).max() / step)
    return DataFit(
        ring_residual_deg=float(np.degrees(np.percentile(np.concatenate(rings), 99))),
        column_residual=float(np.percentile(np.concatenate(columns), 99)),
        phase_spread_columns=spread,
        phase_rad=mean_phase,
    )


def assign_elements(lidar_model: SpinningLidarModel, direction: np.ndarray) -> np.ndarray:
    """Each ray's (row, column) in the model, uint16 [N,2]: nearest laser, nearest azimuth."""
    row, _ = nearest_rows(direction, lidar_model.row_elevations_rad)
    return lidar_model.assign_elements(direction, row)


#: Elevations further apart than this (degrees) belong to different lasers: a CARLA laser's returns
#: lie within ~0.003 deg of its elevation (float32 points), adjacent lasers are >= 0.1 deg apart.
RING_GAP_DEG = 0.03
#: Azimuths closer than this (rad, 0.006 deg) are the same column seen in different frames.
SAME_AZIMUTH_RAD = 1e-4
#: A laser needs this many returns over the frames to count as a ring (fewer: stray returns).
MIN_RING_POINTS = 8


@dataclass(frozen=True)
class PointsFit:
    """A CARLA lidar's geometry measured from its returns alone.

    Attributes:
        spec: the lidar as a protocol would declare it (``points_per_second`` restated from the columns).
        fov_source: ``"protocol"`` when the protocol's upper and lower FOV are where the measured rings
            say (the channel count then fills the FOV, rings without returns included), else ``"points"``
            (the highest and lowest ring seen).
        rings_seen: lasers with returns; ring_step_deg: the measured spacing of the lasers.
        ring_grid_residual_deg: largest distance of a ring's median elevation from the uniform grid.
        fit: the returns against the derived spec (residuals, phase).
    """

    spec: CarlaLidarSpec
    fov_source: str
    rings_seen: int
    ring_step_deg: float
    ring_grid_residual_deg: float
    fit: DataFit


def _rings_deg(elevation_deg: np.ndarray) -> np.ndarray:
    """Median elevation (degrees) of each cluster of elevations [N] (a laser), ascending."""
    order = np.sort(elevation_deg)
    cuts = np.flatnonzero(np.diff(order) > RING_GAP_DEG) + 1
    clusters = np.split(order, cuts)
    return np.array([np.median(c) for c in clusters if len(c) >= MIN_RING_POINTS])


def _column_count(azimuth_rad: np.ndarray, rows: np.ndarray) -> int:
    """Azimuths per laser and revolution: 2 pi over the median step between a laser's neighbouring
    returns (drop-off and empty sky leave gaps of several steps, but most neighbours are one apart;
    the same azimuth in several frames differs by float32 rounding, ~1e-6 rad, and is not a step)."""
    order = np.lexsort((azimuth_rad, rows))
    same_row = rows[order][1:] == rows[order][:-1]
    steps = np.diff(azimuth_rad[order])[same_row]
    steps = steps[steps > SAME_AZIMUTH_RAD]
    if not len(steps):
        raise ValueError("no laser has two returns at different azimuths")
    return int(round(2.0 * np.pi / float(np.median(steps))))


def fit_from_points(frames: list[np.ndarray], fixed_delta_seconds: float, protocol: CarlaLidarSpec | None) -> PointsFit:
    """Derive a CARLA ray-cast lidar (lasers, their FOV, azimuths per revolution, phase) from unit
    rays of a few frames (right-handed lidar frame, [N,3] each), assuming one revolution per tick.

    The lasers are the clusters of elevation; CARLA spaces them uniformly, so a line through the
    clusters' medians gives the step and the top laser. Azimuths per revolution come from the step
    between a laser's neighbouring returns, refined to the count (within 3) whose grid fits the
    azimuths best. ``protocol`` (possibly wrong) only supplies the FOV when its limits lie on the
    measured grid. ValueError, saying what does not fit, when the returns are not CARLA's grid.
    """
    direction = np.concatenate(frames).astype(np.float64)
    if len(direction) < MIN_RING_POINTS * 2:
        raise ValueError(f"too few returns ({len(direction)}) to measure the lidar")
    elevation_deg = np.degrees(np.arcsin(np.clip(direction[:, 2], -1.0, 1.0)))
    rings = _rings_deg(elevation_deg)[::-1]  # top laser first, as CARLA numbers them
    if len(rings) < 2:
        raise ValueError(f"{len(rings)} ring(s) of returns: not a multi-laser spinning lidar")
    gaps = -np.diff(rings)
    step0 = float(gaps.min())
    index = np.round((rings[0] - rings) / step0).astype(np.int64)
    if np.any(np.diff(index) < 1):
        raise ValueError("the rings of returns are not uniformly spaced")
    slope, top = np.polyfit(index.astype(np.float64), rings, 1)
    step = -float(slope)
    grid_residual = float(np.abs(rings - (top - step * index)).max())
    if grid_residual > 0.25 * step:
        raise ValueError(f"the rings of returns are not uniformly spaced (off the grid by {grid_residual:.3f} deg)")
    upper, lower, fov_source = float(top), float(top - step * index[-1]), "points"
    if protocol is not None:
        above = (protocol.upper_fov_deg - top) / step  # whole lasers above the top ring seen
        below = (lower - protocol.lower_fov_deg) / step
        if min(above, below) > -0.1 and max(abs(above - round(above)), abs(below - round(below))) < 0.1:
            upper, lower, fov_source = protocol.upper_fov_deg, protocol.lower_fov_deg, "protocol"
    channels = int(round((upper - lower) / step)) + 1
    azimuth = np.arctan2(direction[:, 1], direction[:, 0])
    row, _ = nearest_rows(direction, np.radians(np.linspace(upper, lower, channels)))
    n0 = _column_count(azimuth, row)

    def spec_with(n: int) -> CarlaLidarSpec:
        rate = 1.0 / fixed_delta_seconds
        return CarlaLidarSpec(channels, upper, lower, rate, n * channels * rate, fixed_delta_seconds)

    candidates = [spec_with(n) for n in range(max(n0 - 3, 2), n0 + 4)]
    fits = [fit_to_data(frames, s) for s in candidates]
    best = int(np.argmin([f.column_residual for f in fits]))
    return PointsFit(candidates[best], fov_source, len(rings), step, grid_residual, fits[best])
