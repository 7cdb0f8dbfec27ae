"""The depth buffer of projected points: which point of a camera picture may hide another (lidar
colours today; per-camera depth labels build on it). Pixels in NCore's pixel-corner convention."""

from __future__ import annotations

import numpy as np


def nearest_in_front(
    cols: np.ndarray, lines: np.ndarray, depth: np.ndarray, cell_px: tuple[int, int], size_px: tuple[int, int]
) -> np.ndarray:
    """For each projected point (pixel ``cols``, ``lines``, int [V]; camera ``depth`` [V], m), the
    depth of the nearest point that may hide it in a buffer of cells of ``cell_px`` (width, height):
    at or above its row in its own cell and in the cells left and right of it (the pixels at a
    silhouette show the occluder up to a cell beyond its last points), and anywhere in the cell
    above (a nearer point below a point is the ground in front of it and does not hide it); inf
    where there is none, float64 [V]."""
    (w, h), (cell_w, cell_h) = size_px, cell_px
    n_cols = -(-w // cell_w) + 2  # a column either side
    cells = (lines // cell_h + 1) * n_cols + cols // cell_w + 1  # and a row above
    order = np.lexsort((lines, cells))
    o_cells, o_depth = cells[order], depth[order]
    key = o_cells * (h + 1) + lines[order]
    big = 2.0 * (float(o_depth.max()) + 1.0) if len(o_depth) else 1.0
    running = np.minimum.accumulate(o_depth - o_cells * big) + o_cells * big  # per cell, down to a row
    grid = np.full((-(-h // cell_h) + 1) * n_cols, np.inf)  # per cell, its nearest point: its last running value
    last = np.flatnonzero(np.r_[o_cells[1:] != o_cells[:-1], True]) if len(o_cells) else np.zeros(0, np.int64)
    grid[o_cells[last]] = running[last]

    def at_or_above(cell: np.ndarray) -> np.ndarray:
        i = np.searchsorted(key, cell * (h + 1) + lines, side="right") - 1
        found = (i >= 0) & (o_cells[np.maximum(i, 0)] == cell)
        return np.where(found, running[np.maximum(i, 0)], np.inf)

    return np.minimum.reduce([at_or_above(cells), at_or_above(cells - 1), at_or_above(cells + 1), grid[cells - n_cols]])
