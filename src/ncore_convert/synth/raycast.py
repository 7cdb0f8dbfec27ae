"""The synthetic world seen: the ray caster (first hit of each ray on the ground and the scene's
boxes, moving boxes at each ray's own time) and the flat-shaded pictures it renders. Lidar returns,
camera pictures and every test's visibility truth come from :func:`cast_rays`.
"""

from __future__ import annotations

import numpy as np

from ncore_convert.synth.scene import GROUND_Z_M, Scene
from ncore_convert.synth.shapes import Shape
from ncore_convert.transforms.camera.models import Pinhole
from ncore_convert.transforms.objects.boxes import convex_span, slab_span


def _azimuth_spans(azimuth_sorted: np.ndarray, offset_m: np.ndarray, sin_half: float) -> list[tuple[int, int]]:
    """The [start, stop) ranges of ``azimuth_sorted`` (ascending, radians) within asin(sin_half) of
    the azimuth of offset_m [3]: one range, or two where the window wraps around ±pi."""
    center = np.arctan2(offset_m[1], offset_m[0])
    half = np.arcsin(min(1.0, sin_half))
    lo, hi = center - half, center + half
    parts = [(lo, hi)]
    if lo < -np.pi:
        parts = [(lo + 2 * np.pi, np.pi), (-np.pi, hi)]
    elif hi > np.pi:
        parts = [(lo, np.pi), (-np.pi, hi - 2 * np.pi)]
    return [
        (int(np.searchsorted(azimuth_sorted, a)), int(np.searchsorted(azimuth_sorted, b, "right"))) for a, b in parts
    ]


SKY_RGB, BUILDING_RGB = (135, 180, 235), (170, 120, 90)
GROUND_RGB = ((90, 90, 90), (150, 150, 130))
CHECKER_M = 10.0  #: the ground's checker squares
SKY = -2  #: the "box index" of a ray that hits nothing, in :func:`render`


def own_colour(seed: int) -> np.ndarray:
    """A box's flat colour drawn from ``seed`` (its index or actor id), uint8 [3]."""
    return np.random.default_rng(int(seed)).integers(30, 230, 3).astype(np.uint8)


def box_colours(scene: Scene) -> np.ndarray:
    """The flat colour of every box of ``scene``, uint8 [B,3]: buildings brown, every other box a
    colour of its own, drawn from its index."""
    return np.array(
        [BUILDING_RGB if b.category == "BUILDING" else own_colour(k) for k, b in enumerate(scene.boxes)], dtype=np.uint8
    ).reshape(-1, 3)


