"""A vehicle's cover map from every sweep of its track (``objects.track_shapes``, issue 74).

A parked car, its annotated box 10 cm wider than its body each side, is passed by the ego: the first
sweep sees its near side from y = -10 m, a later one its far side from y = +10 m. The lines of sight
of a sweep pass through every place outside the body that is on its side of the car or above its
roof; the places behind the body stay unseen. Truth: the body's cells and heights.
"""

from __future__ import annotations

import numpy as np

from ncore_convert.transforms.objects.cores import cover_columns, cover_map
from ncore_convert.transforms.objects.track_shapes import TrackShapes

VEHICLES = {"REGULAR_VEHICLE", "LARGE_VEHICLE", "BUS", "BOX_TRUCK", "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER"}

HALF_M = np.array([2.3, 1.0, 0.8])  # the annotated box
BODY_M = np.array([2.0, 0.9])  # the body's half length and width
ROOF_M = 0.35  # its top, box axes
SIDES = (-1.0, 1.0)  # where each sweep's lidar stands: y = side x 10 m


def _body_points(side: float) -> np.ndarray:
    """The returns one sweep takes of the body from its side: its near flank and the near half of its roof."""
    x = np.arange(-1.95, 1.96, 0.05)
    z = np.arange(-0.45, ROOF_M, 0.05)
    flank = np.stack(np.broadcast_arrays(x[:, None], side * BODY_M[1], z[None, :]), axis=-1).reshape(-1, 3)
    y = np.arange(0.0, BODY_M[1], 0.05) * side
    roof = np.stack(np.broadcast_arrays(x[:, None], y[None, :], ROOF_M), axis=-1).reshape(-1, 3)
    return np.concatenate([flank, roof])


class _Sight:
    """A sweep's lines of sight from ``side``: every place outside the body (5 cm clear of it) on that
    side of the car or above its roof."""

    def __init__(self, side: float) -> None:
        self.side = side

    def passed(self, xyz_m: np.ndarray) -> np.ndarray:
        outside = (np.abs(xyz_m[:, 0]) > BODY_M[0] + 0.05) | (np.abs(xyz_m[:, 1]) > BODY_M[1] + 0.05)
        outside |= xyz_m[:, 2] > ROOF_M + 0.05
        on_its_side = xyz_m[:, 1] * self.side > 0
        return outside & (on_its_side | (xyz_m[:, 2] > ROOF_M + 0.05))


def _covered_volume(top: np.ndarray, bottom: np.ndarray) -> float:
    _, halves = cover_columns(HALF_M, top, bottom)
    return float(np.sum(8 * np.prod(halves, axis=1)))


def _body_top_covered(top: np.ndarray) -> float:
    """The share of the body's footprint cells covered up to its roof (less a cell's rounding)."""
    nx, ny = top.shape
    x = (np.arange(nx) + 0.5) * 0.06 - HALF_M[0]
    y = (np.arange(ny) + 0.5) * 0.06 - HALF_M[1]
    body = (np.abs(x)[:, None] < BODY_M[0] - 0.06) & (np.abs(y)[None, :] < BODY_M[1] - 0.06)
    return float(np.mean(top[body] >= ROOF_M - 0.01))


def test_a_parked_cars_far_side_seen_later_tightens_its_mask_and_keeps_it_whole():
    T_box_world = np.eye(4)[None]
    origins = {side: np.array([0.0, 10.0 * side, 1.0]) for side in SIDES}
    points = {side: _body_points(side) for side in SIDES}
    spacing = {side: np.full((len(points[side]), 2), 0.05) for side in SIDES}
    # the first sweep's own map (what a frame near it got before issue 74)
    first = cover_map(HALF_M, points[-1.0], spacing[-1.0], origins[-1.0], _Sight(-1.0).passed)
    shapes = TrackShapes()
    for side in SIDES:
        shapes.gather(["car"], T_box_world, HALF_M[None], points[side], spacing[side], origins[side], _Sight(side))
    pooled = shapes.cover("car", HALF_M)
    assert pooled is not None
    assert _body_top_covered(pooled[0]) == 1.0 and _body_top_covered(first[0]) == 1.0  # recall kept
    # the box's margin beyond the far flank: the first sweep never looked there, the later one did
    volume_first, volume_pooled = _covered_volume(*first), _covered_volume(*pooled[:2])
    assert volume_pooled < volume_first - 0.2, (volume_first, volume_pooled)
    nx, ny = pooled[0].shape
    far_margin = (np.arange(ny) + 0.5) * 0.06 - HALF_M[1] > BODY_M[1] + 0.06
    assert np.all(pooled[0][:, far_margin] < pooled[1][:, far_margin])  # empty now
    assert np.any(first[0][:, far_margin] > first[1][:, far_margin])  # covered by the first sweep's map


