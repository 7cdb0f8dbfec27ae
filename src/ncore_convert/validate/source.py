"""``validate --source ROOT``: a converted sequence's counts against its source files.

Which source a sequence came from is read from its generic metadata (``source_dataset`` and the
log or scenario id the converters write). The source side is counted from the files themselves
(sweep rows, PCD headers, image files, annotation rows, YAML labels), not from anything the
converter recorded, except the points it declared not representable (zero range or non-finite),
which are in each lidar's metadata and are added back.
"""

from __future__ import annotations

import numpy as np
from ncore.data.v4 import SequenceLoaderV4
from scipy.spatial.transform import Rotation
from upath import UPath

from ncore_convert import contract
from ncore_convert.errors import SourceError
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import argoverse2_annotations as av2_annotations
from ncore_convert.sources import opencood as ocd
from ncore_convert.sources.pcd import read_pcd_header
from ncore_convert.sources.reader import Reader, reading
from ncore_convert.transforms.timebase import floor_us, in_window
from ncore_convert.validate.cuboids import CuboidColumns
from ncore_convert.validate.poses import lever_arm_m, sensor_poses
from ncore_convert.validate.readback import OpenSequence, box_point_counts, boxes_at, sample_frames
from ncore_convert.validate.report import Report

#: The interior-point band (docs/validation.md, "Bands"). A returned point reaches the box test moved
#: from its source position by at most round_trip_margin_m of its range: float32 roundings, each at
#: most one unit roundoff (2**-24) of the range (the converter's decompensation in float32: 3 for the
#: matrix elements, 12 for the products and sums; the stored float32 direction and distance and
#: NCore's product of them: 3; NCore's float32 compensation to the frame end: 3 + 12), and two floors
#: of a time to the µs (the point's own time, and the box's reference time, the sweep's): the rig's
#: motion over at most one µs each. The box test itself runs in float64.
FLOAT32_ROUNDINGS = 33
UNIT_ROUNDOFF_F32 = 2.0**-24
TIME_STEP_S = 1e-6  #: the stored times' step (µs), floored from the source's ns
TIME_FLOORS = 2  #: the point's time and the box's reference time
#: the rig's speed and turn rate are taken from its poses at this spacing over each sampled sweep
MOTION_SAMPLE_US = 1000
#: An observation's centre (m), size (m) and rotation-matrix elements are its annotation row's, up to
#: this many float64 epsilons of each value's magnitude (at least 1): the converter stores the row's
#: centre and size as they are and its rotation as xyz Euler angles, whose round trip through scipy
#: (matrix -> angles -> matrix, far from gimbal lock) costs a few epsilons (the real sample's 11,364
#: cuboids: 4.25 at most).
BOX_EPSILONS = 16
BOX_TOLERANCE = BOX_EPSILONS * float(np.finfo(np.float64).eps)  #: of a value of magnitude <= 1


def compare_with_source(
    report: Report, sequence: OpenSequence, source_root: UPath, cuboids: CuboidColumns, reader: Reader | None = None
) -> None:
    """Add the ``source:`` checks of one sequence (read from ``source_root``, the converter's --root-dir,
    through ``reader``: the log's, whose spool holds what its conversion kept; ``cuboids``: the
    sequence's cuboid observations)."""
    meta = sequence.loader.generic_meta_data
    dataset = meta.get(contract.SOURCE_DATASET)
    try:
        with reading(reader) as r:
            if dataset in contract.ARGOVERSE2_DATASETS:
                _compare_av2(report, sequence, UPath(source_root), meta, cuboids, r)
            elif dataset in contract.OPENCOOD_DATASETS:
                _compare_opencood(report, sequence, UPath(source_root), meta, len(cuboids), r)
            else:
                report.add("source: dataset known", False, f"source_dataset {dataset!r} is not one this tool converts")
    except SourceError as err:
        report.add("source: readable", False, str(err))


def _count(report: Report, what: str, converted: int, source: int) -> None:
    report.add(f"source: {what}", converted == source, f"{converted} converted, {source} in the source")


def _accounted(report: Report, what: str, converted: int, skipped: dict[str, str], source: int) -> None:
    """Every source frame is converted or declared skipped (in the sensor's ``skipped_frames`` metadata)."""
    causes = sorted(set(skipped.values()))
    report.add(
        f"source: {what}",
        converted + len(skipped) == source,
        f"{converted} converted + {len(skipped)} declared skipped {causes if causes else ''}".rstrip()
        + f", {source} in the source",
    )


