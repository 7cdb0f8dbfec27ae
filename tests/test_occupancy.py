"""The occupancy check's allowance counts independent objects (tracks), not box-frames (issue 74)."""

from __future__ import annotations

import numpy as np

from ncore_convert.validate.occupancy import OCCUPANCY_MIN_OBJECTS, OCCUPANCY_SIGMAS, Occupancy, occupancy_verdict


def _tracks(frames, held, turned) -> Occupancy:
    return Occupancy(np.array(frames), np.array(held), np.array(turned))


def test_a_few_objects_occluded_in_every_frame_are_not_a_misregistration():
    """The held-out OPV2V scenario the box-frame count refused: five objects near the agent in all
    five sampled frames, one of them always occluded (20 of 25 hold a point), the best turn 25. As
    25 independent draws the allowance was 3 sqrt(25 0.9 0.1) = 4.5 boxes; as five objects that
    repeat, 3 sqrt(125 0.9 0.1) = 10.1."""
    ok, decisive, slack = occupancy_verdict(_tracks([5] * 5, [5, 5, 5, 5, 0], [5] * 5))
    assert ok and decisive
    assert np.isclose(slack, 3 * np.sqrt(125 * 0.9 * 0.1))


def test_a_one_tick_scenario_counts_each_box_once():
    """One frame: each box is its own object, and the allowance is the binomial one of the box count."""
    ok, decisive, slack = occupancy_verdict(_tracks([1] * 7, [1] * 5 + [0] * 2, [1] * 7))
    share = 12 / 14
    assert ok and decisive
    assert np.isclose(slack, OCCUPANCY_SIGMAS * np.sqrt(7 * share * (1 - share)))


def test_a_turned_lidar_is_still_refused():
    """Upside down or yawed, the stored registration leaves most near boxes empty that the right one
    fills: with five objects over five frames, 3 of 25 against 25 is far beyond the allowance."""
    ok, decisive, _ = occupancy_verdict(_tracks([5] * 5, [1, 1, 1, 0, 0], [5] * 5))
    assert decisive and not ok
    ok, decisive, _ = occupancy_verdict(_tracks([5] * 8, [1] * 4 + [0] * 4, [5] * 8))
    assert decisive and not ok


def test_one_object_near_in_every_frame_does_not_decide():
    """A single parked car beside the lidar for the whole log is one object, not five boxes."""
    ok, decisive, _ = occupancy_verdict(_tracks([5], [0], [5]))
    assert ok and not decisive
    _, decisive, _ = occupancy_verdict(_tracks([5] * 2 + [1] * 3, [5] * 2 + [1] * 3, [5] * 2 + [1] * 3))
    assert not decisive  # (13)^2 / 53 = 3.2 effective objects
    assert occupancy_verdict(_tracks([1] * OCCUPANCY_MIN_OBJECTS, [1] * 5, [1] * 5))[1]


def test_the_allowance_is_the_spread_of_objects_occluded_frame_after_frame():
    """Simulated occlusion: each object is hidden (with probability q) in all the frames it is near
    in, or in none. The held count's standard deviation over many draws is the allowance / SIGMAS."""
    rng = np.random.default_rng(7)
    frames = rng.integers(1, 6, size=9)
    hidden = rng.random((20_000, len(frames))) < 0.5
    held = (~hidden * frames).sum(axis=1)
    _, _, slack = occupancy_verdict(_tracks(frames, frames, 0 * frames))  # the pooled share: 1/2
    assert np.isclose(held.std(), slack / OCCUPANCY_SIGMAS, rtol=0.03)
