"""What a lidar sweep saw in each direction: the nearest return per cell of azimuth and elevation. It
tells whether the lidar's line of sight passed through a place: a return in the place's direction
beyond it shows the place empty (free space); none, or a nearer one, shows nothing about it (between
the rows, or hidden).

A spinning lidar on a moving rig looks in each direction at one time of its sweep, from where the rig
was then: each point's direction is taken from its own origin, and a place is looked up from the
origin of the returns in its direction."""

from __future__ import annotations

import numpy as np

AZIMUTH_CELL_RAD = np.radians(0.4)  #: a cell's width (the VLP-32C's returns are 0.2 degrees apart)
ELEVATION_CELL_RAD = np.radians(0.5)  #: a cell's height (its rows are 0.33-4 degrees apart)
#: A return shows a place empty if it lies this far beyond it, and 1 % (the returns' noise; its line
#: of sight may pass a few centimetres beside the place within the cell).
PASSED_MARGIN_M = 0.1
ROW_GAP = 4  #: the lidar's rows may be this many cells apart (2 degrees: the VLP-32C's lowest are 3-4 apart)


def nearest_per_cell(cell: np.ndarray, range_m: np.ndarray, size: int) -> np.ndarray:
    """The nearest of the ranges ``range_m`` [N] in each of ``size`` cells (``cell``: flat index [N]),
    float64 [size]; NaN where a cell has none."""
    nearest = np.full(size, np.inf)
    np.minimum.at(nearest, cell, range_m)
    return np.where(np.isfinite(nearest), nearest, np.nan)


class RangeImage:
    """The nearest return per direction of a sweep's points ``points_m`` [N,3] (fixed frame), each
    seen from where the lidar was as it measured it, ``origins_m`` [N,3] or [3]."""

    def __init__(self, points_m: np.ndarray, origins_m: np.ndarray) -> None:
        origins = np.broadcast_to(np.asarray(origins_m, np.float64), np.shape(points_m))
        self._middle_m = np.median(origins, axis=0) if len(origins) else np.zeros(3)
        self._shape = (int(np.ceil(np.pi / ELEVATION_CELL_RAD)) + 1, int(np.ceil(2 * np.pi / AZIMUTH_CELL_RAD)) + 1)
        cell, range_m = self._cells(points_m, origins)
        size = self._shape[0] * self._shape[1]
        self._range_m = nearest_per_cell(cell, range_m, size)  # per cell (NaN: none)
        first = np.flatnonzero(range_m == self._range_m[cell])  # each cell's nearest return (or its equals)
        self._origin_m = np.tile(self._middle_m, (size, 1))  # where the lidar was as it looked there
        self._origin_m[cell[first]] = origins[first]

    def _cells(self, xyz_m: np.ndarray, origins_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The cell (flat index) and range (m) of points ``xyz_m`` [M,3] seen from ``origins_m`` [M,3]."""
        sight = np.asarray(xyz_m, np.float64) - origins_m
        range_m = np.linalg.norm(sight, axis=1)
        elevation = np.arcsin(np.clip(sight[:, 2] / np.maximum(range_m, 1e-9), -1.0, 1.0))
        azimuth = np.arctan2(sight[:, 1], sight[:, 0])
        rows = np.clip(((elevation + np.pi / 2) / ELEVATION_CELL_RAD).astype(np.int64), 0, self._shape[0] - 1)
        cols = ((azimuth + np.pi) / AZIMUTH_CELL_RAD).astype(np.int64) % self._shape[1]
        return rows * self._shape[1] + cols, range_m

    def passed(self, xyz_m: np.ndarray) -> np.ndarray:
        """Which places ``xyz_m`` [M,3] (fixed frame) a line of sight passed through: the nearest
        return in their direction lies beyond them (``PASSED_MARGIN_M`` and 1 %). Between two rows of
        the lidar (no return in the place's cell), the nearest return in the cells up to ``ROW_GAP``
        above and below it in its column must lie beyond it, with one on each side. bool [M]."""
        xyz_m = np.asarray(xyz_m, np.float64)
        cell, _ = self._cells(xyz_m, np.broadcast_to(self._middle_m, xyz_m.shape))
        cell, range_m = self._cells(xyz_m, self._origin_m[cell])  # from where the lidar looked there
        nearest = self._range_m[cell]
        between = np.flatnonzero(np.isnan(nearest))  # no return in the place's own cell
        if len(between):
            n_rows, n_cols = self._shape
            row, col = np.divmod(cell[between], n_cols)
            found_m = np.full(len(between), np.nan)
            sides = np.zeros((2, len(between)), bool)  # a return above it, below it
            for step in range(1, ROW_GAP + 1):
                for side, r in enumerate((row + step, row - step)):
                    ok = (r >= 0) & (r < n_rows)
                    found = np.where(ok, self._range_m[np.clip(r, 0, n_rows - 1) * n_cols + col], np.nan)
                    found_m = np.fmin(found_m, found)
                    sides[side] |= np.isfinite(found)
            nearest[between] = np.where(sides.all(axis=0), found_m, np.nan)
        return np.isfinite(nearest) & (nearest > range_m * 1.01 + PASSED_MARGIN_M)
