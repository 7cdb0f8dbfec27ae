"""The synthetic generator's ray caster (``synth.raycast.cast_rays``), which culls by azimuth and by each
box's bounding sphere before the exact slab test, against a brute-force reference that tests every
ray against the ground and every box: the same first hit for any scene, from one shared origin (a
camera) and from many (a moving lidar), with boxes that move during the rays' times, each a plain
box or shaped (``synth.shapes``: then every ray against each of its convex parts cut to the
shape's bound, face by face)."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from ncore_convert.synth.raycast import cast_rays
from ncore_convert.synth.scene import Box, Scene
from ncore_convert.synth.shapes import shape_of

MAX_RANGE_M = 80.0
GROUND_Z_M = -0.3


def _rotation_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def brute_force(origins_m, directions, times_s, scene: Scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(range [N] with inf for no hit, box index [N], -1 ground/none, and each box's own entry range
    [N,B], inf where the ray misses it): every ray against the ground plane and every box (a box
    placed at each ray's time), one ray at a time."""
    ranges, which = np.full(len(origins_m), np.inf), np.full(len(origins_m), -1)
    entries = np.full((len(origins_m), len(scene.boxes)), np.inf)
    shaped = {  # every ray against each shaped box's parts, the box placed at each ray's time
        b: _first_part_entries(
            np.einsum("ni,ij->nj", origins_m - box.center_m(np.asarray(times_s)), box.rotation),
            directions @ box.rotation,
            box.shape,
        )
        for b, box in enumerate(scene.boxes)
        if box.shape is not None
    }
    for i, (o, d, t) in enumerate(zip(origins_m, directions, times_s, strict=True)):
        if d[2] < -1e-9 and (GROUND_Z_M - o[2]) / d[2] > 0:
            ranges[i] = (GROUND_Z_M - o[2]) / d[2]
        for b, box in enumerate(scene.boxes):
            o_box = (o - box.center_m(np.array([t]))[0]) @ box.rotation
            d_box = d @ box.rotation
            if b in shaped:
                entries[i, b] = shaped[b][i]
                if shaped[b][i] < ranges[i]:
                    ranges[i], which[i] = shaped[b][i], b
                continue
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-box.dims_m / 2 - o_box) / d_box
                t2 = (box.dims_m / 2 - o_box) / d_box
            near, far = np.max(np.fmin(t1, t2)), np.min(np.fmax(t1, t2))
            if near <= far and near > 0:
                entries[i, b] = near
            if near <= far and 0 < near < ranges[i]:
                ranges[i], which[i] = near, b
    ranges[ranges > MAX_RANGE_M] = np.inf
    return ranges, which, entries


def _first_part_entries(o: np.ndarray, d: np.ndarray, shape) -> np.ndarray:
    """Where rays (box axes: origins ``o``, directions ``d``, [N,3]) first enter one of the shape's
    convex parts, each cut to the shape's bound, ahead of their origins: each part's faces and the
    bound's six taken one by one (n . p <= offset); inf where they miss them all, [N]."""
    axes = np.eye(3)
    bound = [(axes[k], shape.hi_m[k]) for k in range(3)] + [(-axes[k], -shape.lo_m[k]) for k in range(3)]
    best = np.full(len(o), np.inf)
    for normals, offsets in zip(shape.normals, shape.offsets_m, strict=True):
        enter, leave = np.full(len(o), -np.inf), np.full(len(o), np.inf)
        for n, offset in [*zip(normals, offsets, strict=True), *bound]:
            rate, room = d @ n, offset - o @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                enter = np.where(rate < 0, np.maximum(enter, room / rate), enter)
                leave = np.where(rate > 0, np.minimum(leave, room / rate), leave)
            leave = np.where((rate == 0) & (room < 0), -np.inf, leave)
        hit = (enter <= leave) & (enter > 0)
        best = np.where(hit, np.minimum(best, enter), best)
    return best


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
        st.sampled_from(["REGULAR_VEHICLE", "PEDESTRIAN", "BICYCLIST", "BOLLARD"]),  # its shape, or a box
    ),
    min_size=1,
    max_size=8,
)


#: CI's hypothesis found this: a 0.375 m high car's 0.28 m wheels reached out of its box, past the cull
SMALL_CAR = (0.0, 0.0, 1.0, 1.0, 1.0, 0.375, 0.0, 0.0, 0.0, "REGULAR_VEHICLE")
CUBE_CAR = (0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, "REGULAR_VEHICLE")


@settings(max_examples=60, deadline=None)
@given(boxes, st.booleans(), st.booleans(), st.integers(0, 2**32 - 1))
@example(
    specs=[CUBE_CAR, CUBE_CAR, CUBE_CAR, SMALL_CAR],
    one_origin=False,
    shaped=True,
    seed=0,
)
def test_cast_rays_finds_the_same_first_hit_as_testing_every_box(specs, one_origin, shaped, seed):
    rng = np.random.default_rng(seed)
    scene = Scene(
        None,
        [
            Box(
                np.array([x, y, z]),
                np.array([vx, vy, 0.0]),
                _rotation_z(yaw),
                np.array([lx, wy, hz]),
                category,
                str(i),
                10 + i,
                shape=shape_of(category, np.array([lx, wy, hz])) if shaped else None,
            )
            for i, (x, y, z, lx, wy, hz, yaw, vx, vy, category) in enumerate(specs)
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
    expected_ranges, expected_which, entries = brute_force(origins, directions, times, scene)
    # where two objects are entered at the same range (overlapping boxes), either is the first hit:
    # the two computations round differently (CI's hypothesis found a car and a bollard sharing a face)
    other = np.flatnonzero(which != expected_which)
    tied = (which[other] >= 0) & np.isclose(entries[other, which[other]], expected_ranges[other], rtol=1e-9, atol=0)
    np.testing.assert_array_equal(which[other[~tied]], expected_which[other[~tied]])
    np.testing.assert_allclose(ranges, expected_ranges, rtol=1e-9)
