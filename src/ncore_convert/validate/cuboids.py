"""Cuboid observations read columnar from their documented store layout, checked as arrays, and a
sample of them decoded by nvidia-ncore.

NCore's format documentation (``docs/data/formats.rst``, "Cuboids Component") specifies the layout:
``cuboids/{instance}/cuboids/{attrs}/cuboid_track_observations`` is a JSON list with one object per
observation: ``track_id``, ``class_id``, ``timestamp_us``, ``reference_frame_id``,
``reference_frame_timestamp_us``, ``bbox3`` (``centroid``, ``dim``, ``rot``), ``source`` and
``source_version``. :class:`CuboidColumnsReader` opens the component through nvidia-ncore's
component-reader mechanism (a ``ComponentReader`` subclass, as the library's own readers are) and
reads that attribute into arrays: a 10,000-box log in milliseconds, where the loader's
``get_cuboid_track_observations`` decodes each observation through ``dataclasses_json`` (about
0.3 ms each). An independent reader is also the stronger check of what was written.

The library still decodes a sample (:func:`library_sample`): every track's first and last
observation and a stride over the rest, through ``CuboidTrackObservation.from_dict``, the decoder
its component reader applies to each stored object (the loader's ``get_cuboid_track_observations``
decodes and caches all of them on its first call, so it cannot be asked for a sample). Each decoded
observation must equal its row of the columns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ncore.data.v4 import CuboidsComponent, SequenceComponentGroupsReader, SequenceLoaderV4
from ncore.impl.data.types import CuboidTrackObservation, LabelSource
from ncore.impl.data.v4.components import ComponentReader

from ncore_convert.contract import DEFAULT_INSTANCE
from ncore_convert.transforms.objects.dynamic import by_track
from ncore_convert.validate.poses import sensor_poses
from ncore_convert.validate.report import Report

#: observations decoded by the library besides every track's first and last (a stride over the rest)
LIBRARY_SAMPLE_STRIDED = 64
ATTRIBUTE = "cuboid_track_observations"  #: the documented attribute of the component's ``cuboids`` group


class CuboidColumnsReader(ComponentReader):
    """The ``cuboids`` component (version v1), read as the stored JSON objects."""

    @staticmethod
    def get_component_name() -> str:
        return CuboidsComponent.COMPONENT_NAME

    @staticmethod
    def supports_component_version(version: str) -> bool:
        return version == "v1"

    def stored_objects(self) -> list:
        """The documented attribute as stored: one JSON object per observation."""
        return list(self._group["cuboids"].attrs[ATTRIBUTE])


@dataclass(frozen=True)
class CuboidColumns:
    """Cuboid observations, one row each, in store order.

    Attributes:
        stored: the stored JSON objects [N] (for the library's decode of a sample).
        track_id, class_id, reference_frame_id, source: str [N].
        timestamp_us, reference_frame_timestamp_us: int64 [N], microseconds.
        centroid_m: box centres in the reference frame at its time, float64 [N,3].
        dim_m: (length, width, height), float64 [N,3]; rot_rad: extrinsic xyz Euler angles, float64 [N,3].
    """

    stored: list
    track_id: np.ndarray
    class_id: np.ndarray
    timestamp_us: np.ndarray
    reference_frame_id: np.ndarray
    reference_frame_timestamp_us: np.ndarray
    centroid_m: np.ndarray
    dim_m: np.ndarray
    rot_rad: np.ndarray
    source: np.ndarray

    def __len__(self) -> int:
        return len(self.stored)

    @classmethod
    def from_stored(cls, stored: list) -> CuboidColumns:
        """Columns of the stored objects; ValueError naming the first object that is not an observation."""
        try:
            boxes = np.array(
                [[*o["bbox3"]["centroid"], *o["bbox3"]["dim"], *o["bbox3"]["rot"]] for o in stored], dtype=np.float64
            ).reshape(len(stored), 9)
            times = np.array(
                [[o["timestamp_us"], o["reference_frame_timestamp_us"]] for o in stored], dtype=np.int64
            ).reshape(len(stored), 2)
            texts = [[o["track_id"], o["class_id"], o["reference_frame_id"], o["source"]] for o in stored]
        except (KeyError, TypeError, ValueError, OverflowError) as err:
            raise ValueError(f"{_first_malformed(stored)}: {type(err).__name__} {err}") from None
        texts = np.array(texts, dtype=object).reshape(len(stored), 4)
        return cls(
            stored=stored,
            track_id=texts[:, 0],
            class_id=texts[:, 1],
            timestamp_us=times[:, 0],
            reference_frame_id=texts[:, 2],
            reference_frame_timestamp_us=times[:, 1],
            centroid_m=boxes[:, 0:3],
            dim_m=boxes[:, 3:6],
            rot_rad=boxes[:, 6:9],
            source=texts[:, 3],
        )

    def rows(self, index: np.ndarray) -> CuboidColumns:
        """The rows ``index`` (int [K] or bool [N]) as columns."""
        keep = np.flatnonzero(index) if np.asarray(index).dtype == bool else np.asarray(index, dtype=np.int64)
        fields = {name: getattr(self, name)[keep] for name in self.__dataclass_fields__ if name != "stored"}
        return CuboidColumns([self.stored[i] for i in keep], **fields)


def _first_malformed(stored: list) -> str:
    keys = ("track_id", "class_id", "timestamp_us", "reference_frame_id", "reference_frame_timestamp_us", "source")
    for i, o in enumerate(stored):
        box = o.get("bbox3") if isinstance(o, dict) else None
        if not (isinstance(o, dict) and all(k in o for k in keys) and isinstance(box, dict)):
            return f"observation {i}"
        if not all(len(np.atleast_1d(box.get(k, ()))) == 3 for k in ("centroid", "dim", "rot")):
            return f"observation {i}"
    return "an observation"


def read_cuboids(reader: SequenceComponentGroupsReader, instance: str = DEFAULT_INSTANCE) -> CuboidColumns | None:
    """A sequence's cuboid observations (the ``instance`` component), None when it has none."""
    component = reader.open_component_readers(CuboidColumnsReader).get(instance)
    return None if component is None else CuboidColumns.from_stored(component.stored_objects())


def library_sample(columns: CuboidColumns) -> np.ndarray:
    """Rows for the library to decode, int [K] sorted: every track's first and last observation (in
    time) and ``LIBRARY_SAMPLE_STRIDED`` rows spread evenly over all of them."""
    if not len(columns):
        return np.zeros(0, dtype=np.int64)
    order, bounds = by_track(columns.track_id.astype(str), columns.timestamp_us)
    starts, ends = bounds[:-1], bounds[1:] - 1
    strided = np.unique(np.linspace(0, len(columns) - 1, min(LIBRARY_SAMPLE_STRIDED, len(columns))).astype(np.int64))
    return np.unique(np.concatenate([order[starts], order[ends], strided]))


def _decoded_row(obs: CuboidTrackObservation) -> tuple:
    box = obs.bbox3
    return (
        obs.track_id,
        obs.class_id,
        obs.timestamp_us,
        obs.reference_frame_id,
        obs.reference_frame_timestamp_us,
        *box.centroid,
        *box.dim,
        *box.rot,
        obs.source.name,
    )


def _column_row(columns: CuboidColumns, i: int) -> tuple:
    return (
        columns.track_id[i],
        columns.class_id[i],
        int(columns.timestamp_us[i]),
        columns.reference_frame_id[i],
        int(columns.reference_frame_timestamp_us[i]),
        *columns.centroid_m[i],
        *columns.dim_m[i],
        *columns.rot_rad[i],
        columns.source[i],
    )


def _same(decoded: tuple, read: tuple) -> bool:
    """Equal rows; the box values compared as floats, NaN equal to NaN (a NaN is the box check's finding)."""
    texts = (0, 1, 2, 3, 4, len(read) - 1)
    return [decoded[k] for k in texts] == [read[k] for k in texts] and np.array_equal(
        np.asarray(decoded[5:-1], dtype=np.float64), np.asarray(read[5:-1], dtype=np.float64), equal_nan=True
    )


def check_cuboids(report: Report, loader: SequenceLoaderV4, columns: CuboidColumns) -> None:
    """The checks of every observation, as arrays, and the library's decode of a sample."""
    n = len(columns)
    interval = loader.sequence_timestamp_interval_us
    ids_ok = np.array([isinstance(v, str) and v != "" for v in (*columns.track_id, *columns.class_id)], dtype=bool)
    report.add(
        "cuboids: track and class ids",
        ids_ok.all(),
        f"{int((~ids_ok).sum())} of {2 * n} ids empty or not text; {len(set(columns.track_id))} tracks",
    )
    times = np.stack([columns.timestamp_us, columns.reference_frame_timestamp_us], axis=1)
    outside = (times < interval.start) | (times >= interval.stop)
    report.add(
        "cuboids: times within the sequence",
        not outside.any(),
        f"{int(outside.any(axis=1).sum())} of {n} observations outside [{interval.start}, {interval.stop})",
    )
    _check_reference_frames(report, loader, columns)
    finite = np.isfinite(np.concatenate([columns.centroid_m, columns.dim_m, columns.rot_rad], axis=1)).all(axis=1)
    positive = (columns.dim_m > 0).all(axis=1)
    report.add(
        "cuboids: finite boxes with sizes > 0",
        finite.all() and positive.all(),
        f"{int((~finite).sum())} not finite, {int((finite & ~positive).sum())} with a size <= 0, of {n}",
    )
    sources = set(columns.source)
    unknown = sorted(str(s) for s in sources - set(LabelSource.__members__))
    report.add(
        "cuboids: label sources",
        not unknown,
        f"{sorted(map(str, sources))}" + (f"; not NCore LabelSource names: {unknown}" if unknown else ""),
    )
    sample = library_sample(columns)
    differ = []
    for i in sample:
        try:
            same = _same(_decoded_row(CuboidTrackObservation.from_dict(columns.stored[i])), _column_row(columns, i))
        except Exception as err:  # noqa: BLE001 - whatever the library raises is the finding
            differ.append(f"{i}: {type(err).__name__}")
            continue
        if not same:
            differ.append(str(i))
    report.add(
        "cuboids: decoded by nvidia-ncore as read (sample)",
        not differ,
        f"{len(sample)} of {n} observations decoded (each track's first and last, {LIBRARY_SAMPLE_STRIDED} strided);"
        f" {len(differ)} differ" + (f": {differ[:3]}" if differ else ""),
    )


def _check_reference_frames(report: Report, loader: SequenceLoaderV4, columns: CuboidColumns) -> None:
    """Every reference frame is a pose-graph node whose poses cover the reference times."""
    nodes = set(loader.pose_graph.nodes)
    bad = []
    for frame_id in sorted(set(columns.reference_frame_id), key=str):
        rows = columns.reference_frame_id == frame_id
        if frame_id not in nodes:
            bad.append(f"{frame_id!r} ({int(rows.sum())}): not in the pose graph")
            continue
        t_us = np.unique(columns.reference_frame_timestamp_us[rows]).astype(np.uint64)
        try:
            sensor_poses(loader, frame_id, "world", t_us)
        except (ValueError, KeyError, AssertionError) as err:
            bad.append(f"{frame_id!r}: poses do not cover its times ({type(err).__name__})")
    frames = sorted(map(str, set(columns.reference_frame_id)))
    report.add("cuboids: reference frames posed at their times", not bad, f"{frames}" + (f"; {bad[:3]}" if bad else ""))
