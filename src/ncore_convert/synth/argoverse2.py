"""Synthetic Argoverse 2 Sensor and TbV logs, byte-compatible with the real on-disk formats, with known truth.

The lidar is a simulation of AV2's two VLP-32C units (real beam table, 55.296 µs firing cycle with
paired firings, opposite spin in their own frames, 180° apart) cast against :mod:`.scene`, then
ego-motion compensated to the sweep time and quantised to float16, as in the real data. The units
are phase-locked to a 100 ms clock, and the cameras are triggered on that clock when a unit's
firing azimuth crosses their optical axis, with the ~0.1 ms lag measured on real AV2 data.

A TbV log (``SynthConfig.tbv``) has TbV's differences: a TbV-style log id, no offset_ns column, the
7 ring cameras only (six at half resolution) and no annotations.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pyarrow as pa
from scipy.spatial.transform import Rotation
from upath import UPath

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth.av2_config import MAX_RANGE_M, SweepTruth, SynthConfig, SynthTruth
from ncore_convert.synth.av2_images import write_images
from ncore_convert.synth.ego import EGO_CAMERAS, true_mask
from ncore_convert.synth.feather import write_feather_table
from ncore_convert.synth.maps import write_map
from ncore_convert.synth.raycast import cast_rays
from ncore_convert.synth.scene import Box, Scene, make_scene
from ncore_convert.transforms.geometry import invert_se3, quat_wxyz_from_se3, se3_from_quat_wxyz, transform_points
from ncore_convert.transforms.lidar import vlp32c
from ncore_convert.transforms.objects.boxes import PointGrid, points_in_box

TBV_LIDAR_SCHEMA = pa.schema([f for f in av2.LIDAR_SCHEMA if f.name != "offset_ns"])
SWEEP_PERIOD_NS = 100_000_000
TRAFFIC_STREAM = 1  #: the scene's traffic and annotation jitter draw from their own stream of the seed
#: Start of each unit's sweep window after the sweep timestamp (real data: up ~2.7 ms, down ~6 ms).
UNIT_WINDOW_START_NS = {"up_lidar": 2_650_000, "down_lidar": 6_000_000}
#: Own-frame spin direction (+1 counter-clockwise about +z) and column azimuth at sweep offset 0.
UNIT_SPIN = {"up_lidar": (-1.0, np.radians(144.0)), "down_lidar": (+1.0, np.radians(24.0))}
#: Image timestamps lag a unit's crossing of the camera axis by this much (measured on real AV2).
CAMERA_TRIGGER_DELAY_NS = 100_000
TBV_SEASONS = ("Spring_2020", "Summer_2020", "Autumn_2020", "Winter_2020", "Winter_2021", "Summer_2019", "Autumn_2019")
#: Camera optical-axis yaw in the ego frame (deg), mounting position (m), focal length (px), as in AV2.
CAMERA_MOUNTS = {
    "ring_front_center": (0.0, (1.635, 0.003, 1.398), 1776.0),
    "ring_front_left": (44.9, (1.546, 0.204, 1.394), 1687.5),
    "ring_front_right": (-45.0, (1.551, -0.199, 1.398), 1685.9),
    "ring_rear_left": (153.1, (1.090, 0.126, 1.419), 1683.9),
    "ring_rear_right": (-152.8, (1.101, -0.127, 1.415), 1689.2),
    "ring_side_left": (99.2, (1.306, 0.276, 1.407), 1688.2),
    "ring_side_right": (-98.9, (1.306, -0.279, 1.396), 1686.8),
    "stereo_front_left": (0.0, (1.625, 0.251, 1.191), 1689.6),
    "stereo_front_right": (0.0, (1.631, -0.248, 1.190), 1690.5),
}
#: Lidar extrinsics (qw, qx, qy, qz), (tx, ty, tz) as in real AV2 calibration; down_lidar is upside down.
LIDAR_MOUNTS = {
    "up_lidar": ((0.9999870714742982, 0.0, 0.0, -0.005084966495157445), (1.35018, 0.0, 1.64042)),
    "down_lidar": (
        (-0.0005378898980682196, -0.9949195814043752, 0.10067133271798985, -0.0001413555239330126),
        (1.3467614766959441, 0.0045669612308231996, 1.5254961741451358),
    ),
}
#: OpenCV camera axes in the ego frame for a forward-looking camera (columns: cam x, y, z).
R_EGO_CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _pose_columns(T: np.ndarray) -> dict[str, np.ndarray]:
    q = quat_wxyz_from_se3(T)
    return {
        "qw": q[:, 0],
        "qx": q[:, 1],
        "qy": q[:, 2],
        "qz": q[:, 3],
        "tx_m": T[:, 0, 3],
        "ty_m": T[:, 1, 3],
        "tz_m": T[:, 2, 3],
    }


def _camera_extrinsic(yaw_deg: float, position_m: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix() @ R_EGO_CAM_FORWARD
    T[:3, 3] = position_m
    return T


def calibration(
    tbv: bool = False, camera_scale: int = 1
) -> tuple[dict[str, np.ndarray], dict[str, tuple[float, int, int]]]:
    """T_sensor_ego for all sensors and (focal, width, height) for the cameras (AV2: 9 cameras
    at full resolution; TbV: the 7 ring cameras, all but ring_front_center at half resolution),
    each camera's focal length and size then divided by ``camera_scale``."""
    T_sensor_ego = {}
    cams = {}
    for cam, (yaw, pos, focal) in CAMERA_MOUNTS.items():
        if tbv and cam not in av2.RING_CAMERAS:
            continue
        T_sensor_ego[cam] = _camera_extrinsic(yaw, pos)
        width, height = (1550, 2048) if cam == "ring_front_center" else (2048, 1550)
        if tbv and cam != "ring_front_center":
            focal, width, height = focal / 2, width // 2, height // 2
        if camera_scale != 1:
            focal, width, height = focal / camera_scale, width // camera_scale, height // camera_scale
        cams[cam] = (focal, width, height)
    for lidar, (quat, t) in LIDAR_MOUNTS.items():
        T_sensor_ego[lidar] = se3_from_quat_wxyz(quat, t)
    return T_sensor_ego, cams


