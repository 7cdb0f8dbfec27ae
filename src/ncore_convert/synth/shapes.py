"""What the generator's objects are inside their boxes: a shape is a union of a few convex parts
(boxes cut by sloped planes, octagonal wheels), in its box's own axes (x forward, y left, z up,
metres, the box centre at 0). The box stays the annotation (tight, as annotators draw it); the
shape is what the lidar and the cameras hit (:func:`synth.raycast.cast_rays`).

- a vehicle: a body with ground clearance, a sloped hood and trunk and cut corners; a narrower,
  shorter cabin with raked windscreen and rear window and sides that lean in; four wheels; two
  mirrors that stick out of the box's sides (as real annotators leave them);
- a pedestrian: legs mid-stride, a torso, arms and a head, well inside the box;
- a cyclist: a rider bent over a bicycle (two thin wheels, a frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

MIRROR_OUT_M = 0.2  #: how far a vehicle's mirrors reach out of its box's sides
CLEARANCE_M = 0.3  #: a vehicle body's lowest edge above the ground (the wheels below it)


@dataclass(frozen=True)
class Shape:
    """A union of convex parts, each the points p with n . p <= offset for every face (n, offset),
    cut to the bound ``lo_m``..``hi_m``: what rays can hit stays inside it whatever the box's size (a
    small box's wheel or mirror would reach out of it).

    Attributes:
        normals: unit outward face normals, float64 [P,F,3] (padding faces: normal 0, offset 1);
        offsets_m: float64 [P,F]; lo_m, hi_m: the bound, float64 [3] each; part_lo_m, part_hi_m:
        each part's own bounding box within the bound, float64 [P,3] each.
    """

    normals: np.ndarray
    offsets_m: np.ndarray
    lo_m: np.ndarray
    hi_m: np.ndarray
    part_lo_m: np.ndarray
    part_hi_m: np.ndarray


def _block(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> list[tuple[np.ndarray, float]]:
    """An axis-aligned block's six faces."""
    faces = []
    for k in range(3):
        n = np.zeros(3)
        n[k] = 1.0
        faces += [(n, float(hi[k])), (-n, -float(lo[k]))]
    return faces


def _cut(normal: tuple[float, float, float], through: tuple[float, float, float]) -> tuple[np.ndarray, float]:
    """A face with outward ``normal`` through the point ``through``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    return n, float(n @ np.asarray(through, float))


def _edge_cut(axis: int, a: tuple[float, float], b: tuple[float, float], outward: tuple[float, float]):
    """A face along the line from ``a`` to ``b`` in the plane of the two axes other than ``axis``
    (coordinates in their order), parallel to ``axis``; ``outward`` says which side is outside."""
    u, w = (k for k in range(3) if k != axis)
    d = np.subtract(b, a)
    n2 = np.array([d[1], -d[0]])
    if n2 @ np.asarray(outward) < 0:
        n2 = -n2
    n = np.zeros(3)
    n[u], n[w] = n2
    point = np.zeros(3)
    point[u], point[w] = a
    return _cut(tuple(n), tuple(point))


def _wheel(centre: tuple[float, float, float], radius_m: float, half_width_m: float) -> list:
    """An octagonal wheel around an axle along y, its vertices on the circle of ``radius_m``."""
    apothem = radius_m * np.cos(np.pi / 8)
    faces = []
    for k in range(8):
        a = (k + 0.5) * np.pi / 4
        n = np.array([np.cos(a), 0.0, np.sin(a)])
        faces.append((n, float(n @ np.asarray(centre)) + apothem))
    y = np.array([0.0, 1.0, 0.0])
    return faces + [(y, centre[1] + half_width_m), (-y, -(centre[1] - half_width_m))]


def _extent(faces: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box of a bounded convex part, from its vertices (every three faces that meet in
    one point inside all the others), [3] each."""
    normals = np.array([n for n, _ in faces])
    offsets = np.array([d for _, d in faces])
    vertices = []
    for trio in combinations(range(len(faces)), 3):
        A = normals[list(trio)]
        if abs(np.linalg.det(A)) > 1e-9:
            p = np.linalg.solve(A, offsets[list(trio)])
            if np.all(normals @ p <= offsets + 1e-9):
                vertices.append(p)
    if not vertices:  # empty (a small box's body lower than its clearance), or outside the bound
        return np.full(3, np.inf), np.full(3, -np.inf)
    vertices = np.array(vertices)
    return vertices.min(axis=0), vertices.max(axis=0)