def test_a_box_of_another_size_or_never_gathered_gets_no_pooled_map():
    shapes = TrackShapes()
    shapes.gather(
        ["car"],
        np.eye(4)[None],
        HALF_M[None],
        _body_points(-1.0),
        np.full((1, 2), 0.05).repeat(len(_body_points(-1.0)), 0),
        np.array([0.0, -10.0, 1.0]),
        _Sight(-1.0),
    )
    assert shapes.cover("car", HALF_M) is not None
    assert shapes.cover("car", HALF_M + 0.2) is None
    assert shapes.cover("other", HALF_M) is None


def test_real_av2_parked_vehicles_pooled_over_both_sweeps_keep_their_bodies(av2_sample_root):
    """On the real AV2 sample (2 sweeps, annotations, the real ring cameras at each sweep's ego
    pose): each vehicle annotated in both sweeps whose boxes lie within 0.5 m is pooled at its median
    box over both sweeps (as the labeller pools a static track). Its pooled mask holds >= 99.5 % of
    the pixels of its body's own points (0.3 m over its box's floor) of both sweeps: real bodies,
    real annotation jitter, real lines of sight."""
    from upath import UPath

    from ncore_convert.converters.argoverse2.plan import camera_pinhole
    from ncore_convert.sources import argoverse2 as av2
    from ncore_convert.sources import argoverse2_annotations as av2_annotations
    from ncore_convert.transforms.camera.labels import box_index
    from ncore_convert.transforms.camera.visibility import CameraView
    from ncore_convert.transforms.geometry import invert_se3
    from ncore_convert.transforms.lidar.range_image import RangeImage
    from ncore_convert.transforms.objects.boxes import in_box
    from ncore_convert.transforms.objects.dynamic import static_pose

    log = av2.log_dir(UPath(av2_sample_root), "val", "7fab2350-7eaf-3b7e-a39d-6937a4c1bede")
    intrinsics, T_sensor_ego = av2.read_intrinsics(log), av2.read_sensor_extrinsics(log)
    pose_ns, T_ego_city = av2.read_ego_poses(log)
    boxes = av2_annotations.read_annotations(log)
    lidar_ego_m = np.mean([T_sensor_ego[u][:3, 3] for u in ("up_lidar", "down_lidar")], axis=0)
    sweeps = []
    for ts in av2.list_sweep_timestamps_ns(log):
        T = T_ego_city[np.searchsorted(pose_ns, ts)]
        xyz = av2.read_sweep(log, int(ts)).xyz_ego_m.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        sweeps.append((int(ts), T, xyz, T[:3, :3] @ lidar_ego_m + T[:3, 3]))
    parked = {}
    for uuid in set(boxes.track_uuids):
        rows = [
            r
            for r in np.flatnonzero(np.isin(boxes.timestamps_ns, [ts for ts, *_ in sweeps]))
            if boxes.track_uuids[r] == uuid and boxes.categories[r] in VEHICLES
        ]
        rows = sorted(rows, key=lambda r: boxes.timestamps_ns[r])
        if len(rows) != len(sweeps):
            continue
        T_city = np.stack([sweeps[i][1] @ boxes.T_object_ego[r] for i, r in enumerate(rows)])
        if np.linalg.norm(T_city[0, :3, 3] - T_city[1, :3, 3]) <= 0.5:
            centre, R, dims = static_pose(T_city[:, :3, 3], T_city[:, :3, :3], boxes.dims_m[rows])
            T_box = np.eye(4)
            T_box[:3, :3], T_box[:3, 3] = R, centre
            parked[uuid] = (T_box, dims / 2, T_city, boxes.dims_m[rows] / 2)
    assert len(parked) >= 5, len(parked)
    shapes = TrackShapes()
    keys = list(parked)
    T_boxes = np.stack([parked[k][0] for k in keys])
    halves = np.stack([parked[k][1] for k in keys])
    for _, _, xyz, origin in sweeps:
        spacing = np.linalg.norm(xyz - origin, axis=1)[:, None] * np.radians([0.2, 4.0])
        shapes.gather(keys, T_boxes, halves, xyz, spacing, origin, RangeImage(xyz, origin))
    shares = []
    for _, T, xyz, _ in sweeps:
        for cam in av2.RING_CAMERAS:
            view = CameraView(cam, 0, invert_se3(T @ T_sensor_ego[cam]), camera_pinhole(intrinsics[cam]))
            width, height = view.pinhole.resolution_px
            for k, key in enumerate(keys):
                body = []
                for (_, _, other, _), T_city, half in zip(sweeps, parked[key][2], parked[key][3], strict=True):
                    inside = other[in_box(other, T_city[:3, 3], T_city[:3, :3], half)]
                    body.append(inside[(inside - T_city[:3, 3]) @ T_city[:3, 2] > 0.3 - half[2]])
                body = np.concatenate(body)
                xyz_camera = body @ view.T_world_camera[:3, :3].T + view.T_world_camera[:3, 3]
                if len(body) < 50 or np.any(xyz_camera[:, 2] <= 0.3):
                    continue
                u, v = view.pinhole.project(xyz_camera)
                if np.any((u < 0) | (u >= width) | (v < 0) | (v >= height)):
                    continue
                picture = box_index(view, T_boxes[k : k + 1], halves[k : k + 1], None, xyz, None, None, {}, [key])
                pooled = box_index(
                    view, T_boxes[k : k + 1], halves[k : k + 1], None, xyz, None, None, {}, [key], None, shapes
                )
                assert np.any(pooled.index != picture.index) or shapes.cover(key, halves[k]) is None
                shares.append(float(np.mean(pooled.index[v.astype(np.int64), u.astype(np.int64)] == 0)))
    assert len(shares) >= 10, len(shares)
    assert min(shares) >= 0.995, sorted(shares)[:5]


