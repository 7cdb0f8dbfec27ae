"""Box geometry shared by every box test: the corner table and the edges between corners."""

from __future__ import annotations

import numpy as np

#: The 8 corners of a box as signs of its half sizes, x outermost: (-,-,-), (-,-,+), (-,+,-), ... float64 [8,3].
CORNER_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
#: The 12 edges, as pairs of indices into ``CORNER_SIGNS`` (corners that differ in one sign), int [12,2].
BOX_EDGES = np.array(
    [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(CORNER_SIGNS[i] != CORNER_SIGNS[j]) == 1]
)


class SortedByX:
    """Points sorted by x once, so that each box looks only at the points near it: the one prefilter of
    every points-in-box test (dynamic flags, the synthetic annotations' interior counts, the
    validator's counts).

    Args:
        xyz_m: points in the boxes' frame, float [N,3].
    """

    def __init__(self, xyz_m: np.ndarray) -> None:
        self.xyz_m = xyz_m
        self.by_x = np.argsort(xyz_m[:, 0], kind="stable")
        self._x_sorted = xyz_m[self.by_x, 0]

    def near(self, centre_m: np.ndarray, reach_m: float) -> np.ndarray:
        """The rows within ``reach_m`` of ``centre_m`` [3] along every axis (x by bisection), int [K]:
        a box whose every point is within ``reach_m`` of its centre has no other."""
        lo = np.searchsorted(self._x_sorted, centre_m[0] - reach_m)
        hi = np.searchsorted(self._x_sorted, centre_m[0] + reach_m, "right")
        rows = self.by_x[lo:hi]
        return rows[np.all(np.abs(self.xyz_m[rows, 1:] - centre_m[1:]) <= reach_m, axis=1)]


def in_box(xyz_m: np.ndarray, centre_m: np.ndarray, R_box_frame: np.ndarray, half_m: np.ndarray) -> np.ndarray:
    """Whether points lie inside boxes (faces included), bool [K].

    Args:
        xyz_m: the points, float [K,3]; centre_m: the box centre [3], or each point's box's [K,3];
        R_box_frame: the box rotation (box axes -> frame) [3,3], or each point's [K,3,3];
        half_m: half the box size [3], or each point's box's [K,3]; all in one frame, metres.
    """
    offset = xyz_m - centre_m
    local = offset @ R_box_frame if R_box_frame.ndim == 2 else np.einsum("nji,nj->ni", R_box_frame, offset)
    return np.all(np.abs(local) <= half_m, axis=1)