def camera_trigger_phases_ns(T_sensor_ego: dict[str, np.ndarray], cameras: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Per camera, its two trigger phases (ns after t0 within the 100 ms clock): when each unit's
    firing azimuth crosses the camera's optical axis, plus CAMERA_TRIGGER_DELAY_NS."""
    out = {}
    for cam in cameras:
        phases = []
        for unit, (spin, az0) in UNIT_SPIN.items():
            axis = T_sensor_ego[unit][:3, :3].T @ T_sensor_ego[cam][:3, :3][:, 2]
            psi = np.arctan2(axis[1], axis[0])
            crossing_s = ((psi - az0) / (spin * 2 * np.pi * vlp32c.SPIN_RATE_HZ)) % (1 / vlp32c.SPIN_RATE_HZ)
            phases.append(int(round(crossing_s * 1e9)) + CAMERA_TRIGGER_DELAY_NS)
        out[cam] = np.sort(np.array(phases, dtype=np.int64))
    return out


def simulate_unit(
    unit: str,
    window_ns: tuple[int, int],
    t0_ns: int,
    scene: Scene,
    T_sensor_city_fn,
) -> dict[str, np.ndarray]:
    """Fire one VLP-32C over [start, end) ns and return its hits.

    The unit fires on a continuous clock (cycles of 16 beam pairs every 55.296 µs since t0), spins
    at 10 Hz in its own frame, and each beam is offset in azimuth by the VLP-32C table.

    Returns a dict with time_ns [N], beam [N], direction_sensor [N,3], distance_m [N], intensity [N],
    xyz_city_m [N,3], box_index [N] (the hit box in ``scene.boxes``, -1 for the ground).
    """
    start, end = window_ns
    c0 = -(-(start - t0_ns) // vlp32c.FIRING_CYCLE_NS)
    c1 = -(-(end - t0_ns) // vlp32c.FIRING_CYCLE_NS)
    cycles = np.arange(c0, c1, dtype=np.int64)
    pairs = np.array(vlp32c.FIRING_PAIRS)  # [16,2]
    slot = np.arange(16, dtype=np.int64) * vlp32c.FIRING_PAIR_SPACING_NS
    fire_ns = (t0_ns + cycles[:, None] * vlp32c.FIRING_CYCLE_NS + slot[None, :]).reshape(-1)  # [C*16]
    time_ns = np.repeat(fire_ns, 2)
    beam = np.tile(pairs.reshape(-1), len(cycles))
    spin_dir, az0 = UNIT_SPIN[unit]
    t_rel_s = (time_ns - t0_ns) * 1e-9
    azimuth = (
        az0 + spin_dir * 2 * np.pi * vlp32c.SPIN_RATE_HZ * t_rel_s + np.radians(vlp32c.BEAM_AZIMUTH_OFFSET_DEG[beam])
    )
    elevation = np.radians(vlp32c.BEAM_ELEVATION_DEG[beam])
    direction = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=1
    )
    fire_unique_s = (fire_ns - t0_ns) * 1e-9
    T_sensor_city = T_sensor_city_fn(fire_unique_s)  # [C*16,4,4]
    pose = np.repeat(T_sensor_city, 2, axis=0)
    origin = pose[:, :3, 3]
    direction_city = np.einsum("nij,nj->ni", pose[:, :3, :3], direction)
    distance, intensity, box_index = cast_rays(origin, direction_city, t_rel_s, scene, MAX_RANGE_M)
    hit = np.isfinite(distance)
    return {
        "time_ns": time_ns[hit],
        "beam": beam[hit],
        "direction_sensor": direction[hit],
        "distance_m": distance[hit],
        "intensity": intensity[hit],
        "xyz_city_m": origin[hit] + direction_city[hit] * distance[hit, None],
        "box_index": box_index[hit],
    }


def write_log(out_dir: UPath, config: SynthConfig) -> SynthTruth:
    """Write one synthetic log to ``<out_dir>/<log_id>/`` and return its truth (``out_dir``: the AV2
    split folder, or the TbV root)."""
    rng = np.random.default_rng(config.seed)
    h = rng.bytes(16).hex()
    log_id = f"{h[:8]}-{h[8:12]}-3{h[13:16]}-8{h[17:20]}-{h[20:32]}"
    if config.tbv:
        alphabet = np.array(list("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789"))
        log_id = "".join(rng.choice(alphabet, 32)) + "__" + str(rng.choice(TBV_SEASONS))
    log_dir = UPath(out_dir) / log_id
    n_sweeps = max(1, int(round(config.seconds * 10)))
    t0_ns = 315_970_000_000_000_000 + int(rng.integers(0, 10**12)) // 1000 * 1000
    traffic_rng = np.random.default_rng([config.seed, TRAFFIC_STREAM])
    scene = make_scene(rng, config.seconds, traffic_rng, config.shapes, config.close_range, config.clear_paths)
    T_sensor_ego, cams = calibration(config.tbv, config.camera_scale)
    truth = SynthTruth(log_dir, log_id, t0_ns, scene, T_sensor_ego)

    jitter_us = rng.integers(-3000, 3000, n_sweeps)
    jitter_us[0] = 0
    sweep_ns = t0_ns + np.arange(n_sweeps, dtype=np.int64) * SWEEP_PERIOD_NS + jitter_us * 1000

    # Camera triggers on the 100 ms clock from just before the first sweep to well after the last;
    # poses at every one.
    periods = np.arange(-1, n_sweeps + 4, dtype=np.int64)
    cam_ns = {
        cam: np.sort((t0_ns + periods[:, None] * SWEEP_PERIOD_NS + phases[None, :]).reshape(-1))
        for cam, phases in camera_trigger_phases_ns(T_sensor_ego, config.cameras).items()
    }
    pose_ns = np.unique(np.concatenate([sweep_ns] + list(cam_ns.values())))
    write_feather_table(
        log_dir / "city_SE3_egovehicle.feather",
        av2.POSES_SCHEMA,
        {"timestamp_ns": pose_ns, **_pose_columns(truth.T_ego_city(pose_ns))},
    )
    names = list(config.cameras) + list(av2.LIDARS)
    T = np.stack([T_sensor_ego[n] for n in names])
    write_feather_table(
        log_dir / "calibration" / "egovehicle_SE3_sensor.feather",
        av2.EXTRINSICS_SCHEMA,
        {"sensor_name": names, **_pose_columns(T)},
    )
    k = {"k1": [], "k2": [], "k3": []}
    for _ in config.cameras:
        k["k1"].append(rng.uniform(-0.29, -0.24))
        k["k2"].append(rng.uniform(-0.2, -0.02))
        k["k3"].append(rng.uniform(0.09, 0.33))
    cx_px = [cams[c][1] / 2 + rng.uniform(-4, 4) for c in config.cameras]
    cy_px = [cams[c][2] / 2 + rng.uniform(-4, 4) for c in config.cameras]
    for c, cx, cy in zip(config.cameras, cx_px, cy_px, strict=True):
        truth.intrinsics[c] = (cams[c][0], cx, cy)
        if c in EGO_CAMERAS:
            truth.ego_masks[c] = true_mask(c, T_sensor_ego[c], cams[c][0], cx, cy, cams[c][1], cams[c][2])
    write_feather_table(
        log_dir / "calibration" / "intrinsics.feather",
        av2.INTRINSICS_SCHEMA,
        {
            "sensor_name": list(config.cameras),
            "fx_px": [cams[c][0] for c in config.cameras],
            "fy_px": [cams[c][0] for c in config.cameras],
            "cx_px": cx_px,
            "cy_px": cy_px,
            **k,
            "height_px": [cams[c][2] for c in config.cameras],
            "width_px": [cams[c][1] for c in config.cameras],
        },
    )

    write_map(log_dir, log_id, scene, config.seconds, rng)
    if config.sweeps:
        _write_sweeps(truth, sweep_ns, config)
    if config.camera_fps > 0:
        write_images(truth, cam_ns, cams, rng, config)
    return truth


def _write_sweeps(truth: SynthTruth, sweep_ns: np.ndarray, config: SynthConfig) -> None:
    scene, t0_ns = truth.scene, truth.t0_ns
    annotation_rows: dict[str, list] = {n: [] for n in av2.ANNOTATIONS_SCHEMA.names}
    for ts in sweep_ns:
        ts = int(ts)
        parts = []
        for u, unit in enumerate(av2.LIDARS):
            start = ts + UNIT_WINDOW_START_NS[unit]
            T_sensor_ego = truth.T_sensor_ego[unit]
            hits = simulate_unit(
                unit,
                (start, start + SWEEP_PERIOD_NS),
                t0_ns,
                scene,
                lambda t_s, T=T_sensor_ego: scene.ego.T_ego_city(t_s) @ T,
            )
            high_half = (unit == "down_lidar") != config.swap_lidar_halves
            hits["laser_number"] = (hits["beam"] + (32 if high_half else 0)).astype(np.uint8)
            hits["unit"] = np.full(len(hits["beam"]), u, dtype=np.int8)
            parts.append(hits)
        hits = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        T_city_ego_ref = invert_se3(truth.T_ego_city(np.array([ts]))[0])
        xyz_ego = transform_points(T_city_ego_ref, hits["xyz_city_m"]).astype(np.float16)
        offset_ns = (hits["time_ns"] - ts).astype(np.int32)
        write_feather_table(
            av2.sweep_path(truth.log_dir, ts),
            TBV_LIDAR_SCHEMA if config.tbv else av2.LIDAR_SCHEMA,
            {
                "x": xyz_ego[:, 0],
                "y": xyz_ego[:, 1],
                "z": xyz_ego[:, 2],
                "intensity": hits["intensity"],
                "laser_number": hits["laser_number"],
                "offset_ns": offset_ns,
            },
        )
        sweep = SweepTruth(ts, offset_ns)
        if config.keep_truth:
            sweep.unit, sweep.laser_number = hits["unit"], hits["laser_number"]
            sweep.direction_sensor = hits["direction_sensor"]
            sweep.distance_m, sweep.time_ns = hits["distance_m"], hits["time_ns"]
            sweep.box_index = hits["box_index"]
        truth.sweeps.append(sweep)
        if not config.tbv or config.tbv_annotations:
            _annotate(truth, ts, xyz_ego.astype(np.float64), T_city_ego_ref, annotation_rows)
    if config.tbv and not config.tbv_annotations:  # TbV has no annotations
        return
    truth.n_cuboids = len(annotation_rows["timestamp_ns"])
    write_feather_table(truth.log_dir / "annotations.feather", av2.ANNOTATIONS_SCHEMA, annotation_rows)


ANNOTATION_RADIUS_M = 100.0  #: objects within this horizontal distance of the ego are annotated


def annotated_boxes(scene: Scene, t_s: float, T_city_ego: np.ndarray) -> Iterator[tuple[Box, np.ndarray]]:
    """The annotations at ``t_s`` (seconds from the log start): every annotated scene object within
    ``ANNOTATION_RADIUS_M`` of the ego, with its box as annotated (jitter included) in the ego frame,
    ``T_box_ego`` [4,4]. ``T_city_ego`` [4,4] maps city points into the ego frame at ``t_s``."""
    for box in scene.boxes:
        if box.annotated:
            T_box_ego = T_city_ego @ box.T_annotated_city(t_s)
            if np.linalg.norm(T_box_ego[:2, 3]) <= ANNOTATION_RADIUS_M:
                yield box, T_box_ego


def _annotate(truth: SynthTruth, ts: int, xyz_ego: np.ndarray, T_city_ego: np.ndarray, rows: dict) -> None:
    """Annotation rows (:func:`annotated_boxes`), with num_interior_pts from the stored cloud."""
    points = PointGrid(xyz_ego)
    annotated = list(annotated_boxes(truth.scene, (ts - truth.t0_ns) * 1e-9, T_city_ego))
    if not annotated:
        return
    poses = _pose_columns(np.stack([T_box_ego for _, T_box_ego in annotated]))  # one batch per sweep
    for k, (box, T_box_ego) in enumerate(annotated):
        inside = points_in_box(points, T_box_ego[:3, 3], T_box_ego[:3, :3], box.dims_m / 2)
        rows["timestamp_ns"].append(ts)
        rows["track_uuid"].append(box.track_uuid)
        rows["category"].append(box.category)
        for name, value in zip(("length_m", "width_m", "height_m"), box.dims_m, strict=True):
            rows[name].append(float(value))
        for name, column in poses.items():
            rows[name].append(float(column[k]))
        rows["num_interior_pts"].append(len(inside))
