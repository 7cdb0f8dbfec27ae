"""Time-unit conversions: NCore stores microseconds, Argoverse 2 stamps nanoseconds.

Every ns -> µs conversion in the project goes through :func:`floor_us` (a time stored or compared at
µs resolution: frame times, labels, poses) or :func:`ceil_us` (the end of a range that must cover an
ns-exact time, such as the last lidar point of a log).
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

NS_PER_US = 1000

Time = TypeVar("Time", int, np.integer, np.ndarray)


def floor_us(t_ns: Time) -> Time:
    """Integer ns -> the µs at or before it (int, numpy integer, or int array of any shape)."""
    return t_ns // NS_PER_US


def ceil_us(t_ns: Time) -> Time:
    """Integer ns -> the µs at or after it (int, numpy integer, or int array of any shape)."""
    return -(-t_ns // NS_PER_US)
