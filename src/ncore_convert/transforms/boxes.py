"""Box geometry shared by every box test: the corner table and the edges between corners."""

from __future__ import annotations

import numpy as np

#: The 8 corners of a box as signs of its half sizes, x outermost: (-,-,-), (-,-,+), (-,+,-), ... float64 [8,3].
CORNER_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
#: The 12 edges, as pairs of indices into ``CORNER_SIGNS`` (corners that differ in one sign), int [12,2].
BOX_EDGES = np.array(
    [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(CORNER_SIGNS[i] != CORNER_SIGNS[j]) == 1]
)
