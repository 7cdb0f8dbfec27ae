"""Argoverse 2 cuboid annotations (``annotations.feather``): the boxes, each in the ego frame at its
sweep's time, and the annotators' interior point counts. Frames and names as in
:mod:`.argoverse2` (``ego_SE3_object`` maps box points into the ego frame)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.reader import Reader, reading
from ncore_convert.sources.store import ObjectInfo


@dataclass(frozen=True)
class Annotations:
    """Cuboid annotations (columnar), each in the ego frame at its sweep ``timestamps_ns``.

    Attributes:
        timestamps_ns: int64 [M]; track_uuids, categories: lists of str [M].
        dims_m: (length, width, height) along the object x, y, z axes, float64 [M,3].
        T_object_ego: float64 [M,4,4] (av2's ``ego_SE3_object``), box centre and orientation in the
            ego frame: maps box-frame points to the ego frame.
    """

    timestamps_ns: np.ndarray
    track_uuids: list[str]
    categories: list[str]
    dims_m: np.ndarray
    T_object_ego: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps_ns)

    def subset(self, keep: np.ndarray) -> Annotations:
        """The rows where ``keep`` (bool [M]) is true."""
        rows = np.flatnonzero(keep)
        return Annotations(
            timestamps_ns=self.timestamps_ns[rows],
            track_uuids=[self.track_uuids[i] for i in rows],
            categories=[self.categories[i] for i in rows],
            dims_m=self.dims_m[rows],
            T_object_ego=self.T_object_ego[rows],
        )


def read_annotations(
    log_dir: UPath, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> Annotations | None:
    """Annotations from ``annotations.feather``, or None when the log has none (test split, TbV);
    ``listing``: the log folder's (a remote file is then found and checked by it)."""
    path = log_dir / "annotations.feather"
    with reading(reader) as r:
        if not r.exists(path, listing):
            return None
    names = [n for n in av2.ANNOTATIONS_SCHEMA.names if n != "num_interior_pts"]
    table = av2.read_table(path, av2.ANNOTATIONS_SCHEMA, columns=names, listing=listing, reader=reader)
    dims = np.stack([av2.column(table, c) for c in ("length_m", "width_m", "height_m")], axis=1)
    if np.any(~np.isfinite(dims)) or np.any(dims <= 0):
        raise SourceError(path, "cuboid with non-finite or non-positive dimensions")
    ego_SE3_object = av2.poses_from_table(path, table)
    timestamps_ns = av2.column(table, "timestamp_ns")
    track_uuids = table.column("track_uuid").to_pylist()
    seen: set[tuple[int, str]] = set()
    for row, key in enumerate(zip(timestamps_ns.tolist(), track_uuids, strict=True)):
        if key in seen:
            raise SourceError(path, f"row {row}: track {key[1]} annotated twice at timestamp_ns {key[0]}")
        seen.add(key)
    return Annotations(
        timestamps_ns=timestamps_ns,
        track_uuids=track_uuids,
        categories=table.column("category").to_pylist(),
        dims_m=dims,
        T_object_ego=ego_SE3_object,
    )


@dataclass(frozen=True)
class InteriorPoints:
    """``num_interior_pts`` of each annotation row: how many sweep points AV2 found inside the box.

    Attributes:
        timestamps_ns: int64 [M]; track_uuids: list of str [M]; counts: int64 [M].
    """

    timestamps_ns: np.ndarray
    track_uuids: list[str]
    counts: np.ndarray

    def subset(self, keep: np.ndarray) -> InteriorPoints:
        """The rows where ``keep`` (bool [M]) is true."""
        rows = np.flatnonzero(keep)
        return InteriorPoints(self.timestamps_ns[rows], [self.track_uuids[i] for i in rows], self.counts[rows])


def read_interior_points(
    log_dir: UPath, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> InteriorPoints | None:
    """The annotations' point counts, or None when the log has no ``annotations.feather``;
    ``listing``: the log folder's."""
    path = log_dir / "annotations.feather"
    with reading(reader) as r:
        if not r.exists(path, listing):
            return None
    names = ["timestamp_ns", "track_uuid", "num_interior_pts"]
    table = av2.read_table(path, av2.ANNOTATIONS_SCHEMA, columns=names, listing=listing, reader=reader)
    return InteriorPoints(
        av2.column(table, "timestamp_ns"), table.column("track_uuid").to_pylist(), av2.column(table, "num_interior_pts")
    )
