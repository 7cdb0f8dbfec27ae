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


class WindowError(ValueError):
    """A clip window that selects nothing of the log; the message names the log's duration."""


def clip_window_us(first_us: int, last_us: int, seek_sec: float | None, duration_sec: float | None) -> tuple[int, int]:
    """The inclusive µs window ``[first + seek, first + seek + duration]`` of a log whose reference
    times (sweeps, images, frame ticks) span ``[first_us, last_us]``; the whole log without a window.

    Raises WindowError when the window starts after the log's last reference time, or when seek or
    duration is negative (duration zero).
    """
    duration_s = (last_us - first_us) / 1e6
    if (seek_sec is not None and seek_sec < 0) or (duration_sec is not None and duration_sec <= 0):
        raise WindowError(f"--seek-sec must be >= 0 and --duration-sec > 0 (got {seek_sec}, {duration_sec})")
    start_us = first_us + round((seek_sec or 0.0) * 1e6)
    end_us = last_us if duration_sec is None else start_us + round(duration_sec * 1e6)
    if start_us > last_us:
        raise WindowError(f"--seek-sec {seek_sec:g} starts after the log's end (the log lasts {duration_s:.3f} s)")
    return start_us, min(end_us, last_us)


def in_window(timestamps_us: np.ndarray, window_us: tuple[int, int]) -> np.ndarray:
    """Which reference times (µs, int [N]) lie in the inclusive window: bool [N]."""
    t = np.asarray(timestamps_us, dtype=np.int64)
    return (t >= window_us[0]) & (t <= window_us[1])
