"""Where a labelled object's box is solid: what the box may hide of the points behind it.

A box is not its object. A car's tight box is empty above its hood and trunk, under its body between
the wheels, beside its cabin and around its mirrors; a camera sees the street, the next car or the
sky through those parts. So a box hides only through where its object is likely solid, in the box's
own axes (:func:`solid_entry`), on two kinds of evidence:

- **a vehicle's own points** (the lidar's returns inside its box): the lidar saw the vehicle's top
  surface there, and a vehicle is solid from its floor (``FLOOR_M`` above the box's: real cars' sills
  and bumpers sit 0.2-0.45 m up, and the street shows between the wheels below them) up to that
  surface. The box's footprint is cut into ``CELL_M`` cells; a cell is solid up to the highest own
  point in it (a height map: the hood, the raked glass, the roof and the cabin's leaning sides are
  followed to a cell). The gaps between the lidar's returns are closed over the points' spacing
  (a grey closing: it fills the gaps without growing the outline).
- **its class's shape**, in the cells no own point reaches (the vehicle far away, or its far side):
  every vehicle fills its lower body, from the floor to half its height (below a car's belt line,
  hood and trunk: 0.55-0.65 of its height) over the middle 60 % of its length and its width but
  ``SIDE_INSET_M`` a side, and its cabin, from half its height to ``ROOF_INSET_M`` below the roof,
  over 45 % of its length from 30 % behind the centre and its width but ``CABIN_INSET_M`` a side.
  Vans, buses and trucks fill more of their boxes than a car; the car's core is inside theirs too.

People and riders fill a small, changing part of their boxes, so only their class's core hides: a
person's torso (from half their height to 0.8 of it, the middle 60 % of the box's length and its
width; hips at about 0.5 and shoulders at about 0.82 of a standing person's height), a rider's back
(0.6 to 0.8 of the height, the middle 30 % of the length and its width). A post (a bollard) fills the
middle of its box: 60 % of its length and width, all its height. Other classes (signs, cones,
barriers) hide nothing through their boxes; their own points hide what they cover in the depth
buffer.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt, maximum_filter, minimum_filter

from ncore_convert.transforms.objects.boxes import slab_span

VEHICLE, PERSON, RIDER, POST = 0, 1, 2, 3  #: the kinds of solid (``kind_of``)
#: NCore class -> the kind of solid its objects are (classes not here hide nothing through their boxes).
SOLID_KINDS = {
    **dict.fromkeys(("car", "truck", "bus", "trailer", "vehicle"), VEHICLE),
    "pedestrian": PERSON,
    **dict.fromkeys(("bicyclist", "motorcyclist", "wheeled_rider"), RIDER),
    "bollard": POST,
}
#: (x, y, z) extents of the person's, rider's and post's cores: fractions of the half length and half
#: width (centred), and of the height from the box's floor.
CORES = {
    PERSON: ((-0.6, 0.6), (-0.6, 0.6), (0.5, 0.8)),
    RIDER: ((-0.3, 0.3), (-0.6, 0.6), (0.6, 0.8)),
    POST: ((-0.6, 0.6), (-0.6, 0.6), (0.0, 1.0)),
}


def kind_of(ncore_class: str) -> int:
    """The kind of solid of an NCore class (``SOLID_KINDS``), -1: none."""
    return SOLID_KINDS.get(ncore_class, -1)


FLOOR_M = 0.30  #: a vehicle's solid parts start this far above its box's floor
SIDE_INSET_M = 0.1  #: the body core's sides inside the box's
CABIN_INSET_M = 0.4  #: the cabin core's sides inside the box's
ROOF_INSET_M = 0.12  #: the cabin core's top below the box's
#: A cell's top above its highest own point: a line of sight grazing a roof within this is taken as
#: hidden (the annotations and poses are not better than a centimetre; a far point seen past a roof's
#: edge from just above it fell in the pixel row that shows the roof)
SILHOUETTE_M = 0.01
CELL_M = 0.06  #: the height map's cells (a car's raked glass rises about 0.08 m over one)
#: (lowest, highest) of each class core along the box's length, as a fraction of the half length.
BODY_X = (-0.6, 0.6)
CABIN_X = (-0.3, 0.15)


def floor_z(half_m: np.ndarray) -> float:
    """The height of a vehicle's floor in its box's axes (centre 0), m: ``FLOOR_M`` above the box's."""
    return float(-half_m[2] + FLOOR_M)


