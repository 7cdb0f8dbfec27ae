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
from scipy.spatial import ConvexHull, QhullError

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


def _seen_tops(
    half_m: np.ndarray, own_m: np.ndarray, spacing_m: float, floor: float, margin_m
) -> tuple[np.ndarray, np.ndarray] | None:
    """The tops that a box's own points show over its footprint, in ``CELL_M`` cells from the box's
    (-x, -y) corner, m in the box's axes (centre 0): where they show it (a cell holding own points
    above ``floor``, up to the highest of them and its ``margin_m``; a cell between such cells, a gap
    between the lidar's returns within a closing by ``spacing_m`` of them that does not grow their
    outline, the top of its nearest such cell), ``floor`` - 1 elsewhere; and every cell's nearest
    such cell's top. float64 [nx, ny] each; None: no own point above ``floor``.

    Args:
        half_m: the box's half sizes, [3], m; own_m: its own points in its axes, [P,3], m;
        spacing_m: the lidar's spacing between neighbouring returns on them, m.
        margin_m: how far above each own point the top may be, m (scalar or [P]).
    """
    shape = footprint_cells(half_m)
    keep = own_m[:, 2] > floor
    if not keep.any():
        return None
    above, margin = own_m[keep], np.broadcast_to(margin_m, len(own_m))[keep]
    low = floor - 1.0
    top = np.full(shape, low)
    z_top = np.minimum(above[:, 2] + margin, half_m[2] + SILHOUETTE_M)
    np.maximum.at(top, _cell_of(above[:, 0], above[:, 1], half_m, shape), z_top)
    seen = top > low
    size = 2 * int(np.ceil(spacing_m / CELL_M)) + 1
    grown = maximum_filter(np.pad(seen.astype(np.uint8), size), size=size, mode="constant")
    between = minimum_filter(grown, size=size, mode="constant")[size:-size, size:-size] > 0  # a closing
    _, nearest = distance_transform_edt(~seen, return_indices=True)
    nearest_top = top[nearest[0], nearest[1]]
    return np.where(between, nearest_top, low), nearest_top


def footprint_cells(half_m: np.ndarray) -> tuple[int, int]:
    """The height map's shape over a box of half sizes ``half_m`` (m): ``CELL_M`` cells along x, y."""
    return max(1, int(np.ceil(2 * float(half_m[0]) / CELL_M))), max(1, int(np.ceil(2 * float(half_m[1]) / CELL_M)))