def _left_out(report: Report, sensor_id: str, record: dict, paths: list[UPath], listing: dict, reader: Reader) -> None:
    """A sensor the converter left out for unreadable frames declares every source file it has
    (``contract.SENSORS_NOT_WRITTEN``); one left out for another reason (no calibration) is reported."""
    declared = {UPath(f).name for f in record.get("files", {})}
    present = [p.name for p in paths if reader.exists(p, listing)]
    undeclared = [name for name in present if name not in declared] if declared else []
    report.add(
        f"source: {sensor_id} not written, every file declared",
        not undeclared,
        f"{record.get('reason')}: {len(present) - len(undeclared)} of {len(present)} source files declared"
        + (f", not {undeclared[:3]}" if undeclared else ""),
    )


def _stored_points(loader: SequenceLoaderV4, lidar_id: str) -> int:
    lidar = loader.get_lidar_sensor(lidar_id)
    return sum(lidar.get_frame_ray_bundle_count(i) for i in range(lidar.frames_count))


def _camera_selected(options: dict, camera: str) -> bool:
    """Whether the conversion was asked for this camera (``camera_ids`` None: all)."""
    return options.get("camera_ids") is None or camera in options["camera_ids"]


def _window(meta: dict) -> tuple[int, int] | None:
    """The clip window the sequence was cut to (inclusive µs), None for the whole log."""
    clip = meta.get(contract.CLIP)
    return (int(clip["start_us"]), int(clip["end_us"])) if clip else None


def _in_window_ns(timestamps_ns: np.ndarray, window_us: tuple[int, int] | None) -> np.ndarray:
    """The ns timestamps whose floored µs lie in the window (all without one)."""
    return timestamps_ns if window_us is None else timestamps_ns[in_window(floor_us(timestamps_ns), window_us)]


def _compare_av2(
    report: Report, sequence: OpenSequence, root: UPath, meta: dict, cuboids: CuboidColumns, reader: Reader
) -> None:
    loader = sequence.loader
    log_dir = av2.log_dir(root, meta.get(contract.AV2_SPLIT), meta[contract.AV2_LOG_ID])
    if not reader.is_folder(log_dir):
        report.add("source: log found", False, f"{log_dir}: not a directory")
        return
    options = meta.get(contract.CONVERTER, {}).get("options", {})
    window_us = _window(meta)
    files = reader.list_folder(log_dir)  # remote sizes and ETags: fetched bytes are checked against them
    sweeps = _in_window_ns(av2.list_sweep_timestamps_ns(log_dir, files, reader), window_us)
    for lidar_id in sorted(loader.lidar_ids):
        _count(
            report, f"{lidar_id} frames (one per sweep)", loader.get_lidar_sensor(lidar_id).frames_count, len(sweeps)
        )
    if set(loader.lidar_ids) == set(av2.LIDARS):
        lidar_meta = sequence.sensor_meta()
        not_stored = sum(sum(lidar_meta[u][contract.POINTS_NOT_STORED].values()) for u in av2.LIDARS)
        stored = sum(_stored_points(loader, u) for u in av2.LIDARS)
        source = av2.count_sweep_points(log_dir, sweeps, files, reader)
        report.add(
            "source: lidar points",
            stored + not_stored == source,
            f"{stored} stored + {not_stored} not representable, {source} in the source",
        )
    cameras_dir = log_dir / "sensors" / "cameras"
    in_source = reader.folder_names(cameras_dir, "camera folder")
    for camera in in_source:
        images = len(_in_window_ns(av2.list_image_timestamps_ns(log_dir, camera, reader=reader), window_us))
        if camera in loader.camera_ids:
            _count(report, f"{camera} images", loader.get_camera_sensor(camera).frames_count, images)
        elif images and _camera_selected(options, camera):
            report.add(f"source: {camera} images", False, f"0 converted, {images} in the source")
    interior = av2_annotations.read_interior_points(log_dir, files, reader)
    if interior is not None and window_us is not None:
        interior = interior.subset(in_window(floor_us(interior.timestamps_ns), window_us))
    _count(report, "cuboids", len(cuboids), 0 if interior is None else len(interior.counts))
    if interior is not None:
        annotations = av2_annotations.read_annotations(log_dir, files, reader)
        if window_us is not None:
            annotations = annotations.subset(in_window(floor_us(annotations.timestamps_ns), window_us))
        _boxes_as_annotated(report, cuboids, annotations)
    if interior is not None and set(loader.lidar_ids) == set(av2.LIDARS):
        _interior_points(report, sequence, cuboids, interior)


