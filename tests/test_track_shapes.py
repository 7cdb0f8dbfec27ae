"""A vehicle's cover map from every sweep of its track (``objects.track_shapes``, issue 74).

A parked car, its annotated box 10 cm wider than its body each side, is passed by the ego: the first
sweep sees its near side from y = -10 m, a later one its far side from y = +10 m. The lines of sight
of a sweep pass through every place outside the body that is on its side of the car or above its
roof; the places behind the body stay unseen. Truth: the body's cells and heights.
"""

from __future__ import annotations

import numpy as np

from ncore_convert.transforms.objects.cores import cover_columns, cover_map
from ncore_convert.transforms.objects.track_shapes import TrackShapes

HALF_M = np.array([2.3, 1.0, 0.8])  # the annotated box
BODY_M = np.array([2.0, 0.9])  # the body's half length and width
ROOF_M = 0.35  # its top, box axes
SIDES = (-1.0, 1.0)  # where each sweep's lidar stands: y = side x 10 m


def _body_points(side: float) -> np.ndarray:
    """The returns one sweep takes of the body from its side: its near flank and the near half of its roof."""
    x = np.arange(-1.95, 1.96, 0.05)
    z = np.arange(-0.45, ROOF_M, 0.05)
    flank = np.stack(np.broadcast_arrays(x[:, None], side * BODY_M[1], z[None, :]), axis=-1).reshape(-1, 3)
    y = np.arange(0.0, BODY_M[1], 0.05) * side
    roof = np.stack(np.broadcast_arrays(x[:, None], y[None, :], ROOF_M), axis=-1).reshape(-1, 3)
    return np.concatenate([flank, roof])


class _Sight:
    """A sweep's lines of sight from ``side``: every place outside the body (5 cm clear of it) on that
    side of the car or above its roof."""

    def __init__(self, side: float) -> None:
        self.side = side

    def passed(self, xyz_m: np.ndarray) -> np.ndarray:
        outside = (np.abs(xyz_m[:, 0]) > BODY_M[0] + 0.05) | (np.abs(xyz_m[:, 1]) > BODY_M[1] + 0.05)
        outside |= xyz_m[:, 2] > ROOF_M + 0.05
        on_its_side = xyz_m[:, 1] * self.side > 0
        return outside & (on_its_side | (xyz_m[:, 2] > ROOF_M + 0.05))


def _covered_volume(top: np.ndarray, bottom: np.ndarray) -> float:
    _, halves = cover_columns(HALF_M, top, bottom)
    return float(np.sum(8 * np.prod(halves, axis=1)))


def _body_top_covered(top: np.ndarray) -> float:
    """The share of the body's footprint cells covered up to its roof (less a cell's rounding)."""
    nx, ny = top.shape
    x = (np.arange(nx) + 0.5) * 0.06 - HALF_M[0]
    y = (np.arange(ny) + 0.5) * 0.06 - HALF_M[1]
    body = (np.abs(x)[:, None] < BODY_M[0] - 0.06) & (np.abs(y)[None, :] < BODY_M[1] - 0.06)
    return float(np.mean(top[body] >= ROOF_M - 0.01))


def test_a_parked_cars_far_side_seen_later_tightens_its_mask_and_keeps_it_whole():
    T_box_world = np.eye(4)[None]
    origins = {side: np.array([0.0, 10.0 * side, 1.0]) for side in SIDES}
    points = {side: _body_points(side) for side in SIDES}
    spacing = {side: np.full((len(points[side]), 2), 0.05) for side in SIDES}
    # the first sweep's own map (what a frame near it got before issue 74)
    first = cover_map(HALF_M, points[-1.0], spacing[-1.0], origins[-1.0], _Sight(-1.0).passed)
    shapes = TrackShapes()
    for side in SIDES:
        shapes.gather(["car"], T_box_world, HALF_M[None], points[side], spacing[side], origins[side], _Sight(side))
    pooled = shapes.cover("car", HALF_M)
    assert pooled is not None
    assert _body_top_covered(pooled[0]) == 1.0 and _body_top_covered(first[0]) == 1.0  # recall kept
    # the box's margin beyond the far flank: the first sweep never looked there, the later one did
    volume_first, volume_pooled = _covered_volume(*first), _covered_volume(*pooled)
    assert volume_pooled < volume_first - 0.2, (volume_first, volume_pooled)
    nx, ny = pooled[0].shape
    far_margin = (np.arange(ny) + 0.5) * 0.06 - HALF_M[1] > BODY_M[1] + 0.06
    assert np.all(pooled[0][:, far_margin] < pooled[1][:, far_margin])  # empty now
    assert np.any(first[0][:, far_margin] > first[1][:, far_margin])  # covered by the first sweep's map


def test_a_box_of_another_size_or_never_gathered_gets_no_pooled_map():
    shapes = TrackShapes()
    shapes.gather(
        ["car"],
        np.eye(4)[None],
        HALF_M[None],
        _body_points(-1.0),
        np.full((1, 2), 0.05).repeat(len(_body_points(-1.0)), 0),
        np.array([0.0, -10.0, 1.0]),
        _Sight(-1.0),
    )
    assert shapes.cover("car", HALF_M) is not None
    assert shapes.cover("car", HALF_M + 0.2) is None
    assert shapes.cover("other", HALF_M) is None