def surface_rgb(box_rgb: np.ndarray, box_index: np.ndarray, xyz_m: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """The flat colour of the surface at each ray's hit, uint8 [N,3]: the sky where nothing is hit,
    the ground checkered in ``CHECKER_M`` squares of the scene's x, y, each box its colour.

    Args:
        box_rgb: each scene box's colour, uint8 [B,3] (:func:`box_colours`); box_index: the hit box
            (index into the scene's boxes; -1 ground), int [N]; xyz_m: the hit [N,3]; hit: whether
            anything was hit, bool [N].
    """
    rgb = np.tile(np.array(SKY_RGB, np.uint8), (len(box_index), 1))
    ground = hit & (box_index < 0)
    square = (np.floor(xyz_m[ground, 0] / CHECKER_M) + np.floor(xyz_m[ground, 1] / CHECKER_M)).astype(int)
    rgb[ground] = np.array(GROUND_RGB, np.uint8)[square % 2]
    boxes = hit & (box_index >= 0)
    rgb[boxes] = box_rgb[box_index[boxes]]
    return rgb


def render(
    scene: Scene,
    box_rgb: np.ndarray,
    T_camera_scene: np.ndarray,
    pinhole: Pinhole,
    step: int,
    t_s: float = 0.0,
    max_range_m: float = 300.0,
    ground_z_m: float = GROUND_Z_M,
    with_index: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """A flat-shaded picture of ``scene`` (moving boxes where they are at ``t_s``): one ray through
    the centre of every ``step`` x ``step`` block of pixels, its colour (:func:`surface_rgb`) over
    the block; and, ``with_index``, what each pixel shows.

    Args:
        T_camera_scene: maps the camera frame (OpenCV: x right, y down, z forward) into the scene.
        pinhole: the camera (its resolution is the picture's), with pixel (i, j) covering
            [i, i+1) x [j, j+1).

    Returns:
        rgb: uint8 [height,width,3]; box_index: what each pixel shows, int [height,width] (an index
        into ``scene.boxes``, -1 the ground, ``SKY`` nothing), None without ``with_index``.
    """
    width, height = pinhole.resolution_px
    rays = pinhole.pixel_rays(step)
    d = rays.reshape(-1, 3) @ T_camera_scene[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = np.broadcast_to(T_camera_scene[:3, 3], d.shape)
    distance, _, index = cast_rays(origins, d, np.full(len(d), t_s), scene, max_range_m, ground_z_m)
    hit = np.isfinite(distance)
    rgb = surface_rgb(box_rgb, index, origins + d * np.where(hit, distance, 0.0)[:, None], hit)

    def full(small: np.ndarray) -> np.ndarray:  # each ray's value over its step x step block
        rows, cols = rays.shape[:2]
        grid = small.reshape(rows, 1, cols, 1, *small.shape[1:])
        blocks = np.broadcast_to(grid, (rows, step, cols, step, *small.shape[1:]))
        return blocks.reshape(rows * step, cols * step, *small.shape[1:])[:height, :width]

    return full(rgb), full(np.where(hit, index, SKY)) if with_index else None


def seen_through(
    scene: Scene,
    T_camera_scene: np.ndarray,
    pinhole: Pinhole,
    t_s: float,
    u_px: np.ndarray,
    v_px: np.ndarray,
    ground_z_m: float = GROUND_Z_M,
) -> tuple[np.ndarray, np.ndarray]:
    """What a camera sees through image points at ``t_s``: the truth its labels are scored against.

    Args:
        T_camera_scene: maps the camera frame (OpenCV) into the scene; pinhole: the camera (NCore's
            pixel-corner convention); u_px, v_px: image points, float [K].

    Returns:
        the z (m, along the optical axis; inf: nothing within 500 m) of the surface hit, and the
        scene box hit (index into ``scene.boxes``; -1: the ground or nothing), [K] each.
    """
    d = pinhole.image_rays(u_px, v_px) @ T_camera_scene[:3, :3].T
    norm = np.linalg.norm(d, axis=1)
    origins = np.broadcast_to(T_camera_scene[:3, 3], d.shape)
    distance, _, index = cast_rays(origins, d / norm[:, None], np.full(len(u_px), t_s), scene, 500.0, ground_z_m)
    # along the ray -> along the optical axis (z = 1 per unit of d)
    return distance / norm, np.where(np.isfinite(distance), index, -1)


#: Slack of the bounding-sphere test in cast_rays (metres): far above rounding, far below a box.
SPHERE_MARGIN_M = 1e-3


def _near_sphere(origins_m: np.ndarray, directions: np.ndarray, center_m: np.ndarray, radius_m: float) -> np.ndarray:
    """Which rays (``origins_m``, unit ``directions``: [K,3]) pass within ``radius_m`` (+
    ``SPHERE_MARGIN_M``) of ``center_m`` [3] ahead of their origin (bool [K]): the only ones that
    can hit what that sphere bounds. One shared origin (stride 0, a camera's) is not gathered."""
    if not len(directions):
        return np.zeros(0, dtype=bool)
    if origins_m.strides[0] == 0:
        w = center_m - origins_m[0]  # [3]
        along, w2 = directions @ w, float(w @ w)
    else:
        w = center_m - origins_m  # [K,3]
        along, w2 = np.einsum("ij,ij->i", directions, w), np.einsum("ij,ij->i", w, w)
    ahead = np.maximum(along, 0.0)
    return w2 - ahead * ahead <= (radius_m + SPHERE_MARGIN_M) ** 2


def _gather(sorted_rows: np.ndarray, spans: list[tuple[int, int, np.ndarray]]) -> np.ndarray:
    """The rows of ``sorted_rows`` [N,...] picked by each span (start, stop, mask over the span), in
    order: ``rows[idx]`` read from the sorted copy's contiguous slices instead of gathered."""
    return np.concatenate([sorted_rows[a:z][m] for a, z, m in spans])


#: Rays per convex_span call in :func:`first_entry` (rays x faces arrays stay small).
CHUNK_RAYS = 16384


def first_entry(
    origins_m: np.ndarray, directions: np.ndarray, shape: Shape, bound_enter: np.ndarray, bound_leave: np.ndarray
) -> np.ndarray:
    """Where rays (box axes: ``origins_m``, unit ``directions`` [K,3]) first enter one of ``shape``'s
    parts ahead of their origin, each part cut to the shape's bound (the rays' span through it:
    ``bound_enter``, ``bound_leave`` [K], from the slab test), metres along the ray (inf: they miss
    it), float64 [K]. Each part tests only the rays that meet its own box."""
    out = np.full(len(directions), np.inf)
    for p in range(len(shape.normals)):
        enter_box, leave_box = slab_span(origins_m.T, directions.T, shape.part_lo_m[p], shape.part_hi_m[p])
        rays = np.flatnonzero((enter_box <= leave_box) & (leave_box > 0))
        for chunk in np.array_split(rays, max(1, -(-len(rays) // CHUNK_RAYS))):
            enter, leave = convex_span(
                origins_m[chunk], directions[chunk], shape.normals[p : p + 1], shape.offsets_m[p : p + 1]
            )
            enter = np.maximum(enter[:, 0], bound_enter[chunk])
            leave = np.minimum(leave[:, 0], bound_leave[chunk])
            entry = np.where((enter <= leave) & (enter > 0), enter, np.inf)
            out[chunk] = np.minimum(out[chunk], entry)
    return out


def cast_rays(
    origins_m: np.ndarray,
    directions: np.ndarray,
    times_s: np.ndarray,
    scene: Scene,
    max_range_m: float,
    ground_z_m: float = GROUND_Z_M,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of each ray against the ground plane z = ``ground_z_m`` and the scene boxes.

    Args:
        origins_m: ray origins [N,3]; directions: unit directions [N,3]; times_s: ray times [N]
            (moving boxes are placed at each ray's own time). All in the scene's frame.

    Returns:
        range_m [N] (inf where nothing is hit within max_range_m), the hit intensity [N] (uint8)
        and the index of the hit box in ``scene.boxes`` [N] (-1: the ground or nothing).
    """
    one_origin = origins_m.strides[0] == 0  # a camera's rays (broadcast from one point)
    if not one_origin:  # a strided view (a pose stack's translations) gathers slowly
        origins_m = np.ascontiguousarray(origins_m)
    n = len(origins_m)
    best = np.full(n, np.inf)
    intensity = np.zeros(n, dtype=np.uint8)
    box_index = np.full(n, -1, dtype=np.int64)
    if not n:
        return best, intensity, box_index
    down = directions[:, 2] < -1e-9
    s_ground = np.full(n, np.inf)
    s_ground[down] = (ground_z_m - origins_m[down, 2]) / directions[down, 2]
    hit = (s_ground > 0) & (s_ground < best)
    best[hit] = s_ground[hit]
    intensity[hit] = 12
    # the origins' bounding box: its centre, and the reach of its corners from there in x, y
    lo_m, hi_m = (origins_m[0], origins_m[0]) if one_origin else (origins_m.min(0), origins_m.max(0))
    center_m, spread_m = (lo_m + hi_m) / 2, float(np.linalg.norm(hi_m[:2] - lo_m[:2])) / 2
    half_span_s = float(np.ptp(times_s)) / 2
    one_time = half_span_s == 0.0  # a picture's rays: each moving box placed once
    t_mid_s = float(times_s[0]) if one_time else float(np.median(times_s))
    # every box at once: its bound, bounding-sphere radius, motion over the rays' times, centre then
    bounds = [box.bound_m for box in scene.boxes]
    lo_all, hi_all = (np.array([bound[k] for bound in bounds]).reshape(-1, 3) for k in (0, 1))
    box_reach_m = np.linalg.norm(np.maximum(-lo_all, hi_all), axis=1)
    velocity_mps = np.array([box.velocity_mps for box in scene.boxes]).reshape(-1, 3)
    motion_m = np.linalg.norm(velocity_mps, axis=1) * half_span_s
    span_s = np.array([(box.move_from_s, box.move_until_s) for box in scene.boxes]).reshape(-1, 2)
    centers_m = np.array([box.center0_m for box in scene.boxes]).reshape(-1, 3)
    centers_m = centers_m + np.clip(t_mid_s, span_s[:, 0], span_s[:, 1])[:, None] * velocity_mps
    # the rays sorted by azimuth, so that the rays towards a box are contiguous slices (a stable
    # sort: a picture's rows and a lidar's firing order are runs already in order, which it merges)
    azimuth = np.arctan2(directions[:, 1], directions[:, 0])
    order = np.argsort(azimuth, kind="stable")
    azimuth_sorted, directions_sorted = azimuth[order], directions[order]
    origins_sorted = origins_m if one_origin else origins_m[order]
    for b, box in enumerate(scene.boxes):
        # Only rays whose azimuth points at the box can hit it: seen from the origins' centre, the box
        # (at the rays' middle time) lies within a disc of radius r, padded by the spread of the
        # origins and the box's motion over the rays' times.
        center = centers_m[b]
        r = box_reach_m[b] + spread_m + motion_m[b]
        distance = np.linalg.norm(center[:2] - center_m[:2])
        if distance - r > max_range_m:
            continue
        spans = [(0, n)] if distance <= r else _azimuth_spans(azimuth_sorted, center - center_m, r / distance)
        # of those, the rays that pass the box's bounding sphere (padded by its motion)
        reach_m = box_reach_m[b] + motion_m[b]
        near = [(a, z, _near_sphere(origins_sorted[a:z], directions_sorted[a:z], center, reach_m)) for a, z in spans]
        idx = np.concatenate([order[a:z][m] for a, z, m in near])
        if not len(idx):
            continue
        moving = np.any(box.velocity_mps)
        if one_origin and (one_time or not moving):  # one origin in the box frame (the box where it is then)
            placed_m = center if moving else box.center0_m
            o_b = np.broadcast_to((origins_m[:1] - placed_m) @ box.rotation, (len(idx), 3))
        elif moving:
            o_b = (_gather(origins_sorted, near) - box.center_m(times_s[idx])) @ box.rotation
        else:
            o_b = (_gather(origins_sorted, near) - box.center0_m) @ box.rotation
        d_b = _gather(directions_sorted, near) @ box.rotation
        t_near, t_far = slab_span(o_b.T, d_b.T, *bounds[b])
        if box.shape is None:
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < best[idx])
        else:  # what the rays through its bound (from outside it or from within) hit of the object itself
            through = (t_near <= t_far) & (t_far > 0) & (t_near < best[idx])
            entry = np.full(len(idx), np.inf)
            entry[through] = first_entry(o_b[through], d_b[through], box.shape, t_near[through], t_far[through])
            t_near, hit = entry, entry < best[idx]
        nearer = idx[hit]  # idx holds each ray once (the spans are disjoint): write only the hits
        best[nearer], intensity[nearer], box_index[nearer] = t_near[hit], box.intensity, b
    best[best > max_range_m] = np.inf
    return best, intensity, box_index