def _boxes_as_annotated(report: Report, cuboids: CuboidColumns, annotations: av2_annotations.Annotations) -> None:
    """Every observation is its annotation row (same track, the row's µs-floored time), in the rig
    frame at that time (AV2's ego frame): the same centre, size and rotation within
    ``BOX_EPSILONS`` float64 epsilons of each value's magnitude."""
    row_of = {
        key: row
        for row, key in enumerate(
            zip(annotations.track_uuids, floor_us(annotations.timestamps_ns).tolist(), strict=True)
        )
    }
    rows = np.array(
        [row_of.get(k, -1) for k in zip(cuboids.track_id, cuboids.timestamp_us.tolist(), strict=True)], dtype=np.int64
    )
    found = rows >= 0
    T = annotations.T_object_ego[rows[found]]
    R_box_rig = Rotation.from_euler("xyz", cuboids.rot_rad[found]).as_matrix() if found.any() else np.zeros((0, 3, 3))
    expected = np.concatenate([T[:, :3, 3], annotations.dims_m[rows[found]], T[:, :3, :3].reshape(-1, 9)], axis=1)
    stored = np.concatenate([cuboids.centroid_m[found], cuboids.dim_m[found], R_box_rig.reshape(-1, 9)], axis=1)
    error = np.abs(stored - expected) / np.maximum(1.0, np.abs(expected))  # in units of each value's magnitude
    off = np.flatnonzero(error.max(axis=1, initial=0.0) > BOX_TOLERANCE)
    frames = set(cuboids.reference_frame_id[found])
    ok = found.all() and not len(off) and frames <= {"rig"}
    report.add(
        "source: every cuboid is its annotation (track, time, centre, size, rotation)",
        ok,
        f"{int((~found).sum())} of {len(cuboids)} without an annotation row, {len(off)} differ by more than"
        f" {BOX_EPSILONS} float64 epsilons; reference frames {sorted(map(str, frames))}"
        + (f"; worst {error.max() / np.finfo(np.float64).eps:.3g} epsilons ({error.max():.2e})" if len(error) else ""),
    )


def round_trip_margin_m(range_m: np.ndarray, speed_mps: float, turn_rate_radps: float) -> np.ndarray:
    """How far the conversion and the read-back can move a returned point at ``range_m`` (metres [B],
    from the rig origin plus the lidars' lever arm), while the rig moves at up to ``speed_mps`` and turns
    at up to ``turn_rate_radps``: the float32 roundings and the µs floors of the point's time and the
    box's reference time (see FLOAT32_ROUNDINGS), metres [B]."""
    time_m = TIME_FLOORS * (speed_mps + turn_rate_radps * range_m) * TIME_STEP_S
    return time_m + FLOAT32_ROUNDINGS * UNIT_ROUNDOFF_F32 * range_m


def rig_motion_bounds(loader: SequenceLoaderV4, start_us: int, end_us: int) -> tuple[float, float]:
    """The rig's largest speed (m/s) and turn rate (rad/s) over [start_us, end_us], from its poses
    every MOTION_SAMPLE_US (NCore interpolates poses piecewise linearly, so these are the segments' own)."""
    t_us = np.arange(start_us - MOTION_SAMPLE_US, end_us + 2 * MOTION_SAMPLE_US, MOTION_SAMPLE_US, dtype=np.int64)
    t_us = t_us[
        (t_us >= loader.sequence_timestamp_interval_us.start) & (t_us <= loader.sequence_timestamp_interval_us.stop)
    ]
    T = sensor_poses(loader, "rig", "world", t_us.astype(np.uint64))
    if len(T) < 2:
        return 0.0, 0.0
    dt_s = np.diff(t_us) * 1e-6
    speed = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1) / dt_s
    turn = Rotation.from_matrix(np.einsum("nji,njk->nik", T[:-1, :3, :3], T[1:, :3, :3])).magnitude() / dt_s
    return float(speed.max()), float(turn.max())


