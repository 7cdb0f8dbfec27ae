"""Evenly spread samples: which few frames, sweeps or images stand for a whole log."""

from __future__ import annotations

import numpy as np


def spread_indices(n_items: int, n_picks: int) -> np.ndarray:
    """Up to ``n_picks`` distinct indices spread evenly over ``range(n_items)``, the first and last
    included (all of them when ``n_items <= n_picks``), increasing, int [K]."""
    return np.unique(np.linspace(0, n_items - 1, min(n_picks, n_items)).round().astype(int))