def under_floor(kind: int, half_m: np.ndarray, local_m: np.ndarray) -> np.ndarray:
    """The points (box axes, [V,3], m) below a vehicle's floor: the street under its body, which the
    body may hide although it lies inside the box; bool [V] (all False for the other kinds)."""
    if kind != VEHICLE:
        return np.zeros(len(local_m), bool)
    return local_m[:, 2] <= floor_z(half_m)


def _cell_of(x_m: np.ndarray, y_m: np.ndarray, half_m: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """The height-map cell (:func:`height_map`, ``shape``) over box-frame ``x_m``, ``y_m`` (any shape,
    m; clamped to the footprint): its indices along x and y, int each."""
    return (
        np.clip(((x_m + float(half_m[0])) / CELL_M).astype(np.int64), 0, shape[0] - 1),
        np.clip(((y_m + float(half_m[1])) / CELL_M).astype(np.int64), 0, shape[1] - 1),
    )


def height_map(half_m: np.ndarray, own_m: np.ndarray, spacing_m: float) -> np.ndarray:
    """A vehicle's solid top over its box's footprint, in ``CELL_M`` cells from the box's (-x, -y)
    corner, float64 [nx, ny], m in the box's axes (centre 0); ``floor_z`` - 1 where it is not solid.

    A cell holding own points is solid up to the highest of them (and ``SILHOUETTE_M``). A cell
    between such cells (a gap between the lidar's returns: within a closing by ``spacing_m`` of the
    seen cells, which does not grow their outline) takes the top of its nearest seen cell. In the
    cells beyond them (the cabin's leaning side the lidar did not see, the box's empty corners, the
    vehicle's far side) the class core holds.

    Args:
        half_m: the box's half sizes, [3], m.
        own_m: its own points in its axes, [P,3], m (those below the floor are left out).
        spacing_m: the lidar's spacing between neighbouring returns on it, m.
    """
    hx, hy, hz = (float(v) for v in half_m)
    floor = floor_z(half_m)
    low = floor - 1.0  # not solid
    shape = (max(1, int(np.ceil(2 * hx / CELL_M))), max(1, int(np.ceil(2 * hy / CELL_M))))
    X, Y = np.meshgrid(
        (np.arange(shape[0]) + 0.5) * CELL_M - hx, (np.arange(shape[1]) + 0.5) * CELL_M - hy, indexing="ij"
    )  # the cells' centres
    core = np.full(shape, low)
    core[(X >= BODY_X[0] * hx) & (X <= BODY_X[1] * hx) & (np.abs(Y) <= hy - SIDE_INSET_M)] = 0.0
    core[(X >= CABIN_X[0] * hx) & (X <= CABIN_X[1] * hx) & (np.abs(Y) <= hy - CABIN_INSET_M)] = hz - ROOF_INSET_M
    above = own_m[own_m[:, 2] > floor]
    if not len(above):
        return core
    cell = _cell_of(above[:, 0], above[:, 1], half_m, shape)
    top = np.full(shape, low)
    np.maximum.at(top, cell, np.minimum(above[:, 2], hz) + SILHOUETTE_M)
    seen = top > low
    size = 2 * int(np.ceil(spacing_m / CELL_M)) + 1
    grown = maximum_filter(np.pad(seen.astype(np.uint8), size), size=size, mode="constant")
    between = minimum_filter(grown, size=size, mode="constant")[size:-size, size:-size] > 0  # a closing
    _, nearest = distance_transform_edt(~seen, return_indices=True)
    top = np.where(between, top[nearest[0], nearest[1]], low)
    return np.where(top > floor, top, core)


def solid_entry(
    kind: int, half_m: np.ndarray, own_m: np.ndarray, spacing_m: float, origin_m: np.ndarray, step_m: np.ndarray
) -> np.ndarray:
    """Where lines of sight first enter the solid part of one box: the fraction of each line's length,
    float64 [V] (inf: never; see the module docstring).

    Args:
        kind: the kind of solid its object is (``VEHICLE``, ``PERSON``, ``RIDER``, ``POST``).
        half_m: the box's half sizes, [3], m.
        own_m: its own points in its axes (centre 0), [P,3], m; spacing_m: the lidar's spacing
            between neighbouring returns on them, m.
        origin_m: the lines' common origin (the camera) in the box's axes, [3], m.
        step_m: each line's length and direction, from the origin to its point, box axes, [V,3], m.
    """
    hx, hy, hz = (float(v) for v in half_m)
    steps = [step_m[:, a] for a in range(3)]
    if kind != VEHICLE:
        (x0, x1), (y0, y1), (z0, z1) = CORES[kind]
        lo = (x0 * hx, y0 * hy, -hz + 2 * hz * z0)
        hi = (x1 * hx, y1 * hy, -hz + 2 * hz * z1)
        enter, leave = slab_span(origin_m, steps, lo, hi)
        return np.where((enter <= leave) & (enter > 0), enter, np.inf)
    top = height_map(half_m, own_m, spacing_m)
    floor = floor_z(half_m)
    enter, leave = slab_span(origin_m, steps, (-hx, -hy, floor), (hx, hy, float(top.max())), enter_from=0.0)
    entry = np.full(len(step_m), np.inf)
    crossing = np.flatnonzero(enter <= leave)
    if not len(crossing) or top.max() <= floor:
        return entry
    for rows in np.array_split(crossing, int(np.ceil(len(crossing) / MARCH_ROWS))):
        entry[rows] = _march(top, floor, half_m, origin_m, step_m[rows], enter[rows], leave[rows])
    return entry


MARCH_ROWS = 4096  #: lines marched at once (memory: rows x samples x 3 floats)
MAX_SAMPLES = 700  #: a line's samples in a box at most (the run across a 20 m bus in half cells)


def _march(
    top: np.ndarray, floor: float, half_m: np.ndarray, origin_m: np.ndarray, step_m: np.ndarray, enter, leave
) -> np.ndarray:
    """The first fraction of each line (``origin_m`` + t ``step_m``, [V,3]; inside the box's footprint
    for ``enter`` <= t <= ``leave``, [V]) below the height map ``top`` and above ``floor``, sampled
    every half cell of its horizontal run, float64 [V] (inf: none). A line steep enough to stay in
    one cell is sampled at its ends (a vertical line's run is 0: enter and leave)."""
    # each line sampled every half cell of its horizontal run from where it enters (its own samples,
    # whichever lines are marched with it), and where it leaves
    run_per_t = np.maximum(np.hypot(step_m[:, 0], step_m[:, 1]), 1e-9)
    dt = 0.5 * CELL_M / run_per_t
    count = np.minimum(np.ceil((leave - enter) / dt), MAX_SAMPLES).astype(np.int64) + 1
    k = np.arange(int(count.max()))
    t = np.minimum(enter[:, None] + k[None, :] * dt[:, None], leave[:, None])
    p = origin_m[None, None, :] + t[..., None] * step_m[:, None, :]
    inside = (p[..., 2] >= floor) & (p[..., 2] <= top[_cell_of(p[..., 0], p[..., 1], half_m, top.shape)])
    first = np.argmax(inside, axis=1)
    hit = inside[np.arange(len(step_m)), first]
    return np.where(hit, t[np.arange(len(step_m)), first], np.inf)