def _interior_points(
    report: Report, sequence: OpenSequence, cuboids: CuboidColumns, interior: av2_annotations.InteriorPoints
) -> None:
    """On sampled sweeps: AV2's ``num_interior_pts`` of every box lies in [converted points inside the
    box shrunk by ε, inside it grown by ε] (both lidars, motion-compensated with the per-point times),
    ε per box from :func:`round_trip_margin_m` at the box's farthest reach."""
    source_points = {
        (track, floor_us(int(t_ns))): int(n)
        for track, t_ns, n in zip(interior.track_uuids, interior.timestamps_ns, interior.counts, strict=True)
    }
    loader = sequence.loader
    frames_us = loader.get_lidar_sensor(av2.LIDARS[0]).frames_timestamps_us
    sampled = sample_frames(len(frames_us))
    lever_m = lever_arm_m(loader, av2.LIDARS)
    checked, off, widest = 0, [], 0.0
    for i in sampled:
        boxes = boxes_at(cuboids, int(frames_us[i, 0]), int(frames_us[i, 1]))
        keys = list(zip(boxes.track_id, boxes.timestamp_us.tolist(), strict=True))
        known = np.array([k in source_points for k in keys], dtype=bool)
        boxes, keys = boxes.rows(known), [k for k in keys if k in source_points]
        if not len(boxes):
            continue
        same_sweep = [_frame_starting_at(loader, unit, int(frames_us[i, 0])) for unit in av2.LIDARS]
        if None in same_sweep:  # a unit lacks this sweep: the frame counts above already fail
            continue
        try:
            xyz_world = np.concatenate(
                [sequence.world_points(u, f)[0] for u, f in zip(av2.LIDARS, same_sweep, strict=True)]
            )
        except AssertionError:  # NCore refuses to compensate points timed outside their frame
            off.append(f"sweep at {int(frames_us[i, 0])} µs: point times outside the frame, not compensated")
            continue
        reach_m = np.linalg.norm(boxes.centroid_m, axis=1) + 0.5 * np.linalg.norm(boxes.dim_m, axis=1) + lever_m
        margin_m = round_trip_margin_m(reach_m, *rig_motion_bounds(loader, int(frames_us[i, 0]), int(frames_us[i, 1])))
        inner, outer = box_point_counts(loader, boxes, xyz_world, margin_m)
        expected = np.array([source_points[k] for k in keys])
        bad = (expected < inner) | (expected > outer)
        checked += len(boxes)
        widest = max(widest, float(margin_m.max()))
        for k in np.flatnonzero(bad):
            beyond = max(inner[k] - expected[k], expected[k] - outer[k])
            off.append(
                f"{boxes.track_id[k][:8]}@{boxes.timestamp_us[k]}: {expected[k]} not in [{inner[k]}, {outer[k]}]"
                f" ({beyond} beyond; ε {margin_m[k] * 1e6:.0f} µm)"
            )
    detail = f"{len(off)} of {checked} boxes outside their band on {len(sampled)} sampled sweeps"
    detail += f" (ε <= {widest * 1e6:.0f} µm)"
    report.add(
        "source: points inside each box match num_interior_pts", not off, detail + (f": {off[:3]}" if off else "")
    )


def _frame_starting_at(loader: SequenceLoaderV4, lidar_id: str, start_us: int) -> int | None:
    """The index of the lidar's frame starting at ``start_us`` (the sweep time), or None."""
    index = np.flatnonzero(loader.get_lidar_sensor(lidar_id).frames_timestamps_us[:, 0] == start_us)
    return int(index[0]) if len(index) else None


