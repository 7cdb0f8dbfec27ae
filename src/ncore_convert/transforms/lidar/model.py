"""Empirical structured model of a spinning lidar, derived from decompensated returns (WIP, issue 3).

Frames: every direction is a unit vector in the lidar's own frame at the ray's own time. Angles
are radians; azimuth is about +z from +x, elevation from the x-y plane.

The model is NCore's row-offset spinning model: element (row, column) has the ray
(elevation E[row], azimuth B[column] + D[row]). Rows are beams sorted by descending elevation;
columns are an upsampled uniform azimuth grid over one revolution in the spin direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Returns closer than this are too affected by the beams' origin offsets to fit angles from,
#: unless a beam has too few far returns (steep downward beams only hit the near ground).
FAR_FIT_M = 10.0
MIN_FAR_POINTS = 200
#: Rays used to fit a frame's column-time alignment.
REMAP_SAMPLES = 4096


def wrap_angle(angle_rad: np.ndarray) -> np.ndarray:
    """Angles (rad, any shape) wrapped to [-pi, pi)."""
    return (angle_rad + np.pi) % (2.0 * np.pi) - np.pi


def circular_mean(angle_rad: np.ndarray) -> float:
    """The circular mean of angles (rad, [N]), in (-pi, pi]."""
    return float(np.arctan2(np.sin(angle_rad).mean(), np.cos(angle_rad).mean()))


@dataclass(frozen=True)
class SpinningLidarModel:
    """Row-offset spinning lidar model (numpy side of NCore's RowOffsetStructuredSpinningLidarModelParameters).

    Attributes:
        spinning_frequency_hz: revolutions per second.
        spinning_direction: "cw" or "ccw" about +z.
        row_elevations_rad: [R], strictly descending.
        row_azimuth_offsets_rad: [R].
        column_azimuths_rad: [C], column 0 first, stepping 2π/C in the spin direction.
        beam_to_row: [B] int, row of each source beam id.
    """

    spinning_frequency_hz: float
    spinning_direction: str
    row_elevations_rad: np.ndarray
    row_azimuth_offsets_rad: np.ndarray
    column_azimuths_rad: np.ndarray
    beam_to_row: np.ndarray

    def row_steps_rad(self, columns_per_return: int = 1) -> np.ndarray:
        """The angles between each row's returns and their neighbours', float64 [R,2]: across (the
        column step times ``columns_per_return``, the columns between a row's successive returns:
        a model upsampled 16 times has 16) and along the rows' elevations (the row's wider gap to
        the rows beside it: a VLP-32C's rows are 1/3 degree apart near the horizon and up to 9
        degrees at its lowest)."""
        elevations = self.row_elevations_rad
        order = np.argsort(elevations)
        gaps = np.diff(elevations[order])
        wider = np.zeros(len(elevations))
        if len(gaps):
            wider[order] = np.maximum(np.r_[gaps[:1], gaps], np.r_[gaps, gaps[-1:]])
        across = 2.0 * np.pi * columns_per_return / len(self.column_azimuths_rad)
        return np.stack([np.full(len(elevations), across), wider], axis=1)

    @property
    def _sign(self) -> float:
        return 1.0 if self.spinning_direction == "ccw" else -1.0

    def assign_elements(self, direction: np.ndarray, beam: np.ndarray) -> np.ndarray:
        """Nearest model element of each ray: uint16 [N,2] (row, column).

        Args:
            direction: unit rays in the sensor frame [N,3] (float32 is enough: a column is 2e-4 rad);
            beam: source beam id [N].
        """
        row = self.beam_to_row[beam]
        n = len(self.column_azimuths_rad)
        # signed progress from column 0 in the spin direction, in columns; the integer modulo wraps it
        start = self.column_azimuths_rad[0] + self.row_azimuth_offsets_rad
        azimuth = np.arctan2(direction[:, 1], direction[:, 0])
        progress = (azimuth - start[row].astype(azimuth.dtype)) * (self._sign * n / (2.0 * np.pi))
        column = np.rint(progress).astype(np.int64) % n
        out = np.empty((len(row), 2), dtype=np.uint16)
        out[:, 0] = row
        out[:, 1] = column
        return out

    def element_directions(self, elements: np.ndarray) -> np.ndarray:
        """Unit rays [N,3] of model elements [N,2] (row, column)."""
        row, column = elements[:, 0].astype(np.int64), elements[:, 1].astype(np.int64)
        elevation = self.row_elevations_rad[row]
        azimuth = self.column_azimuths_rad[column] + self.row_azimuth_offsets_rad[row]
        c = np.cos(elevation)
        return np.stack([np.cos(azimuth) * c, np.sin(azimuth) * c, np.sin(elevation)], axis=1)


def column_time_remap(columns: np.ndarray, time_s: np.ndarray, n_columns: int, spinning_frequency_hz: float) -> dict:
    """Affine column <-> time alignment of one frame: column = phase + rate * (t - t_first), modulo
    the number of columns.

    The phase places the frame on the revolution and the rate follows spin-rate drift. A frame can
    span a little more than one revolution, so columns are first unwrapped against the nominal spin.

    Args:
        columns: model columns of the frame's rays [N]; time_s: their firing times [N], seconds.
    Returns:
        {"first_time_s", "column_at_first_time", "columns_per_second", "residual_p99_columns"}
        (empty for fewer than two rays).
    """
    if len(columns) < 2:
        return {}
    step = max(1, len(columns) // REMAP_SAMPLES)  # a uniform subsample fits the two numbers as well
    t = time_s[::step] - time_s.min()
    nominal = t * n_columns * spinning_frequency_hz
    angle = 2.0 * np.pi * (columns[::step] - nominal) / n_columns
    reference = n_columns * (circular_mean(angle) % (2.0 * np.pi)) / (2.0 * np.pi)
    c = columns[::step] + n_columns * np.rint((reference + nominal - columns[::step]) / n_columns)
    dt, dc = t - t.mean(), c - c.mean()
    rate = float(np.dot(dt, dc) / np.dot(dt, dt)) if np.dot(dt, dt) > 0 else 0.0
    phase = float(c.mean() - rate * t.mean())
    return {
        "first_time_s": float(time_s.min()),
        "column_at_first_time": phase % n_columns,
        "columns_per_second": rate,
        "residual_p99_columns": float(np.percentile(np.abs(c - (phase + rate * t)), 99)),
    }


def derive_model(
    direction: np.ndarray,
    distance_m: np.ndarray,
    beam: np.ndarray,
    time_s: np.ndarray,
    frame: np.ndarray,
    n_beams: int,
    firing_cycle_s: float,
    upsample: int,
) -> SpinningLidarModel:
    """Fit the model from decompensated returns of one unit over one or more frames.

    Args:
        direction: unit rays in the sensor frame at their own time [N,3].
        distance_m: ranges [N]; beam: beam id [N] in 0..n_beams-1.
        time_s: firing time relative to the frame's reference time [N], seconds.
        frame: frame index of each return [N] (the spin phase is fitted per frame).
        firing_cycle_s: time of one firing cycle (one native column).
        upsample: columns per native column.
    """
    azimuth = np.arctan2(direction[:, 1], direction[:, 0])
    elevation = np.arctan2(direction[:, 2], np.hypot(direction[:, 0], direction[:, 1]))
    fit = _fit_mask(distance_m, beam, n_beams)

    beam_elevation = _group_medians(elevation[fit], beam[fit], n_beams)
    rate = _spin_rate_rad_s(azimuth[fit], time_s[fit], beam[fit], frame[fit])

    # azimuth = phase[frame] + rate * t + offset[beam], with offsets of zero circular mean
    frame_ids, frame_index = np.unique(frame, return_inverse=True)
    spun = azimuth - rate * time_s
    offset = np.zeros(n_beams)
    for _ in range(3):
        phase = _group_circular_means((spun - offset[beam])[fit], frame_index[fit], len(frame_ids))
        offset = _group_circular_means((spun - phase[frame_index])[fit], beam[fit], n_beams)
        offset = wrap_angle(offset - circular_mean(offset))
    phase = _group_circular_means((spun - offset[beam])[fit], frame_index[fit], len(frame_ids))

    order = np.argsort(-beam_elevation)
    beam_to_row = np.empty(n_beams, dtype=np.int64)
    beam_to_row[order] = np.arange(n_beams)
    frequency = abs(rate) / (2.0 * np.pi)
    n_columns = int(round(1.0 / (frequency * firing_cycle_s))) * upsample
    sign = 1.0 if rate > 0 else -1.0
    first_time_s = np.full(len(frame_ids), np.inf)
    np.minimum.at(first_time_s, frame_index, time_s)
    frame_start = phase + rate * first_time_s  # azimuth where each frame's first firing points
    mean_start = circular_mean(frame_start)
    start = mean_start + sign * np.min(wrap_angle(sign * (frame_start - mean_start)))  # no frame starts before column 0
    columns = wrap_angle(start + sign * 2.0 * np.pi * np.arange(n_columns) / n_columns)
    return SpinningLidarModel(
        spinning_frequency_hz=float(frequency),
        spinning_direction="ccw" if rate > 0 else "cw",
        row_elevations_rad=beam_elevation[order],
        row_azimuth_offsets_rad=offset[order],
        column_azimuths_rad=columns,
        beam_to_row=beam_to_row,
    )


def _fit_mask(distance_m: np.ndarray, beam: np.ndarray, n_beams: int) -> np.ndarray:
    """Far returns, except for beams with too few of them, which use all returns beyond 1 m."""
    far = distance_m >= FAR_FIT_M
    counts = np.bincount(beam[far], minlength=n_beams)
    near_beams = np.flatnonzero(counts < MIN_FAR_POINTS)
    return far | (np.isin(beam, near_beams) & (distance_m >= 1.0))


def _group_medians(values: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """Median of ``values`` per group id in 0..n_groups-1 (NaN for an empty group)."""
    order = np.lexsort((values, group))
    bounds = np.searchsorted(group[order], np.arange(n_groups + 1))
    return np.array(
        [np.median(values[order[a:b]]) if b > a else np.nan for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    )


def _group_circular_means(angle_rad: np.ndarray, group: np.ndarray, n_groups: int) -> np.ndarray:
    """Circular mean of angles per group id in 0..n_groups-1."""
    s = np.bincount(group, weights=np.sin(angle_rad), minlength=n_groups)
    c = np.bincount(group, weights=np.cos(angle_rad), minlength=n_groups)
    return np.arctan2(s, c)


def _spin_rate_rad_s(azimuth: np.ndarray, time_s: np.ndarray, beam: np.ndarray, frame: np.ndarray) -> float:
    """Median over (frame, beam) tracks of the least-squares slope of unwrapped azimuth over time."""
    track = np.unique(frame, return_inverse=True)[1] * (int(beam.max()) + 1) + beam
    order = np.lexsort((time_s, track))
    track, t = track[order], time_s[order]
    a = np.unwrap(azimuth[order])  # jumps between tracks only add a per-track constant
    n_tracks = int(track.max()) + 1
    n = np.bincount(track, minlength=n_tracks).astype(np.float64)
    t0 = np.bincount(track, weights=t, minlength=n_tracks) / np.maximum(n, 1)
    a0 = np.bincount(track, weights=a, minlength=n_tracks) / np.maximum(n, 1)
    dt, da = t - t0[track], a - a0[track]
    sxy = np.bincount(track, weights=dt * da, minlength=n_tracks)
    sxx = np.bincount(track, weights=dt * dt, minlength=n_tracks)
    usable = (n >= 100) & (sxx > 0)
    return float(np.median(sxy[usable] / sxx[usable]))


def angle_between_rad(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rays a [N,3] and b [N,3] (any lengths), radians [N]; accurate at small angles."""
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    return np.arctan2(cross, np.einsum("ij,ij->i", a, b))
