"""Converter output against the synthetic generator's ground truth (issue 2 acceptance, synthetic part)."""

from __future__ import annotations

import numpy as np
import pytest
from ncore.data.v4 import CameraSensorComponent, LidarSensorComponent, PosesComponent
from ncore.impl.data.types import IdealPinholeCameraModelParameters, LabelSource, ShutterType
from scipy.spatial.transform import Rotation

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth.argoverse2 import calibration

UNITS = ("up_lidar", "down_lidar")


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b)))


def stored_frames(conv, unit):
    lidar = conv.loader.get_lidar_sensor(unit)
    for i in range(lidar.frames_count):
        yield (
            lidar.get_frame_ray_bundle_direction(i),
            lidar.get_frame_ray_bundle_timestamp_us(i),
            lidar.get_frame_ray_bundle_return_distance_m(i),
            lidar.frames_timestamps_us[i],
        )


@pytest.mark.parametrize("unit_index,unit", list(enumerate(UNITS)))
def test_directions_match_simulated_raw_rays(synth_log, unit_index, unit):
    errors, range_errors = [], []
    for sweep, (direction, _, distance, _) in zip(synth_log.truth.sweeps, stored_frames(synth_log, unit), strict=True):
        mine = sweep.unit == unit_index
        assert len(direction) == mine.sum()
        errors.append(angle_deg(direction.astype(np.float64), sweep.direction_sensor[mine]))
        range_errors.append(np.abs(distance - sweep.distance_m[mine]))
    errors = np.concatenate(errors)
    assert np.median(errors) <= 0.01, f"median {np.median(errors):.4f} deg"
    # float16 storage of ~100 m coordinates limits far points to ~0.03 m, i.e. a few hundredths of a degree
    assert np.percentile(errors, 99) < 0.1
    assert np.median(np.concatenate(range_errors)) < 0.02