def _compare_opencood(
    report: Report, sequence: OpenSequence, root: UPath, meta: dict, n_cuboids: int, reader: Reader
) -> None:
    loader = sequence.loader
    scenario_dir = ocd.scenario_dir(root, meta[contract.OPENCOOD_SPLIT], meta[contract.SCENARIO])
    if not reader.is_folder(scenario_dir):
        report.add("source: scenario found", False, f"{scenario_dir}: not a directory")
        return
    options = meta.get(contract.CONVERTER, {}).get("options", {})
    agents = list(meta[contract.AGENTS])
    prefixed = len(agents) > 1 or options.get("layout") == "scenario"
    files: dict = {}  # remote files' sizes and ETags: existence is read from the listings
    keys = {a: ocd.list_frame_keys(scenario_dir / a, files, reader) for a in ocd.list_agents(scenario_dir, reader)}
    if (window_us := _window(meta)) is not None:
        dt_s = meta["carla_fixed_delta_seconds"]
        keys = {
            a: [k for k, keep in zip(ks, in_window(ocd.key_timestamps_us(ks, dt_s), window_us), strict=True) if keep]
            for a, ks in keys.items()
        }
    sensor_meta = sequence.sensor_meta()
    left_out = meta.get(contract.SENSORS_NOT_WRITTEN) or {}
    for agent in agents:
        prefix = contract.agent_prefix(agent) if prefixed else ""
        agent_dir = scenario_dir / agent
        lidar_id = prefix + ocd.LIDAR
        read_keys = [k for k in keys[agent] if _vehicle_ids(agent_dir, k, files, reader) is not None]  # readable YAMLs
        if lidar_id in left_out:
            _left_out(
                report, lidar_id, left_out[lidar_id], [ocd.pcd_path(agent_dir, k) for k in read_keys], files, reader
            )
        elif lidar_id in loader.lidar_ids:
            lidar = loader.get_lidar_sensor(lidar_id)
            skipped = sensor_meta[lidar_id].get(contract.SKIPPED_FRAMES, {})
            _accounted(report, f"{lidar_id} frames", lidar.frames_count, skipped, len(keys[agent]))
            not_stored = sum(
                int(lidar.get_frame_generic_meta_data(i).get(contract.POINTS_NOT_STORED, 0))
                for i in range(lidar.frames_count)
            )
            stored = _stored_points(loader, lidar_id)
            source = sum(
                read_pcd_header(ocd.pcd_path(agent_dir, k), reader).points for k in keys[agent] if k not in skipped
            )
            report.add(
                f"source: {lidar_id} points",
                stored + not_stored == source,
                f"{stored} stored + {not_stored} not representable, {source} in the source's"
                " frames not declared skipped",
            )
        for index, camera in enumerate(ocd.CAMERAS):
            if prefix + camera in loader.camera_ids:
                skipped = sensor_meta[prefix + camera].get(contract.SKIPPED_FRAMES, {})
                converted = loader.get_camera_sensor(prefix + camera).frames_count
                _accounted(report, f"{prefix}{camera} images", converted, skipped, len(keys[agent]))
            elif prefix + camera in left_out:
                paths = [ocd.camera_path(agent_dir, k, index) for k in read_keys]
                _left_out(report, prefix + camera, left_out[prefix + camera], paths, files, reader)
            elif _camera_selected(options, camera):
                if images := sum(reader.exists(ocd.camera_path(agent_dir, k, index), files) for k in keys[agent]):
                    report.add(f"source: {prefix}{camera} images", False, f"0 converted, {images} in the source")
    reference = next((a for a in agents if meta[contract.AGENTS][a].get("opencood_ego")), agents[0])
    readable = [k for k in keys[reference] if _vehicle_ids(scenario_dir / reference, k, files, reader) is not None]
    labels = sum(len(_labelled(scenario_dir, keys, key, files, reader)) for key in readable)  # the reference's frames
    _count(report, "cuboids (every agent's labels per frame, plus the CAVs)", n_cuboids, labels)


def _labelled(scenario_dir: UPath, keys: dict[str, list[str]], key: str, listing: dict, reader: Reader) -> set[int]:
    """Actor ids at one frame key: every agent's labelled vehicles and the CAVs themselves (an agent
    whose YAML is unreadable adds nothing, as in the converter, which skipped and declared it)."""
    ids: set[int] = set()
    for agent, agent_keys in keys.items():
        if key in agent_keys and (vehicles := _vehicle_ids(scenario_dir / agent, key, listing, reader)) is not None:
            ids.update(vehicles)
            if not ocd.is_infrastructure(agent):
                ids.add(int(agent))
    return ids


_VEHICLES: dict[tuple[str, str], frozenset[int] | None] = {}  #: (agent folder, key) -> its YAML's vehicles


def _vehicle_ids(agent_dir: UPath, key: str, listing: dict, reader: Reader) -> frozenset[int] | None:
    """The vehicles one agent's YAML labels, None if it is unreadable (kept: every agent's sequence
    of a scenario needs them all; a remote YAML is fetched by its ``listing`` entry, or taken from
    the run's spool)."""
    cache_key = (str(agent_dir), key)
    if cache_key not in _VEHICLES:
        if len(_VEHICLES) > 8192:
            _VEHICLES.clear()
        try:
            raw = reader.read(ocd.yaml_path(agent_dir, key), listing)
            _VEHICLES[cache_key] = frozenset(ocd.read_agent_frame(agent_dir, key, raw).vehicles.actor_ids.tolist())
        except SourceError:
            _VEHICLES[cache_key] = None
    return _VEHICLES[cache_key]
