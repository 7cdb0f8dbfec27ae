"""The vectorised PCD reader against files written here the way Open3D writes them (known truth)."""

from __future__ import annotations

import numpy as np
import pytest
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.pcd import intensity_from_rgb, read_pcd

HEADER = (
    "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\n"
    "COUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
)


def open3d_like_cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xyz [N,3] float32, red channel [N] uint8 and the packed rgb float ({b, g, r, 0} bytes)."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-80, 80, (n, 3)).astype(np.float32)
    red = rng.integers(0, 256, n).astype(np.uint8)
    rgb = (red.astype(np.uint32) << 16).view(np.float32)
    return xyz, red, rgb


def write_ascii(path, xyz, rgb) -> None:
    rows = "\n".join(f"{x:.10g} {y:.10g} {z:.10g} {c:.10g}" for (x, y, z), c in zip(xyz, rgb, strict=True))
    path.write_text(HEADER.format(n=len(xyz), data="ascii") + rows + "\n")


def write_binary(path, xyz, rgb) -> None:
    record = np.zeros(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    record["x"], record["y"], record["z"], record["rgb"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], rgb
    path.write_bytes(HEADER.format(n=len(xyz), data="binary").encode() + record.tobytes())


@pytest.mark.parametrize("write", [write_ascii, write_binary])
def test_points_and_intensity_read_back_exactly(tmp_path, write):
    xyz, red, rgb = open3d_like_cloud(2000)
    write(tmp_path / "000068.pcd", xyz, rgb)
    columns = read_pcd(UPath(tmp_path / "000068.pcd"))
    assert list(columns) == ["x", "y", "z", "rgb"]
    got = np.stack([columns["x"], columns["y"], columns["z"]], axis=1)
    assert got.dtype == np.float32 and np.array_equal(got, xyz)
    np.testing.assert_array_equal(intensity_from_rgb(columns["rgb"]), red / np.float32(255.0))


@pytest.mark.parametrize(
    "text, cause",
    [
        (HEADER.format(n=3, data="ascii") + "1 2 3 0\n", "holds 1 points, the header says 3"),
        (HEADER.format(n=2, data="ascii") + "1 2 3 0\n1 2 3\n", "not 4 numbers per line"),
        (HEADER.format(n=1, data="ascii") + "1 2 x 0\n", "not 4 numbers per line"),
        (HEADER.format(n=2, data="ascii"), "body is empty, the header says 2 points"),
        (HEADER.format(n=1, data="binary_compressed"), "DATA binary_compressed is not supported"),
        (HEADER.format(n=1, data="ascii").replace("TYPE F F F F", "TYPE F F F Q"), "unsupported PCD field types"),
        ("VERSION 0.7\nFIELDS x\n", "no DATA line"),
        (HEADER.format(n=1, data="ascii").replace("FIELDS x y z", "FIELDS x x z") + "1 2 3 0\n", "names a field twice"),
    ],
)
def test_bad_files_name_the_file_and_the_cause(tmp_path, text, cause):
    path = tmp_path / "bad.pcd"
    path.write_text(text)
    with pytest.raises(SourceError, match=cause) as err:
        read_pcd(UPath(path))
    assert str(path) in str(err.value)
