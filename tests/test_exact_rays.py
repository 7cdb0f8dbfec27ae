"""Issue 38: rays that give the source's float32 points back bit for bit (``transforms.lidar.rays.exact_rays``).

NCore stores a float32 unit direction and a float32 distance; a reader multiplies them (float32). The
truth here is the input itself: every point's product must be its own bits, except the listed ones,
which must be within one unit in the last place; the directions must pass NCore's unit-norm check.
"""

from __future__ import annotations

import numpy as np
from conftest import find_opv2v_agent
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from upath import UPath

from ncore_convert.sources.pcd import read_pcd
from ncore_convert.transforms.lidar.rays import exact_rays, ray_bundle


def check(xyz: np.ndarray, max_inexact_share: float) -> np.ndarray:
    direction, distance_m, inexact = exact_rays(xyz)
    assert direction.dtype == np.float32 and distance_m.dtype == np.float32
    back = direction * distance_m[:, None]  # what NCore's get_frame_point_cloud computes
    exact = np.all(back.view(np.uint32) == xyz.view(np.uint32), axis=1)
    assert np.array_equal(np.flatnonzero(~exact), inexact)
    assert len(inexact) <= max_inexact_share * len(xyz)
    near, got = xyz[inexact], back[inexact]
    up, down = np.nextafter(near, np.float32(np.inf)), np.nextafter(near, np.float32(-np.inf))
    tiny = np.abs(got.astype(np.float64) - near) < 1e-30  # a component ~1e-38 m: its direction is subnormal
    assert np.all((got == near) | (got == up) | (got == down) | tiny)  # one float32 step at most
    norm_sq = np.sum(direction.astype(np.float64) ** 2, axis=1)
    assert np.abs(norm_sq - 1.0).max() < 1e-5  # NCore asserts 1e-4
    return inexact


def test_the_real_opv2v_frames():
    """The real agent's four frames: these rays give 99 %+ of the points back bit for bit, and the
    rest (one component's float32 grid coarser than the point's) are listed."""
    paths = sorted(find_opv2v_agent().glob("*.pcd"))
    assert len(paths) == 4
    for path in paths:
        data = read_pcd(UPath(path))
        xyz = np.stack([data["x"], data["y"], data["z"]], axis=1)
        check(xyz, max_inexact_share=0.01)


def test_round_grid_coordinates_and_signed_zeros():
    """Points on a 0.1 m grid (where one ulp moves a point across a voxel edge) and points with
    +0.0 / -0.0 components come back with their exact bits, signs of zero included."""
    grid = np.stack(np.meshgrid(*(np.arange(-40, 41) * 0.1,) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid.astype(np.float32)
    grid = grid[np.linalg.norm(grid, axis=1) > 0.05]
    zeros = np.array([[12.6, 0.0, -0.0], [-0.0, 3.0, 0.0], [0.0, -0.0, -1.5]], dtype=np.float32)
    inexact = check(np.concatenate([grid, zeros]), max_inexact_share=0.01)
    assert not np.isin(np.arange(len(grid), len(grid) + 3), inexact).any()


@settings(max_examples=60, deadline=None)
@given(arrays(np.float32, (64, 3), elements=st.floats(-300, 300, width=32)), st.sampled_from([1.0, 1e-3, 1e3]))
def test_any_float32_points(xyz, scale):
    xyz = (xyz * np.float32(scale)).astype(np.float32)
    xyz = xyz[np.linalg.norm(xyz.astype(np.float64), axis=1) >= 1e-3]
    if len(xyz):
        check(xyz, max_inexact_share=1.0)  # the share is for real distributions: (3, 3, 3) has no exact pair


def test_ray_bundle_keeps_the_exact_rays_and_drops_zero_range():
    xyz = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0], [np.nan, 1.0, 1.0], [-7.3, 0.1, 0.2]], dtype=np.float32)
    rays = ray_bundle(xyz, np.zeros(4, dtype=np.int64), np.zeros(4, dtype=np.uint8), 0, exact=True)
    assert rays.source_index.tolist() == [0, 3] and (rays.n_zero_range, rays.n_non_finite) == (1, 1)
    back = rays.direction * rays.distance_m[:, None]
    exact = np.all(back.view(np.uint32) == xyz[[0, 3]].view(np.uint32), axis=1)
    assert np.array_equal(np.flatnonzero(~exact), rays.inexact)
