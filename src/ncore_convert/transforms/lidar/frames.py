"""One lidar frame, whatever the dataset: from what a reader yields (:class:`LidarFrame`: points,
per-point times computed once, intensity, the frame's pose) to what is stored per lidar
(:class:`StoredRays`): rays at each point's own time with their model elements, and each ray's
``dynamic_flag`` and ``rgb`` from its point in the fixed frame.

AV2/TbV hand over both units of a sweep together (each unit's points may hide the other's from a
camera), OPV2V/V2XSet an agent's one lidar. The flags come first: a point on a moving object takes
its colour only from a camera frame close to its time.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from ncore_convert.contract import DYNAMIC_FLAG, DYNAMIC_UNKNOWN, LIDAR_RGB
from ncore_convert.transforms.camera.colours import FILL_RGB
from ncore_convert.transforms.geometry import transform_points
from ncore_convert.transforms.lidar.rays import RayBundle, ray_bundle
from ncore_convert.transforms.objects.boxes import PointGrid, points_in_box
from ncore_convert.transforms.objects.dynamic import BOX_MARGIN_M, DynamicBoxes, dynamic_flags
from ncore_convert.transforms.timebase import floor_us

#: ``(xyz_fixed_m [N,3], timestamps_us int64 [N], dynamic bool [N], spacing_m=float [N,2] | None) -> (rgb uint8
#: [N,3], coloured bool [N])`` (``spacing_m`` by keyword: :class:`PointData`'s)
Colouring = Callable[..., tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Moved:
    """What the lidar itself saw move in one frame (``transforms.lidar.free_space``).

    Attributes:
        found: lidar -> which of its rays are on a mover, bool [N] (stored-ray order).
        unknown: lidar -> which of its rays the lidar could not judge, bool [N] (None: not told).
        parked: the annotated boxes of the tracks that stand still, and their median boxes (box ->
            fixed frame [S,4,4], half sizes [S,3]), all grown like the dynamic ones: a point in one is
            never flagged from the lidar (``--dynamic-source both``); None: no such rule.
    """

    found: dict[str, np.ndarray]
    parked: tuple[DynamicBoxes, np.ndarray, np.ndarray] | None = None
    unknown: dict[str, np.ndarray] | None = None

    def taken(self, index: dict[str, np.ndarray]) -> Moved:
        """The same, at each lidar's rows ``index`` (int [M] per lidar: each stored ray's row)."""
        unknown = None if self.unknown is None else {lidar: self.unknown[lidar][i] for lidar, i in index.items()}
        return replace(self, found={lidar: self.found[lidar][i] for lidar, i in index.items()}, unknown=unknown)

    def standing(self, xyz_m: np.ndarray, timestamps_us: np.ndarray) -> np.ndarray:
        """Which points (fixed frame, float64 [N,3], at ``timestamps_us``) lie in a standing track's
        box (``parked``), bool [N]."""
        inside = np.zeros(len(xyz_m), bool)
        if self.parked is None:
            return inside
        annotated, T_box_frame, half_m = self.parked
        inside |= dynamic_flags(xyz_m, timestamps_us, annotated) == 1
        grid = PointGrid(xyz_m)
        for T, half in zip(T_box_frame, half_m, strict=True):
            inside[points_in_box(grid, T[:3, 3], T[:3, :3], half + BOX_MARGIN_M)] = True
        return inside


@dataclass
class PointData:
    """What :func:`point_data` made of one frame.

    Attributes:
        generic: lidar -> its rays' per-point generic data (``dynamic_flag`` int8 [N] with boxes,
            ``rgb`` uint8 [N,3] with a colouring).
        coloured: lidar -> how many of its points a camera coloured.
        flag_seconds, colour_seconds: the time each took (benchmark figures).
        xyz_fixed_m, timestamps_us, dynamic: the frame's points of all lidars together, where the
            lidar saw them in the fixed frame (float64 [N,3]), their own times (µs, int64 [N]) and
            which are on dynamic tracks (bool [N]): what camera labels are made from.
        spacing_m: the lidar's spacing between neighbouring returns at each point, across and along
            its rows (its range times its row's angular steps), m [N,2]; None where a lidar has no model.
        unknown: the points whose motion the lidar could not judge (``Moved.unknown``), bool [N]; None:
            not told.
    """

    generic: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    coloured: dict[str, int] = field(default_factory=dict)
    flag_seconds: float = 0.0
    colour_seconds: float = 0.0
    unknown: np.ndarray | None = None
    xyz_fixed_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    timestamps_us: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    dynamic: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    spacing_m: np.ndarray | None = None


def point_data(
    xyz_fixed_m: dict[str, np.ndarray],
    timestamps_us: dict[str, np.ndarray],
    boxes: DynamicBoxes | None,
    colouring: Colouring | None,
    spacing_m: dict[str, np.ndarray | None] | None = None,
    moved: Moved | None = None,
) -> PointData:
    """Each stored ray's ``dynamic_flag`` (with ``boxes``) and ``rgb`` (with a ``colouring``), per lidar.

    Args:
        xyz_fixed_m: lidar -> its rays' points where the lidar saw them, in the boxes' and cameras'
            fixed frame, float64 [N,3] (one row per stored ray, in ray order).
        timestamps_us: lidar -> each ray's own time, µs [N].
        boxes: the dynamic tracks (None: no ``dynamic_flag``).
        colouring: colours the frame's points of all lidars together (None: no ``rgb``).
        spacing_m: lidar -> the spacing between neighbouring returns at each ray's point, across and
            along its rows, m [N,2] (None, or a lidar's None: not known).
        moved: the rays the lidar itself saw move (:class:`Moved`), flagged besides ``boxes``'.
    """
    out = PointData({lidar: {} for lidar in xyz_fixed_m})
    lidars = list(xyz_fixed_m)
    if not lidars:
        return out
    xyz = np.concatenate([xyz_fixed_m[lidar] for lidar in lidars])
    times_us = np.concatenate([np.asarray(timestamps_us[lidar]).astype(np.int64) for lidar in lidars])
    bounds = np.cumsum([0] + [len(xyz_fixed_m[lidar]) for lidar in lidars])
    spacings = [None if spacing_m is None else spacing_m.get(lidar) for lidar in lidars]
    spacing = None if any(s is None for s in spacings) else np.concatenate(spacings)
    parts = list(zip(lidars, bounds[:-1], bounds[1:], strict=True))
    dynamic = np.zeros(len(xyz), bool)
    if boxes is not None or moved is not None:
        started = time.perf_counter()
        if boxes is not None:
            dynamic = dynamic_flags(xyz, times_us, boxes) == 1
        unknown = None
        if moved is not None:
            found = np.concatenate([moved.found[lidar] for lidar in lidars])
            standing = moved.standing(xyz, times_us)
            dynamic |= found & ~standing  # never a point in a parked car's box
            if moved.unknown is not None:  # an annotated mover or a parked car is known
                unknown = np.concatenate([moved.unknown[lidar] for lidar in lidars]) & ~dynamic & ~standing
        out.flag_seconds = time.perf_counter() - started
        for lidar, a, b in parts:
            out.generic[lidar][DYNAMIC_FLAG] = dynamic[a:b].astype(np.int8)
            if unknown is not None:
                out.generic[lidar][DYNAMIC_UNKNOWN] = unknown[a:b].astype(np.int8)
        out.unknown = unknown
    if colouring is not None:
        started = time.perf_counter()
        rgb, coloured = colouring(xyz, times_us, dynamic, spacing_m=spacing)
        out.colour_seconds = time.perf_counter() - started
        for lidar, a, b in parts:
            out.generic[lidar][LIDAR_RGB] = rgb[a:b]
            out.coloured[lidar] = int(coloured[a:b].sum())
    out.xyz_fixed_m, out.timestamps_us, out.dynamic, out.spacing_m = xyz, times_us, dynamic, spacing
    return out


@dataclass(frozen=True)
class LidarFrame:
    """One lidar frame as a reader yields it.

    Attributes:
        xyz_m: the points in the frame's reference frame at ``timestamp_ns``, float [N,3] (AV2/TbV: the
            ego frame, motion-compensated to the sweep time; CARLA: the lidar's frame at the tick).
        times_ns: each point's own time, int64 [N], computed once (TbV: reconstructed).
        intensity: [N]; timestamp_ns: the frame's time.
        rows: lidar -> the rows it measured, int [K] (AV2: the laser_number halves).
        T_reference_fixed: the reference frame at ``timestamp_ns`` -> the fixed frame of the boxes and
            cameras [4,4] (world or world_global).
    """

    xyz_m: np.ndarray
    times_ns: np.ndarray
    intensity: np.ndarray
    timestamp_ns: int
    rows: dict[str, np.ndarray]
    T_reference_fixed: np.ndarray


@dataclass(frozen=True)
class LidarGeometry:
    """How one lidar's rows become rays.

    Attributes:
        to_sensor: ``(xyz_reference [K,3], times_ns [K]) -> xyz_sensor [K,3]``, each point in the
            lidar's frame at its own time (AV2: decompensation); None: the points are that already.
        exact: the points are the source's own float32 values (``ray_bundle(exact=True)``).
        elements: ``(rays, rows) -> (model elements uint16 [N,2], column-time remap dict)`` with a model
            (``rows``: each ray's frame row); None: no model.
        row_steps_rad: the angles between neighbouring returns of each model row, across and along the
            rows (:meth:`model.SpinningLidarModel.row_steps_rad`), float64 [R,2]; None: not known (no model).
    """

    to_sensor: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
    exact: bool = False
    elements: Callable[[RayBundle, np.ndarray], tuple[np.ndarray, dict]] | None = None
    row_steps_rad: np.ndarray | None = None


@dataclass(frozen=True)
class StoredRays:
    """One lidar's share of a frame, ready to store.

    Attributes:
        rays: unit directions in the lidar's frame at each ray's own time, with per-ray times.
        model_elements: (row, column) of each ray in the lidar's model, uint16 [N,2]; None without one.
        column_time_remap: the frame's column-time alignment (empty without a model).
        rows: the frame row of each ray, int [N].
        generic: per-point generic data (``dynamic_flag``, ``rgb``); coloured: points a camera coloured.
    """

    rays: RayBundle
    model_elements: np.ndarray | None
    column_time_remap: dict
    rows: np.ndarray
    generic: dict[str, np.ndarray]
    coloured: int


def lidar_frame(
    frame: LidarFrame,
    geometry: dict[str, LidarGeometry],
    boxes: DynamicBoxes | None,
    colouring: Colouring | None,
    moved: Moved | None = None,
) -> tuple[dict[str, StoredRays], PointData]:
    """Every lidar's rays, model elements and per-point data of one frame (lidars: ``geometry``'s
    keys); also the :class:`PointData` (its timings). ``moved``: what the lidar saw move, its
    ``found`` per row of ``frame.rows[lidar]`` (the rays keep their rows')."""
    rays, rows, elements = {}, {}, {}
    for lidar, how in geometry.items():
        own = frame.rows[lidar]
        xyz = frame.xyz_m[own] if how.to_sensor is None else how.to_sensor(frame.xyz_m[own], frame.times_ns[own])
        rays[lidar] = ray_bundle(
            xyz, frame.times_ns[own], frame.intensity[own], floor_us(frame.timestamp_ns), exact=how.exact
        )
        rows[lidar] = own[rays[lidar].source_index]
        elements[lidar] = (None, {}) if how.elements is None else how.elements(rays[lidar], rows[lidar])
    xyz_fixed = {
        lidar: transform_points(frame.T_reference_fixed, frame.xyz_m[rows[lidar]].astype(np.float64))
        for lidar in geometry
    }
    spacing = {  # the lidar's spacing between neighbouring returns at each point: its range times its row's step
        lidar: None
        if how.row_steps_rad is None or elements[lidar][0] is None
        else rays[lidar].distance_m.astype(np.float64)[:, None] * how.row_steps_rad[elements[lidar][0][:, 0]]
        for lidar, how in geometry.items()
    }
    if moved is not None:  # each ray's row's
        moved = moved.taken({lidar: rays[lidar].source_index for lidar in geometry})
    data = point_data(
        xyz_fixed, {lidar: rays[lidar].timestamp_us for lidar in geometry}, boxes, colouring, spacing, moved
    )
    stored = {
        lidar: StoredRays(rays[lidar], *elements[lidar], rows[lidar], data.generic[lidar], data.coloured.get(lidar, 0))
        for lidar in geometry
    }
    return stored, data


@dataclass
class LidarCounts:
    """One lidar's tallies over the frames written (its metadata's figures)."""

    stored: int = 0  #: rays stored
    zero_range: int = 0  #: points at zero range: no ray
    non_finite: int = 0  #: points with non-finite coordinates: no ray
    coloured: int = 0  #: points a camera coloured

    def add(self, frame: StoredRays) -> None:
        self.stored += len(frame.rays)
        self.zero_range += frame.rays.n_zero_range
        self.non_finite += frame.rays.n_non_finite
        self.coloured += frame.coloured

    @property
    def not_stored(self) -> int:
        return self.zero_range + self.non_finite


def point_data_notes(
    boxes: DynamicBoxes | None,
    why_no_boxes: str,
    lidar_rgb: bool,
    cameras: bool,
    taken_from: str,
    from_lidar: str = "",
) -> dict[str, str]:
    """What a lidar's metadata says of the per-point data :func:`lidar_frame` writes on its frames,
    given what the frames get (the same ``boxes``; colours when ``lidar_rgb`` and ``cameras``):

    - ``dynamic_flag``: written from the dynamic tracks' boxes and, with ``from_lidar`` (how), from
      what the lidar itself saw move; or why not (``why_no_boxes``: the dataset's reason when
      ``boxes`` is None);
    - ``rgb``: written (``taken_from``: the pixel of which camera frame, and what occludes it), or why
      not (``--lidar-rgb`` off, no cameras converted).
    """
    by_boxes = (
        ""
        if boxes is None
        else f"inside one of {len(boxes)} dynamic tracks' boxes grown by {BOX_MARGIN_M:g} m at the point's own"
        " time (cuboids metadata: dynamic_tracks, dynamic_rule)"
    )
    if not by_boxes and not from_lidar:
        flags = f"not written: {why_no_boxes}"
    else:
        flags = "written: int8 per point, 1 = " + " or ".join(part for part in (by_boxes, from_lidar) if part)
    if not lidar_rgb:
        rgb = "not written (--lidar-rgb is off)"
    elif not cameras:
        rgb = "not written: no cameras converted"
    else:
        rgb = (
            f"written: uint8 [N,3] per point, the colour of the {taken_from}; {list(FILL_RGB)} where no camera"
            " sees it (rgb_coloured_points counts the others)"
        )
    notes = {DYNAMIC_FLAG: flags, LIDAR_RGB: rgb}
    if from_lidar:
        notes[DYNAMIC_UNKNOWN] = (
            "written: int8 per point, 1 = the lidar could not judge whether it moved (its dynamic_flag is 0; the"
            " sequence metadata's dynamic_flag_source says when)"
        )
    return notes
