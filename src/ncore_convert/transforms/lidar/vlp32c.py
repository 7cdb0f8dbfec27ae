"""Velodyne VLP-32C facts as they appear in Argoverse 2 sweeps (per *beam*, i.e. laser_number % 32).

Measured on real AV2 sweeps (the real sample is held to them in ``tests/test_lidar_model.py``): AV2's laser_number is
neither Velodyne's laser id nor elevation-sorted, so the tables are indexed by AV2 beam index.
These are the nominal datasheet values that the measured medians round to.
"""

from __future__ import annotations

import numpy as np

N_BEAMS = 32
SPIN_RATE_HZ = 10.0

#: Beam elevation in the unit's own frame, degrees, by AV2 beam index (laser_number % 32).
BEAM_ELEVATION_DEG = np.array(
    [
        7.0,
        -5 / 3,
        5 / 3,
        -2 / 3,
        15.0,
        -1 / 3,
        10 / 3,
        2 / 3,
        4 / 3,
        0.0,
        1.0,
        7 / 3,
        1 / 3,
        -1.0,
        14 / 3,
        31 / 3,
        -6.148,
        -15.639,
        -3.0,
        -2.0,
        -4.0,
        -8.843,
        -14 / 3,
        -10 / 3,
        -8 / 3,
        -16 / 3,
        -4 / 3,
        -7.254,
        -11 / 3,
        -11.31,
        -7 / 3,
        -25.0,
    ]
)

#: Beam azimuth offset relative to the column azimuth in the unit's own frame, degrees.
BEAM_AZIMUTH_OFFSET_DEG = np.array(
    [
        1.4,
        -1.4,
        4.2,
        -4.2,
        1.4,
        -1.4,
        1.4,
        -4.2,
        1.4,
        1.4,
        -1.4,
        -1.4,
        4.2,
        4.2,
        -1.4,
        -1.4,
        1.4,
        1.4,
        -1.4,
        -4.2,
        1.4,
        1.4,
        -1.4,
        -4.2,
        1.4,
        -4.2,
        1.4,
        -1.4,
        4.2,
        -1.4,
        4.2,
        -1.4,
    ]
)

#: Beams fired together, in firing order within one cycle (AV2 beam indices).
FIRING_PAIRS = (
    (13, 31),
    (1, 17),
    (9, 29),
    (3, 21),
    (12, 27),
    (5, 16),
    (8, 25),
    (7, 20),
    (2, 22),
    (10, 28),
    (6, 23),
    (11, 24),
    (0, 18),
    (14, 30),
    (4, 19),
    (15, 26),
)

FIRING_CYCLE_NS = 55_296  #: one cycle of 16 firing pairs
FIRING_PAIR_SPACING_NS = 2_304  #: spacing between consecutive pairs within a cycle