class _Blind:
    """Lines of sight that passed nowhere."""

    @staticmethod
    def passed(xyz_m: np.ndarray) -> np.ndarray:
        return np.zeros(len(xyz_m), bool)


def test_annotated_boxes_that_jitter_are_registered_before_their_points_pool():
    """A car seen from both sides in each of three sweeps, annotated 12-18 cm off from sweep to sweep
    (a human's boxes): each sweep's points are registered to the first's (offsets within 1 cm of
    the true jitter differences), so the pooled body is one car, not three; a sweep whose points do
    not agree (a wall through the box, which fits the car's flank only 0.9 m away) pools nothing and
    its frames keep their own map."""
    y, z = np.meshgrid(np.arange(-0.85, 0.86, 0.05), np.arange(-0.45, ROOF_M, 0.05), indexing="ij")
    ends = [np.stack(np.broadcast_arrays(x, y, z), axis=-1).reshape(-1, 3) for x in (-BODY_M[0], BODY_M[0])]
    body_m = np.concatenate([_body_points(-1.0), _body_points(1.0), *ends])  # seen all round over the sweeps
    jitter_m = np.array([[0.0, 0.0, 0.0], [0.15, -0.12, 0.0], [-0.18, 0.1, 0.02]])
    shapes = TrackShapes()
    for s, j in enumerate(jitter_m):
        T_annotated = np.eye(4)
        T_annotated[:3, 3] = j  # the box as annotated; the car stands at the origin
        shapes.gather(
            ["car"],
            T_annotated[None],
            HALF_M[None],
            body_m,
            np.full((len(body_m), 2), 0.05),
            np.array([0, -10.0, 1]),
            _Blind(),
            register=np.array([True]),
            time_us=s * 100_000,
        )
    for s, j in enumerate(jitter_m):
        top, bottom, offset_m = shapes.cover("car", HALF_M, s * 100_000 + 10_000)
        # the pooled shape lies at the first sweep's box: sweep s's box axes are off it by j_s - j_0
        assert np.allclose(offset_m, j - jitter_m[0], atol=0.01), (s, offset_m)
    kept = shapes.evidence("car").own_m
    assert len(kept) <= 1.2 * len(np.unique(np.floor(body_m / 0.03), axis=0))  # one car's voxels, not three
    wall = np.stack(np.broadcast_arrays(np.linspace(-2, 2, 80)[:, None], 0.0, np.linspace(-0.7, 0.7, 30)), -1)
    T_annotated = np.eye(4)
    shapes.gather(
        ["car"],
        T_annotated[None],
        HALF_M[None],
        wall.reshape(-1, 3),
        np.full((2400, 2), 0.05),
        np.array([0, -10.0, 1]),
        _Blind(),
        register=np.array([True]),
        time_us=300_000,
    )
    assert shapes.cover("car", HALF_M, 300_000) is None
    assert shapes.cover("car", HALF_M, 0) is not None