@pytest.mark.parametrize("unit_index,unit", list(enumerate(UNITS)))
def test_point_timestamps_exact_to_the_microsecond(synth_log, unit_index, unit):
    frames = stored_frames(synth_log, unit)
    for sweep, (_, timestamp_us, _, frame_us) in zip(synth_log.truth.sweeps, frames, strict=True):
        expected = sweep.time_ns[sweep.unit == unit_index] // 1000
        np.testing.assert_array_equal(timestamp_us, expected.astype(np.uint64))
        assert frame_us[0] == min(sweep.timestamp_ns // 1000, expected.min())
        assert frame_us[1] == expected.max()


@pytest.mark.parametrize("fixture", ["synth_log", "synth_swapped"])
def test_unit_labels_come_from_the_data(request, fixture):
    conv = request.getfixturevalue(fixture)
    swapped = fixture == "synth_swapped"
    meta = conv.reader.open_component_readers(LidarSensorComponent.Reader)["up_lidar"].generic_meta_data
    decision = meta["av2_unit_decision"]
    assert decision["laser_number_lt_32"] == ("down_lidar" if swapped else "up_lidar")
    assert decision["margin"] >= 2.0
    # and the stored rays really are the right unit's: each unit's rays match its simulated rays
    for unit_index, unit in enumerate(UNITS):
        direction, *_ = next(stored_frames(conv, unit))
        sweep = conv.truth.sweeps[0]
        truth = sweep.direction_sensor[sweep.unit == unit_index]
        assert np.median(angle_deg(direction.astype(np.float64), truth)) < 0.01


#: NCore's AV2 converter's class map (test_convert_real.AV2_TO_NCORE_CLASS), for the categories the
#: generator writes (default --class-names ncore)
NCORE_CLASS = {"REGULAR_VEHICLE": "car", "PEDESTRIAN": "pedestrian", "BOLLARD": "bollard"}


def test_cuboids_round_trip_to_simulated_boxes_in_world(synth_log):
    truth = synth_log.truth
    poses = synth_log.reader.open_component_readers(PosesComponent.Reader)["default"]
    T_rig_world, ts_us = poses.get_dynamic_pose("rig", "world")
    T_world_global = poses.get_static_pose("world", "world_global").astype(np.float64)
    by_uuid = {box.track_uuid: box for box in truth.scene.boxes}
    observations = list(synth_log.loader.get_cuboid_track_observations())
    assert len(observations) == truth.n_cuboids > 0
    centre_err, rot_err = [], []
    for obs in observations:
        assert obs.reference_frame_id == "rig" and obs.source == LabelSource.EXTERNAL
        assert obs.timestamp_us == obs.reference_frame_timestamp_us
        k = np.flatnonzero(ts_us == obs.timestamp_us)
        assert len(k) == 1, "annotation times are pose times in AV2"
        T_rig_city = T_world_global @ T_rig_world[k[0]].astype(np.float64)
        box_rig = np.eye(4)
        box_rig[:3, :3] = Rotation.from_euler("xyz", obs.bbox3.rot).as_matrix()
        box_rig[:3, 3] = obs.bbox3.centroid
        est = T_rig_city @ box_rig
        box = by_uuid[obs.track_id]
        assert obs.class_id == NCORE_CLASS[box.category]
        np.testing.assert_allclose(obs.bbox3.dim, box.dims_m, atol=1e-9)
        ref = box.T_annotated_city((obs.timestamp_us * 1000 - truth.t0_ns) * 1e-9)  # the annotator's box
        centre_err.append(np.linalg.norm(est[:3, 3] - ref[:3, 3]))
        rot_err.append(np.degrees(Rotation.from_matrix(est[:3, :3].T @ ref[:3, :3]).magnitude()))
    assert max(centre_err) <= 0.01
    assert max(rot_err) <= 0.01


def test_cuboids_keep_full_3dof_rotation(synth_log):
    rots = np.array([obs.bbox3.rot for obs in synth_log.loader.get_cuboid_track_observations()])
    assert np.abs(rots[:, :2]).max() > np.radians(1.0), "tilted synthetic boxes must keep roll/pitch"


def test_image_bytes_identical_to_source(synth_log):
    truth = synth_log.truth
    stored = 0
    for cam in av2.CAMERAS:
        sensor = synth_log.loader.get_camera_sensor(cam)
        sources = sorted(p for p in truth.image_paths if p.parent.name == cam)
        assert sensor.frames_count == len(sources) > 0
        for i, path in enumerate(sources):
            handle = sensor.get_frame_handle(i).get_data()
            assert handle.get_encoded_image_data() == path.read_bytes()
            assert handle.get_encoded_image_format() == "jpeg"
            t_us = int(path.stem) // 1000
            np.testing.assert_array_equal(sensor.frames_timestamps_us[i], [t_us, t_us])
            stored += 1
    assert stored == truth.n_images


def test_cameras_are_ideal_pinhole_global_shutter_with_distortion_kept(synth_log):
    readers = synth_log.reader.open_component_readers(CameraSensorComponent.Reader)
    intrinsics = av2.read_intrinsics(synth_log.truth.log_dir)
    for cam in av2.CAMERAS:
        params = synth_log.loader.get_camera_sensor(cam).model_parameters
        assert isinstance(params, IdealPinholeCameraModelParameters)
        assert params.shutter_type == ShutterType.GLOBAL
        src = intrinsics[cam]
        np.testing.assert_array_equal(params.resolution, [src.width_px, src.height_px])
        np.testing.assert_allclose(params.focal_length, [src.fx_px, src.fy_px], rtol=1e-6)
        np.testing.assert_allclose(params.principal_point, [src.cx_px + 0.5, src.cy_px + 0.5], rtol=1e-6)
        meta = readers[cam].generic_meta_data["av2_original_distortion"]
        assert meta == pytest.approx({"k1": src.k1, "k2": src.k2, "k3": src.k3})


def test_every_sensor_has_a_static_extrinsic_equal_to_the_calibration(synth_log):
    T_sensor_ego, _ = calibration()
    poses = synth_log.reader.open_component_readers(PosesComponent.Reader)["default"]
    static = dict(poses.get_static_poses())
    assert set(static) == {(s, "rig") for s in T_sensor_ego} | {("world", "world_global")}
    for sensor, T in T_sensor_ego.items():
        stored = static[(sensor, "rig")]
        assert stored.dtype == np.float32
        np.testing.assert_allclose(stored, T, atol=1e-6)
    camera = synth_log.loader.get_camera_sensor("ring_front_center")
    # OpenCV camera frame: optical axis (+z) looks along rig +x for the front camera
    np.testing.assert_allclose(camera.T_sensor_rig[:3, 2], [1, 0, 0], atol=1e-6)


def test_trajectory_covers_every_frame_and_point(synth_log):
    loader = synth_log.loader
    interval = loader.sequence_timestamp_interval_us
    poses = synth_log.reader.open_component_readers(PosesComponent.Reader)["default"]
    T, ts = poses.get_dynamic_pose("rig", "world")
    assert T.dtype == np.float32 and ts[0] == interval.start and ts[-1] == interval.stop - 1
    np.testing.assert_allclose(T[0], np.eye(4), atol=1e-6)
    for unit in UNITS:
        for _, timestamp_us, _, frame_us in stored_frames(synth_log, unit):
            assert ts[0] <= frame_us[0] and frame_us[1] <= ts[-1]
            assert ts[0] <= timestamp_us.min() and timestamp_us.max() <= ts[-1]
        # NCore's own motion compensation works for every frame (it cannot extrapolate)
        lidar = loader.get_lidar_sensor(unit)
        pc = lidar.get_frame_point_cloud(lidar.frames_count - 1, motion_compensation=True, with_start_points=False)
        assert np.isfinite(pc.xyz_m_end).all()


def test_stored_points_reproject_to_the_source_sweep(synth_log):
    """Compensating the stored rays with NCore's own reader returns the source (float16) points."""
    truth, loader = synth_log.truth, synth_log.loader
    sweep = truth.sweeps[2]
    source = av2.read_sweep(truth.log_dir, sweep.timestamp_ns)
    for unit_index, unit in enumerate(UNITS):
        lidar = loader.get_lidar_sensor(unit)
        pc = lidar.get_frame_point_cloud(2, motion_compensation=True, with_start_points=False)
        frame_end = int(lidar.frames_timestamps_us[2][1])
        pg = loader.pose_graph
        T_rig_ref_world = pg.evaluate_poses("rig", "world", np.array(sweep.timestamp_ns // 1000, dtype=np.uint64))
        T_sensor_end_world = pg.evaluate_poses(unit, "world", np.array(frame_end, dtype=np.uint64))
        M = np.linalg.inv(T_rig_ref_world.astype(np.float64)) @ T_sensor_end_world.astype(np.float64)
        xyz = pc.xyz_m_end.astype(np.float64) @ M[:3, :3].T + M[:3, 3]
        src = source.xyz_ego_m[sweep.unit == unit_index]
        assert np.median(np.linalg.norm(xyz - src, axis=1)) < 0.001


def test_sequence_metadata(synth_log):
    meta = synth_log.loader.generic_meta_data
    assert meta["source_dataset"] == "argoverse2-sensor"
    assert meta["argoverse2_split"] == "val"
    assert meta["argoverse2_log_id"] == synth_log.truth.log_id
    assert meta["converter"]["name"] == "ncore-convert"
    assert meta["converter"]["version"]
    assert synth_log.loader.sequence_id == synth_log.truth.log_id
