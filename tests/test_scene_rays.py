"""The synthetic generator's ray caster (``synth.raycast.cast_rays``), which culls by azimuth and by each
box's bounding sphere before the exact slab test, against a brute-force reference that tests every
ray against the ground and every box: the same first hit for any scene, from one shared origin (a
camera) and from many (a moving lidar), with boxes that move during the rays' times."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from ncore_convert.synth.raycast import cast_rays
from ncore_convert.synth.scene import Box, Scene

MAX_RANGE_M = 80.0
GROUND_Z_M = -0.3


def _rotation_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def brute_force(origins_m, directions, times_s, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(range [N] with inf for no hit, box index [N], -1 ground/none): every ray against the ground
    plane and every box (a box placed at each ray's time), one ray at a time."""
    ranges, which = np.full(len(origins_m), np.inf), np.full(len(origins_m), -1)
    for i, (o, d, t) in enumerate(zip(origins_m, directions, times_s, strict=True)):
        if d[2] < -1e-9 and (GROUND_Z_M - o[2]) / d[2] > 0:
            ranges[i] = (GROUND_Z_M - o[2]) / d[2]
        for b, box in enumerate(scene.boxes):
            o_box = (o - box.center_m(np.array([t]))[0]) @ box.rotation
            d_box = d @ box.rotation
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-box.dims_m / 2 - o_box) / d_box
                t2 = (box.dims_m / 2 - o_box) / d_box
            near, far = np.max(np.fmin(t1, t2)), np.min(np.fmax(t1, t2))
            if near <= far and 0 < near < ranges[i]:
                ranges[i], which[i] = near, b
    ranges[ranges > MAX_RANGE_M] = np.inf
    return ranges, which


boxes = st.lists(
    st.tuples(
        st.floats(-40, 40),
        st.floats(-40, 40),
        st.floats(0.0, 3.0),  # centre
        st.floats(0.3, 12.0),
        st.floats(0.3, 5.0),
        st.floats(0.3, 6.0),  # dims
        st.floats(-np.pi, np.pi),  # yaw
        st.sampled_from([0.0, 0.0, 8.0, -15.0]),
        st.sampled_from([0.0, 4.0]),  # velocity x, y
    ),
    min_size=1,
    max_size=8,
)


@settings(max_examples=60, deadline=None)
@given(boxes, st.booleans(), st.integers(0, 2**32 - 1))
def test_cast_rays_finds_the_same_first_hit_as_testing_every_box(specs, one_origin, seed):
    rng = np.random.default_rng(seed)
    scene = Scene(
        None,
        [
            Box(
                np.array([x, y, z]),
                np.array([vx, vy, 0.0]),
                _rotation_z(yaw),
                np.array([lx, wy, hz]),
                "REGULAR_VEHICLE",
                str(i),
                10 + i,
            )
            for i, (x, y, z, lx, wy, hz, yaw, vx, vy) in enumerate(specs)
        ],
    )
    n = 600
    azimuth, elevation = rng.uniform(-np.pi, np.pi, n), rng.uniform(-0.5, 0.3, n)
    directions = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    if one_origin:
        origins = np.broadcast_to(np.array([0.5, -0.2, 1.6]), (n, 3))
        times = np.full(n, 0.3)
    else:  # a lidar driving at 10 m/s over a 0.1 s sweep
        times = np.sort(rng.uniform(0.0, 0.1, n))
        origins = np.stack([10.0 * times, np.zeros(n), np.full(n, 1.8)], axis=1)
    ranges, _, which = cast_rays(origins, directions, times, scene, MAX_RANGE_M, GROUND_Z_M)
    expected_ranges, expected_which = brute_force(origins, directions, times, scene)
    np.testing.assert_array_equal(which, expected_which)
    np.testing.assert_allclose(ranges, expected_ranges, rtol=1e-9)