def _shape(parts: list[list[tuple[np.ndarray, float]]], lo: np.ndarray, hi: np.ndarray) -> Shape:
    """The shape of ``parts`` (lists of faces) within the bound ``lo``..``hi`` [3] (a part with
    nothing inside it has an empty box: no ray hits it)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    extents = [_extent(part + _block(tuple(lo), tuple(hi))) for part in parts]
    faces = max(len(p) for p in parts)
    normals = np.zeros((len(parts), faces, 3))
    offsets = np.ones((len(parts), faces))
    for i, part in enumerate(parts):
        for j, (n, d) in enumerate(part):
            normals[i, j], offsets[i, j] = n, d
    return Shape(normals, offsets, lo, hi, np.array([e[0] for e in extents]), np.array([e[1] for e in extents]))


def vehicle_shape(dims_m: np.ndarray) -> Shape:
    """A car in its tight box of ``dims_m`` (length, width, height), mirrors out of its sides."""
    length, width, height = (float(v) for v in dims_m)
    xf, yw, zb, zt = length / 2, width / 2, -height / 2, height / 2
    belt = zb + 0.58 * height  # the body's top (the windows' lower edge)
    radius = float(np.clip(0.21 * height, 0.28, 0.40))
    body = _block((-xf, -yw, zb + CLEARANCE_M), (xf, yw, belt))
    body += [
        _edge_cut(1, (xf, zb + 0.42 * height), (xf - 0.25 * length, belt), (1.0, 1.0)),  # hood
        _edge_cut(1, (-xf, zb + 0.50 * height), (-xf + 0.12 * length, belt), (-1.0, 1.0)),  # trunk
    ]
    for sx in (-1.0, 1.0):  # cut corners, seen from above
        for sy in (-1.0, 1.0):
            body.append(_edge_cut(2, (sx * xf, sy * (yw - 0.3)), (sx * (xf - 0.3), sy * yw), (sx, sy)))
    x_rear, x_front = -xf + 0.18 * length, xf - 0.28 * length  # the cabin's foot
    rise = zt - belt
    side = yw - 0.06
    cabin = _block((x_rear, -side, belt - 0.02), (x_front, side, zt))
    cabin += [
        _edge_cut(1, (x_front, belt), (x_front - 1.2 * rise, zt), (1.0, 1.0)),  # windscreen
        _edge_cut(1, (x_rear, belt), (x_rear + 0.7 * rise, zt), (-1.0, 1.0)),  # rear window
        _edge_cut(0, (side, belt), (side - 0.16, zt), (1.0, 1.0)),  # the sides lean in
        _edge_cut(0, (-side, belt), (-side + 0.16, zt), (-1.0, 1.0)),
    ]
    wheels = [
        _wheel((sx * 0.31 * length, sy * (yw - 0.13), zb + radius), radius, 0.11)
        for sx in (-1.0, 1.0)
        for sy in (-1.0, 1.0)
    ]
    x_mirror = x_front - 0.1
    mirrors = [
        _block((x_mirror - 0.15, yw - 0.02, belt + 0.02), (x_mirror, yw + MIRROR_OUT_M, belt + 0.17)),
        _block((x_mirror - 0.15, -yw - MIRROR_OUT_M, belt + 0.02), (x_mirror, -yw + 0.02, belt + 0.17)),
    ]
    reach = np.array([xf, yw + MIRROR_OUT_M, zt])
    return _shape([body, cabin, *wheels, *mirrors], -reach, reach)


def pedestrian_shape(dims_m: np.ndarray) -> Shape:
    """A person mid-stride in a box of ``dims_m``: legs, torso, arms and head (parts scaled from a
    0.6 x 0.6 x 1.7 m box)."""
    s = np.asarray(dims_m, float) / np.array([0.6, 0.6, 1.7])
    zb = -float(dims_m[2]) / 2

    def block(x, y, z):  # centre x, y and half sizes in the 0.6 x 0.6 x 1.7 box; z from the ground
        (cx, hx), (cy, hy), (z0, z1) = x, y, z
        return _block(
            (s[0] * (cx - hx), s[1] * (cy - hy), zb + s[2] * z0), (s[0] * (cx + hx), s[1] * (cy + hy), zb + s[2] * z1)
        )

    parts = [
        block((0.09, 0.07), (0.1, 0.075), (0.0, 0.82)),  # legs, one ahead, one behind
        block((-0.09, 0.07), (-0.1, 0.075), (0.0, 0.82)),
        block((0.0, 0.11), (0.0, 0.19), (0.78, 1.40)),  # torso
        block((0.06, 0.05), (0.25, 0.045), (0.80, 1.36)),  # arms, swinging
        block((-0.06, 0.05), (-0.25, 0.045), (0.80, 1.36)),
        block((0.01, 0.09), (0.0, 0.08), (1.43, 1.70)),  # head
    ]
    half = np.asarray(dims_m, float) / 2
    return _shape(parts, -half, half)


def cyclist_shape(dims_m: np.ndarray) -> Shape:
    """A rider on a bicycle in a box of ``dims_m`` (parts scaled from a 1.8 x 0.6 x 1.7 m box)."""
    s = np.asarray(dims_m, float) / np.array([1.8, 0.6, 1.7])
    zb = -float(dims_m[2]) / 2

    def block(x, y, z):  # x and z ranges, y centre and half size in the 1.8 x 0.6 x 1.7 box
        (x0, x1), (cy, hy), (z0, z1) = x, y, z
        return _block((s[0] * x0, s[1] * (cy - hy), zb + s[2] * z0), (s[0] * x1, s[1] * (cy + hy), zb + s[2] * z1))

    radius = 0.34 * s[2]
    parts = [
        _wheel((s[0] * 0.55, 0.0, zb + radius), radius, 0.02 * s[1]),
        _wheel((-s[0] * 0.55, 0.0, zb + radius), radius, 0.02 * s[1]),
        block((-0.55, 0.55), (0.0, 0.03), (0.50, 0.60)),  # frame
        block((-0.30, 0.20), (0.0, 0.18), (0.95, 1.42)),  # back, bent forward
        block((0.12, 0.34), (0.0, 0.09), (1.42, 1.70)),  # head
        block((-0.12, 0.08), (0.12, 0.06), (0.30, 0.95)),  # legs on the pedals
        block((-0.12, 0.08), (-0.12, 0.06), (0.30, 0.95)),
        block((0.10, 0.50), (0.18, 0.04), (1.10, 1.22)),  # arms to the handlebar
        block((0.10, 0.50), (-0.18, 0.04), (1.10, 1.22)),
    ]
    half = np.asarray(dims_m, float) / 2
    return _shape(parts, -half, half)


#: The shape of each class that has one (the others are their boxes).
SHAPES = {
    "REGULAR_VEHICLE": vehicle_shape,
    "VEHICLE": vehicle_shape,  # OPV2V / V2XSet
    "PEDESTRIAN": pedestrian_shape,
    "BICYCLIST": cyclist_shape,
}


def shape_of(category: str, dims_m: np.ndarray) -> Shape | None:
    """The shape of an object of ``category`` in a box of ``dims_m``, None for a plain box."""
    make = SHAPES.get(category)
    return make(np.asarray(dims_m, float)) if make else None