def _cell_centres(half_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The x and y (box axes, m) of every height-map cell's centre, float64 [nx, ny] each."""
    nx, ny = footprint_cells(half_m)
    x_m = (np.arange(nx) + 0.5) * CELL_M - float(half_m[0])
    return np.meshgrid(x_m, (np.arange(ny) + 0.5) * CELL_M - float(half_m[1]), indexing="ij")


def height_map(half_m: np.ndarray, own_m: np.ndarray, spacing_m: float) -> np.ndarray:
    """A vehicle's solid top over its box's footprint, in ``CELL_M`` cells from the box's (-x, -y)
    corner, float64 [nx, ny], m in the box's axes (centre 0); ``floor_z`` - 1 where it is not solid.

    Where its own points show the top (:func:`_seen_tops`), that top; in the cells beyond them (the
    cabin's leaning side the lidar did not see, the box's empty corners, the vehicle's far side) the
    class core.

    Args:
        half_m: the box's half sizes, [3], m.
        own_m: its own points in its axes, [P,3], m (those below the floor are left out).
        spacing_m: the lidar's spacing between neighbouring returns on it, m.
    """
    hx, hy, hz = (float(v) for v in half_m)
    floor = floor_z(half_m)
    X, Y = _cell_centres(half_m)
    core = np.full(X.shape, floor - 1.0)
    core[(X >= BODY_X[0] * hx) & (X <= BODY_X[1] * hx) & (np.abs(Y) <= hy - SIDE_INSET_M)] = 0.0
    core[(X >= CABIN_X[0] * hx) & (X <= CABIN_X[1] * hx) & (np.abs(Y) <= hy - CABIN_INSET_M)] = hz - ROOF_INSET_M
    tops = _seen_tops(half_m, own_m, spacing_m, floor, SILHOUETTE_M)
    if tops is None:
        return core
    return np.where(tops[0] > floor, tops[0], core)


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


def _half_cell_samples(step_m: np.ndarray, enter: np.ndarray, stop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Samples along lines (each ``step_m`` [V,3] long, box axes, m) every half ``CELL_M`` of their
    horizontal run from ``enter`` ([V], in units of the line's length) while below ``stop`` ([V]): the
    ray parameters, float64 [V, K] (each row its own samples, the count past them), and how many of
    each row's lie before ``stop``, int [V] (at most ``MAX_SAMPLES``)."""
    dt = 0.5 * CELL_M / _run_per_t(step_m)
    count = np.clip(np.ceil((stop - enter) / dt), 0, MAX_SAMPLES).astype(np.int64)
    return enter[:, None] + np.arange(int(count.max(initial=0)) + 1)[None, :] * dt[:, None], count


def _run_per_t(step_m: np.ndarray) -> np.ndarray:
    """How far lines (each ``step_m`` [V,3] long, m) run horizontally per unit of their parameter, m [V]."""
    return np.maximum(np.hypot(step_m[:, 0], step_m[:, 1]), 1e-9)


def _march(
    top: np.ndarray, floor: float, half_m: np.ndarray, origin_m: np.ndarray, step_m: np.ndarray, enter, leave
) -> np.ndarray:
    """The first fraction of each line (``origin_m`` + t ``step_m``, [V,3]; inside the box's footprint
    for ``enter`` <= t <= ``leave``, [V]) below the height map ``top`` and above ``floor``, sampled
    every half cell of its horizontal run, float64 [V] (inf: none). A line steep enough to stay in
    one cell is sampled at its ends (a vertical line's run is 0: enter and leave)."""
    # each line sampled every half cell of its horizontal run from where it enters (its own samples,
    # whichever lines are marched with it), and where it leaves
    t, _ = _half_cell_samples(step_m, enter, leave)
    t = np.minimum(t, leave[:, None])
    p = origin_m[None, None, :] + t[..., None] * step_m[:, None, :]
    inside = (p[..., 2] >= floor) & (p[..., 2] <= top[_cell_of(p[..., 0], p[..., 1], half_m, top.shape)])
    first = np.argmax(inside, axis=1)
    hit = inside[np.arange(len(step_m)), first]
    return np.where(hit, t[np.arange(len(step_m)), first], np.inf)


#: What a labelled object may cover in a picture (its masks, :func:`cover_map`): the box is the upper
#: bound, cut where the data shows it empty. A vehicle's body may reach this low over its box's floor
#: (real cars' sills 0.2-0.45 m up) ...
COVER_FLOOR_M = 0.2
#: ... but for its wheels, which reach the ground: where a car's axles are (the wheels' centres at
#: 0.55-0.65 of the half length from the centre, radii 0.3-0.4 m), these fractions of the half length,
#: within ``WHEEL_IN_M`` of the box's sides.
WHEEL_X = (0.45, 0.8)
WHEEL_IN_M = 0.35
#: A box's own points (its masks' evidence, :func:`cover_map`) are those within this of it (annotation error).
OWN_MARGIN_M = 0.1
GROUND_M = 0.15  #: an object's own points this low over its box's floor may be the ground's
#: ... but for a vehicle's bottom, an own point this far over its box's floor is its body's, not the street's
LOW_POINT_M = 0.05
COVER_TOP_M = 0.05  #: a cell's top above its highest own point (the returns' spread on a surface)
#: A vehicle box no taller than this is a car's, lower than a roof-mounted lidar (AV2's at about 1.9 m,
#: CARLA's at 1.9-2.4 m), which sees its upper surfaces from above: its own points show its tops. A
#: taller one (a van, a truck, a bus) may rise above the lidar's top row: its top is not cut.
CAR_HEIGHT_M = 2.0
#: Where a car's own points show no top (its far side, a hood behind its cabin), a generous car: full
#: height over this part of its length (fractions of the half length: from an SUV's or a van's tail to a
#: windscreen's foot), and ``CAR_BODY_TOP`` of its height elsewhere (hoods, trunks and belt lines of cars,
#: SUVs and pickups lie at 0.55-0.65 of it).
CAR_CABIN_X = (-0.9, 0.6)
CAR_BODY_TOP = 0.7
CAR_LEAN_M = 0.2  #: the generous car's cabin leans in from the box's sides to its full height over this
#: ... and its corners, seen from above, are cut this far along each side (real cars' bumper corners
#: round off over 0.3-0.5 m)
CAR_CORNER_M = 0.25


#: How far a lidar's line of sight may be off where it passed (the points' noise, the box's tilt), m.
PASSED_TOLERANCE_M = 0.03
LIFT_M = 0.5  #: a line of sight to the street under a car shows its body's underside no higher than this
#: Lines of sight under a car's body through this many cells show its underside's height (the 3rd quartile
#: of theirs): the body's bottom everywhere but at its wheels.
UNDERSIDE_CELLS = 10


def _lines_of_sight(half_m: np.ndarray, own_m: np.ndarray, origins_m: np.ndarray) -> np.ndarray:
    """How high the lidar's lines of sight to the street in a box's footprint (its own points below
    ``GROUND_M``, ``own_m`` [P,3] from ``origins_m`` [P,3] or [3], box axes, m) passed through each
    ``CELL_M`` cell of its footprint below ``LIFT_M``, before their point's cell (each line sampled
    every half cell of its horizontal run): the street seen under the body, m in the box's axes;
    -inf where none passed. float64 [nx, ny]."""
    under = np.full(footprint_cells(half_m), -np.inf)
    hx, hy, hz = (float(v) for v in half_m)
    inside = (np.abs(own_m[:, 0]) <= hx) & (np.abs(own_m[:, 1]) <= hy)
    to_ground = np.flatnonzero(inside & (own_m[:, 2] < -hz + GROUND_M))
    if not len(to_ground):
        return under
    end_m = own_m[to_ground]
    start_m = np.broadcast_to(origins_m, own_m.shape)[to_ground]
    step_m = end_m - start_m
    enter, leave = slab_span(start_m.T, step_m.T, (-hx, -hy, -np.inf), (hx, hy, np.inf), enter_from=0.0)
    last = 1.0 - 1.5 * CELL_M / _run_per_t(step_m)  # short of the point's own cell
    t, count = _half_cell_samples(step_m, enter, last)
    if not count.max(initial=0):
        return under
    valid = (np.arange(t.shape[1])[None, :] < count[:, None]) & (enter <= leave)[:, None]
    p = start_m[:, None, :] + t[..., None] * step_m[:, None, :]
    cell = _cell_of(p[..., 0][valid], p[..., 1][valid], half_m, under.shape)
    z = p[..., 2][valid]
    low = z < -hz + LIFT_M
    np.maximum.at(under, (cell[0][low], cell[1][low]), z[low])
    return under


def _among_seen(X: np.ndarray, Y: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The cells (centres ``X``, ``Y``, m, [nx, ny] each) within the convex hull of the ``seen`` ones
    (bool [nx, ny]), bool [nx, ny]; only the seen ones where they span no area."""
    centres = np.stack([X[seen], Y[seen]], axis=1)
    try:
        hull = ConvexHull(centres)
    except (QhullError, ValueError):  # fewer than three, or all on a line
        return seen
    normals, offsets = hull.equations[:, :2], hull.equations[:, 2]  # inside: normal . p + offset <= 0
    inside = np.all(np.stack([X, Y], axis=-1) @ normals.T + offsets <= 1e-9, axis=-1)
    return inside | seen


def cover_map(
    half_m: np.ndarray,
    own_m: np.ndarray,
    spacing_m: np.ndarray,
    origins_m: np.ndarray | None = None,
    passed=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Where a labelled vehicle may be in its box, as it covers a picture: the top and the bottom of
    each ``CELL_M`` cell of its footprint from the box's (-x, -y) corner, float64 [nx, ny] each, m in
    the box's axes (centre 0); a cell whose top is below its bottom is empty. A mask made from it must
    not under-cover: where neither the data nor the vehicle's shape shows a part empty, it is taken as
    full.

    - A car (a box no taller than ``CAR_HEIGHT_M``): its own points show its top (:func:`_seen_tops`
      above ``GROUND_M``, ``COVER_TOP_M`` over the highest in a cell, the gaps between returns
      closed). A cell they do not show takes its mirror cell's across the car's length if they show
      that (a car is symmetric); amid the cells they show, the highest of them about as near as the
      nearest (:func:`_near_tops`); elsewhere a generous car (``CAR_CABIN_X``, ``CAR_BODY_TOP``,
      ``CAR_LEAN_M``, ``CAR_CORNER_M``). Such a cell is then cut down to where the lidar's lines of sight passed through
      its column (``passed``: a return beyond it, every ``CARVE_STEP_M`` from the top down).
    - A taller vehicle (a van, a truck, a bus): its whole height.
    - The bottom: the body from ``COVER_FLOOR_M`` above the box's floor (the street shows under it),
      the wheels (``WHEEL_X``, ``WHEEL_IN_M``) and the cells holding own points below that (more
      than ``LOW_POINT_M`` up: a skirt, a low bumper) from the floor; higher where the lidar's lines of
      sight to the street under the body passed higher (:func:`_lines_of_sight`).

    Args:
        half_m: the box's half sizes, [3], m.
        own_m: its own points in its axes (centre 0), [P,3], m.
        spacing_m: the lidar's spacing between neighbouring returns at each own point, across and
            along its rows, [P,2], m.
        origins_m: where the lidar was as it measured each own point, box axes, [P,3] or [3], m
            (None: not known; no line of sight bounds the bottom).
        passed: ``(places [M,3], box axes, m) -> bool [M]``: which places a line of sight of the
            sweep passed through (:meth:`lidar.range_image.RangeImage.passed`); None: none is known.
    """
    hx, hy, hz = (float(v) for v in half_m)
    X, Y = _cell_centres(half_m)
    wheels = (np.abs(X) >= WHEEL_X[0] * hx) & (np.abs(X) <= WHEEL_X[1] * hx) & (np.abs(Y) >= hy - WHEEL_IN_M)
    bottom = np.where(wheels, -hz, -hz + COVER_FLOOR_M)
    low = own_m[(own_m[:, 2] > -hz + LOW_POINT_M) & (own_m[:, 2] < -hz + COVER_FLOOR_M)]
    if len(low):  # its own points show the body lower there (a skirt, a bumper): down to the street
        np.minimum.at(bottom, _cell_of(low[:, 0], low[:, 1], half_m, bottom.shape), -hz)
    if 2 * hz > CAR_HEIGHT_M:
        return np.full(X.shape, hz), bottom
    if origins_m is not None:
        under = _lines_of_sight(half_m, own_m, origins_m)
        lifted = np.isfinite(under) & ~wheels  # at the wheels, a line of sight in a cell passed beside a tyre
        bottom[lifted] = np.maximum(bottom[lifted], under[lifted] - PASSED_TOLERANCE_M)
        if lifted.sum() >= UNDERSIDE_CELLS:  # the body's underside: one height
            underside = float(np.quantile(under[lifted], 0.75)) - PASSED_TOLERANCE_M
            bottom[~wheels] = np.maximum(bottom[~wheels], underside)
    body_top = -hz + 2 * hz * CAR_BODY_TOP
    cabin = (X >= CAR_CABIN_X[0] * hx) & (X <= CAR_CABIN_X[1] * hx)
    lean = np.clip((hy - np.abs(Y)) / CAR_LEAN_M, 0.0, 1.0)  # 0 at the box's side, 1 inside the lean
    top = np.where(cabin, body_top + lean * (hz - body_top), body_top)  # the generous car ...
    corner = np.abs(X) - (hx - CAR_CORNER_M) + np.abs(Y) - (hy - CAR_CORNER_M) > CAR_CORNER_M
    top[corner] = bottom[corner] - 1.0  # ... with its corners rounded off
    gaps_m = float(np.median(spacing_m.max(axis=1))) if len(spacing_m) else CELL_M
    tops = _seen_tops(half_m, own_m, gaps_m, -hz + GROUND_M, COVER_TOP_M)
    seen = np.zeros(X.shape, bool)
    if tops is not None:
        seen = tops[0] > -hz
        among = _among_seen(X, Y, seen) & ~seen
        top[among] = np.minimum(_near_tops(tops[0], seen)[among], top[among])
        mirrored = ~seen & seen[:, ::-1]  # a car is its own mirror image across its length
        top[mirrored] = tops[0][:, ::-1][mirrored]
        top[seen] = tops[0][seen]
    if passed is not None:
        top[~seen] = _carved(X[~seen], Y[~seen], top[~seen], bottom[~seen], passed)
    body = own_m[(own_m[:, 2] > -hz + LOW_POINT_M) & (own_m[:, 2] <= hz)]  # every own point of the body
    if len(body):  # a cell holding own points is covered up to them, whatever else says
        np.maximum.at(top, _cell_of(body[:, 0], body[:, 1], half_m, top.shape), body[:, 2] + COVER_TOP_M)
    return top, bottom


CARVE_STEP_M = 0.1  #: a column's lines of sight are looked up this far apart, from its top down


def _carved(x_m: np.ndarray, y_m: np.ndarray, top: np.ndarray, bottom: np.ndarray, passed) -> np.ndarray:
    """The columns at ``x_m``, ``y_m`` (box axes, m, [C] each) from ``bottom`` up to ``top`` ([C] each),
    cut down to below the highest place in them that no line of sight passed through (``passed``),
    looked at every ``CARVE_STEP_M`` from the top down; a column every place of which a line passed
    through is empty (its top ``bottom`` - 1). float64 [C]."""
    levels = int(np.ceil(float(np.max(top - bottom, initial=0.0)) / CARVE_STEP_M)) + 1
    z = top[:, None] - np.arange(levels)[None, :] * CARVE_STEP_M  # [C, L], from the top down
    inside = z >= bottom[:, None]
    places = np.stack(np.broadcast_arrays(x_m[:, None], y_m[:, None], z), axis=-1)[inside]
    empty = np.ones(z.shape, bool)
    empty[inside] = passed(places)
    solid = ~empty & inside
    first = np.argmax(solid, axis=1)  # the highest place no line passed through
    return np.where(solid.any(axis=1), np.minimum(top, z[np.arange(len(top)), first] + CARVE_STEP_M), bottom - 1.0)


def _near_tops(seen_top: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Each cell's highest seen top (``seen_top`` where ``seen``, [nx, ny]) within 1.5 times its distance
    to the nearest seen cell (a gap between the lidar's scan lines: the surface there lies no higher
    than its higher side), float64 [nx, ny]."""
    low = float(seen_top.min()) - 1.0
    distance = distance_transform_edt(~seen)
    out = np.full(seen.shape, low)
    for radius in (1, 2, 4, 8, 16, 32):
        window = maximum_filter(np.where(seen, seen_top, low), size=2 * radius + 1, mode="constant", cval=low)
        pick = (out == low) & (1.5 * distance <= radius)
        out[pick] = window[pick]
    return np.where(out == low, maximum_filter(np.where(seen, seen_top, low), size=65, mode="nearest"), out)


def cover_columns(half_m: np.ndarray, top: np.ndarray, bottom: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A :func:`cover_map` (``top``, ``bottom`` [nx, ny]) as the columns it fills: each non-empty cell's
    centre and half sizes in the box's axes, m, float64 [C,3] each."""
    X, Y = _cell_centres(half_m)
    full = top > bottom
    centres = np.stack([X[full], Y[full], (top[full] + bottom[full]) / 2], axis=1)
    halves = np.stack(
        [np.full(len(centres), CELL_M / 2), np.full(len(centres), CELL_M / 2), (top[full] - bottom[full]) / 2], 1
    )
    return centres, halves
