"""The contract NCore's consumers read (docs/consumers.md), on synthetic data with known truth, read
the way the consumers read it: ``SequenceLoaderV4``, NCore's own camera models, and the
point-cloud-source API for ``dynamic_flag``.

Covers issue 19: ``--camera-model``, ``--class-names``, ``--cuboid-label-source``, ``dynamic_flag``,
``--seek-sec/--duration-sec`` and ``--world-global-mode``.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import Converted, component_meta, convert_synthetic, open_sequence, run_cli, synth_and_convert
from ncore.data.v4 import (
    CameraSensorComponent,
    CuboidsComponent,
    LidarSensorComponent,
    PosesComponent,
    SequenceComponentGroupsReader,
)
from ncore.impl.data.types import (
    FThetaCameraModelParameters,
    IdealPinholeCameraModelParameters,
    LabelSource,
    OpenCVPinholeCameraModelParameters,
    ShutterType,
)
from ncore.impl.sensors.camera import camera_model_from_parameters
from scipy.spatial.transform import Rotation
from upath import UPath

from ncore_convert import contract
from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
from ncore_convert.converters.consumer import cuboid_labels
from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.sources.argoverse2 import read_intrinsics
from ncore_convert.synth import opencood as synth_opencood
from ncore_convert.synth.argoverse2 import SynthConfig, write_log
from ncore_convert.transforms.objects import dynamic
from ncore_convert.transforms.objects.classes import AV2_TO_NCORE
from ncore_convert.transforms.objects.dynamic import (
    TrackObservations,
    box_motion,
    classify_tracks,
    static_pose,
    track_motion,
)
from ncore_convert.validate.readback import world_points
from ncore_convert.validate.sequence import validate_sequence

UNITS = ("up_lidar", "down_lidar")
CONSUMER = {"camera_model": "ftheta", "class_names": "source", "cuboid_label_source": "autolabel"}


@pytest.fixture(scope="module")
def av2(tmp_path_factory) -> dict[str, Converted]:
    """One synthetic AV2 log (truth kept) converted with default options, with the consumer options,
    and with an OpenCV pinhole."""
    tmp = tmp_path_factory.mktemp("consumers-av2")
    config = SynthConfig(seconds=1.0, seed=4, keep_truth=True, camera_fps=2)
    runs = {"default": synth_and_convert(tmp / "default", config)}
    truth = runs["default"].truth
    runs["consumer"] = convert_synthetic(truth, tmp / "consumer", Argoverse2Options(split="val", **CONSUMER))
    options = Argoverse2Options(split="val", camera_model="opencv-pinhole", lidar_ids=())
    runs["opencv"] = convert_synthetic(truth, tmp / "opencv", options)
    return runs


@pytest.fixture(scope="module")
def tbv(tmp_path_factory) -> Converted:
    tmp = tmp_path_factory.mktemp("consumers-tbv")
    truth = write_log(UPath(tmp / "src"), SynthConfig(seconds=0.6, seed=5, camera_fps=4, tbv=True))
    options = Argoverse2Options(split=None, camera_model="ftheta")
    summary = convert_log(UPath(tmp / "src"), UPath(tmp / "out"), truth.log_id, options)
    return Converted(truth, summary, tmp / "out", open_sequence(tmp / "out", truth.log_id))


@dataclass
class Cooperative:
    truth: synth_opencood.ScenarioTruth
    out: dict[str, Path]  #: run name -> scenario output folder

    def loader(self, run: str, agent_id: str):
        return open_sequence(self.out[run] / agent_id, f"{self.truth.scenario}_agent{agent_id}")


@pytest.fixture(scope="module")
def opv2v(tmp_path_factory) -> Cooperative:
    tmp = tmp_path_factory.mktemp("consumers-opv2v")
    config = synth_opencood.SynthConfig(
        dataset="opv2v", frames=6, seed=6, lidar_columns=360, keep_truth=True, render_step=8
    )
    (truth,) = synth_opencood.write_dataset(UPath(tmp / "src"), config)
    runs = {
        "default": {},
        "consumer": CONSUMER,
        "external": {"cuboid_label_source": "external", "camera_model": "opencv-pinhole"},
    }
    out = {}
    for run, extra in runs.items():
        out[run] = tmp / run / truth.scenario
        options = OpenCoodOptions(dataset="opv2v", split="test", **extra)
        convert_scenario(UPath(tmp / "src"), UPath(out[run]), truth.scenario, options)
    return Cooperative(truth, out)


# --- camera models ---------------------------------------------------------------------------------


def _ncore_model(params):
    return camera_model_from_parameters(params, device="cpu", dtype=torch.float64)


def _pixel_centres(width: int, height: int, step: int = 1) -> torch.Tensor:
    u, v = np.meshgrid(np.arange(0, width, step) + 0.5, np.arange(0, height, step) + 0.5)
    return torch.tensor(np.stack([u.ravel(), v.ravel()], axis=1), dtype=torch.float64)


def _ftheta_errors_px(pinhole, ftheta) -> tuple[np.ndarray, np.ndarray]:
    """Over every pixel centre, through NCore's own camera models: |ftheta projection of the pinhole
    ray - the pixel| and |pinhole projection of the ftheta ray - the pixel|, px."""
    width, height = (int(v) for v in pinhole.resolution)
    pixels = _pixel_centres(width, height)
    ideal, fitted = _ncore_model(pinhole), _ncore_model(ftheta)
    forward = fitted.camera_rays_to_image_points(ideal.image_points_to_camera_rays(pixels)).image_points - pixels
    backward = ideal.camera_rays_to_image_points(fitted.image_points_to_camera_rays(pixels)).image_points - pixels
    return forward.norm(dim=1).numpy(), backward.norm(dim=1).numpy()


def test_default_camera_model_is_the_ideal_pinhole(av2):
    loader = av2["default"].loader
    assert {type(loader.get_camera_sensor(c).model_parameters) for c in loader.camera_ids} == {
        IdealPinholeCameraModelParameters
    }


def test_opencv_pinhole_has_zero_distortion_and_the_pinholes_rays(av2):
    default, opencv = av2["default"].loader, av2["opencv"].loader
    assert set(opencv.camera_ids) == set(default.camera_ids) and len(opencv.camera_ids) == 9
    for camera_id in opencv.camera_ids:
        params = opencv.get_camera_sensor(camera_id).model_parameters
        assert isinstance(params, OpenCVPinholeCameraModelParameters)
        coefficients = np.concatenate([params.radial_coeffs, params.tangential_coeffs, params.thin_prism_coeffs])
        assert not coefficients.any()
        pinhole = default.get_camera_sensor(camera_id).model_parameters
        pixels = _pixel_centres(*(int(v) for v in pinhole.resolution), step=7)
        rays = _ncore_model(params).image_points_to_camera_rays(pixels)
        truth = _ncore_model(pinhole).image_points_to_camera_rays(pixels)
        assert float((rays - truth).norm(dim=1).max()) < 1e-6


@pytest.mark.parametrize(
    "dataset, camera_id",
    [("av2", "ring_front_center"), ("av2", "ring_rear_left"), ("tbv", "ring_side_left"), ("opv2v", "camera_front")],
)
def test_ftheta_within_half_a_pixel_of_the_pinhole_over_every_pixel_centre(dataset, camera_id, av2, tbv, opv2v):
    """The acceptance figures of issue 19: worst <= 0.5 px, median <= 0.05 px, per camera type (AV2's
    portrait 1550x2048 front camera, a 2048x1550 ring camera, TbV's half resolution, OPV2V's 100° HFOV)."""
    if dataset == "opv2v":
        agent = next(iter(opv2v.truth.agents))
        fitted = opv2v.loader("consumer", agent)
        pinhole = opv2v.loader("default", agent).get_camera_sensor(camera_id).model_parameters
    elif dataset == "tbv":
        fitted, pinhole = tbv.loader, _tbv_pinhole(tbv, camera_id)
    else:
        fitted = av2["consumer"].loader
        pinhole = av2["default"].loader.get_camera_sensor(camera_id).model_parameters
    params = fitted.get_camera_sensor(camera_id).model_parameters
    assert isinstance(params, FThetaCameraModelParameters) and isinstance(pinhole, IdealPinholeCameraModelParameters)
    forward, backward = _ftheta_errors_px(pinhole, params)
    assert len(forward) == int(pinhole.resolution[0]) * int(pinhole.resolution[1])
    assert forward.max() <= 0.5 and np.median(forward) <= 0.05, (forward.max(), np.median(forward))
    assert backward.max() <= 0.5 and np.median(backward) <= 0.05
    meta = _camera_meta(fitted, camera_id)["camera_model"]
    assert meta["type"] == "ftheta"
    assert meta["ftheta_fit"]["max_reprojection_error_px"] == pytest.approx(forward.max(), abs=2e-3)


def _camera_meta(loader, camera_id: str) -> dict:
    return component_meta(loader, CameraSensorComponent, camera_id)


def _tbv_pinhole(tbv: Converted, camera_id: str) -> IdealPinholeCameraModelParameters:
    """The TbV camera as the generator wrote it (calibration/intrinsics.feather), as an NCore pinhole."""
    intr = read_intrinsics(tbv.truth.log_dir)[camera_id]
    return IdealPinholeCameraModelParameters(
        resolution=np.array([intr.width_px, intr.height_px], dtype=np.uint64),
        shutter_type=ShutterType.GLOBAL,
        principal_point=np.array([intr.cx_px + 0.5, intr.cy_px + 0.5], dtype=np.float32),
        focal_length=np.array([intr.fx_px, intr.fy_px], dtype=np.float32),
    )


def test_av2_original_distortion_is_kept_in_every_camera_model(av2):
    for run in ("default", "consumer", "opencv"):
        for camera_id in av2[run].loader.camera_ids:
            assert set(_camera_meta(av2[run].loader, camera_id)["av2_original_distortion"]) == {"k1", "k2", "k3"}


# --- class names and label sources -----------------------------------------------------------------


def _cuboids_meta(loader) -> dict:
    return component_meta(loader, CuboidsComponent, "default")


def test_av2_class_names_and_label_source(av2):
    categories = {box.track_uuid: box.category for box in av2["default"].truth.scene.boxes}
    default = list(av2["default"].loader.get_cuboid_track_observations())
    consumer = list(av2["consumer"].loader.get_cuboid_track_observations())
    assert {o.source for o in default} == {LabelSource.EXTERNAL}
    assert {o.source for o in consumer} == {LabelSource.AUTOLABEL}
    assert {o.class_id for o in default} == {"car", "pedestrian", "bollard"}  # NCore's AV2 converter's class map
    assert all(o.class_id == categories[o.track_id] for o in consumer)  # --class-names source
    for run in ("default", "consumer"):
        meta = _cuboids_meta(av2[run].loader)
        assert meta[contract.SOURCE_CLASS_BY_TRACK] == {o.track_id: categories[o.track_id] for o in default}
    assert "not a provenance claim" in _cuboids_meta(av2["consumer"].loader)["label_source_note"]


def test_opv2v_class_names_and_label_source(opv2v):
    agent = next(iter(opv2v.truth.agents))
    expected = {
        "default": ({"car"}, LabelSource.GT_SYNTHETIC),
        "consumer": ({"vehicle"}, LabelSource.AUTOLABEL),
        "external": ({"car"}, LabelSource.EXTERNAL),
    }
    for run, (classes, source) in expected.items():
        observations = list(opv2v.loader(run, agent).get_cuboid_track_observations())
        assert {o.class_id for o in observations} == classes and {o.source for o in observations} == {source}
        meta = _cuboids_meta(opv2v.loader(run, agent))
        assert set(meta[contract.SOURCE_CLASS_BY_TRACK].values()) == {"vehicle"}


def test_a_category_outside_the_table_is_kept_and_reported_once():
    observations = TrackObservations(
        ["a", "a", "b", "c"], np.array([0, 1, 0, 0]), np.zeros((4, 3)), np.tile(np.eye(3), (4, 1, 1)), np.ones((4, 3))
    )
    labels = cuboid_labels(
        observations,
        ["REGULAR_VEHICLE", "REGULAR_VEHICLE", "HOVERCRAFT", "HOVERCRAFT"],
        AV2_TO_NCORE,
        "ncore",
        "auto",
        "EXTERNAL",
        "world",
        "log/annotations.feather",
    )
    assert labels.class_ids == ["car", "car", "HOVERCRAFT", "HOVERCRAFT"] and labels.label_source == "EXTERNAL"
    assert labels.warnings == [
        "log/annotations.feather: categories without an NCore class name kept as they are: HOVERCRAFT"
    ]


# --- dynamic tracks and dynamic_flag ---------------------------------------------------------------


def _track(t_us: np.ndarray, xy_m: np.ndarray) -> np.ndarray:
    return np.column_stack([xy_m, np.full(len(t_us), 0.8)])


def test_box_motion_tells_jitter_strays_and_slow_motion_apart():
    """Known motions over a 15 s track at 10 Hz: jitter of 1.4 m peak with a stray box, a creeper,
    a car that waits 10 s and drives off, one that drives off and comes back, a moving sign."""
    rng = np.random.default_rng(0)
    t_us = np.arange(0, 15_000_000, 100_000)
    t_s = t_us * 1e-6
    walk = np.cumsum(rng.normal(0, 1, (len(t_us), 2)), axis=0)
    walk -= np.linspace(0, 1, len(t_us))[:, None] * walk[-1]  # a walk that returns
    parked = _track(t_us, np.array([10.0, 5.0]) + walk * (1.4 / np.linalg.norm(walk, axis=1).max()))
    parked[70] += [6.0, -3.0, 0.0]  # one stray observation, 6.7 m off
    net, deviation = box_motion(t_us, parked)
    assert net < 1.5 and deviation < 1.6 and not track_motion(t_us, parked, None).dynamic
    creeper = _track(t_us, np.column_stack([np.clip(t_s - 3.0, 0, 8) * 0.5, np.zeros(len(t_us))]))  # 4 m
    assert box_motion(t_us, creeper)[0] == pytest.approx(4.0, abs=0.01)
    stop_and_go = _track(t_us, np.column_stack([np.clip(t_s - 10.0, 0, None) * 3.0, np.zeros(len(t_us))]))
    back = _track(t_us, np.column_stack([4.0 * np.sin(np.pi * t_s / 15.0), np.zeros(len(t_us))]))
    net_back, deviation_back = box_motion(t_us, back)
    assert net_back < 0.5 and deviation_back > dynamic.DEVIATION_DYNAMIC_M  # caught by the deviation only
    ids = ["parked"] * 150 + ["creeper"] * 150 + ["go"] * 150 + ["back"] * 150 + ["ped"] * 3 + ["sign"] * 150
    classes = ["car"] * 600 + ["pedestrian"] * 3 + ["sign"] * 150
    times = np.concatenate([t_us] * 4 + [t_us[:3], t_us])
    centres = np.concatenate([parked, creeper, stop_and_go, back, parked[:3], creeper])  # the "sign" moves
    observations = TrackObservations(ids, times, centres, np.tile(np.eye(3), (len(ids), 1, 1)), np.ones((len(ids), 3)))
    decided = {t: m.dynamic for t, m in classify_tracks(observations, classes).items()}
    assert decided == {"parked": False, "creeper": True, "go": True, "back": True, "ped": True, "sign": False}


def test_measured_speeds_decide_when_every_observation_has_one():
    t_us = np.arange(0, 2_000_000, 100_000)
    still = _track(t_us, np.zeros((len(t_us), 2)))
    assert track_motion(t_us, still, np.full(len(t_us), 0.5)).dynamic  # 1.8 km/h, though the box stands still
    assert not track_motion(t_us, still, np.full(len(t_us), 0.2)).dynamic  # 0.72 km/h
    assert track_motion(t_us, still, np.where(t_us > 0, 0.0, np.nan)).max_speed_mps is None  # one missing: boxes


def test_static_pose_is_the_median_box():
    """The median centre and size, and the medoid rotation: a flipped box does not turn it."""
    rng = np.random.default_rng(1)
    yaw = 0.3 + rng.normal(0, 0.02, 41)
    yaw[5] += np.pi  # an annotator flipped the heading once
    R = Rotation.from_euler("z", yaw[:, None]).as_matrix()
    centres = np.array([3.0, -2.0, 0.7]) + rng.normal(0, 0.2, (41, 3))
    centres[7] += 5.0
    dims = np.array([4.5, 1.9, 1.5]) + rng.normal(0, 0.05, (41, 3))
    centre, R_med, dim = static_pose(centres, R, dims)
    np.testing.assert_allclose(centre, np.median(centres, axis=0))
    np.testing.assert_allclose(dim, np.median(dims, axis=0))
    assert abs(Rotation.from_matrix(R_med).as_euler("xyz")[2] - 0.3) < 0.02


def test_dynamic_tracks_are_the_generators_moving_boxes(av2):
    truth = av2["default"].truth
    annotated = {o.track_id for o in av2["default"].loader.get_cuboid_track_observations()}
    moving = {b.track_uuid for b in truth.scene.boxes if b.category == "PEDESTRIAN" or np.any(b.velocity_mps)}
    dynamic = _cuboids_meta(av2["default"].loader)[contract.DYNAMIC_TRACKS]
    assert set(dynamic) == moving & annotated and len(dynamic) > 5
    assert all(set(figures) == {"net_m", "peak_deviation_m"} for figures in dynamic.values())


def _flags(loader, lidar_id: str) -> list[np.ndarray]:
    """Every frame's dynamic_flag through the point-cloud-source API, as 3DGRUT reads it."""
    source = loader.get_point_clouds_source(lidar_id)
    lidar = loader.get_lidar_sensor(lidar_id)
    flags = []
    for i in range(source.pcs_count):
        flag = source.get_pc_generic_data(i, "dynamic_flag")
        assert flag.dtype == np.int8 and flag.shape == (lidar.get_frame_ray_bundle_count(i),)
        flags.append(flag)
    return flags


def test_av2_dynamic_flag_matches_the_generators_truth(av2):
    """Every point that hits a moving box or a pedestrian is flagged (recall 1), and the flags are the
    rule's truth (the generator's exact box at each point's own time, grown by 0.5 m)."""
    run = av2["default"]
    truth, boxes = run.truth, run.truth.scene.boxes
    is_dynamic = np.array([b.category == "PEDESTRIAN" or (b.annotated and np.any(b.velocity_mps)) for b in boxes])
    hits = flagged = hit_flagged = rule = rule_flagged = 0
    for unit_index, unit in enumerate(UNITS):
        for sweep, flag in zip(truth.sweeps, _flags(run.loader, unit), strict=True):
            rows = sweep.unit == unit_index
            flag = flag.astype(bool)
            hit = (sweep.box_index[rows] >= 0) & is_dynamic[sweep.box_index[rows]]
            t_s = (sweep.time_ns[rows] - truth.t0_ns) * 1e-9
            T_sensor_city = truth.scene.ego.T_ego_city(t_s) @ truth.T_sensor_ego[unit]
            xyz = sweep.direction_sensor[rows] * sweep.distance_m[rows, None]
            xyz_city = np.einsum("nij,nj->ni", T_sensor_city[:, :3, :3], xyz) + T_sensor_city[:, :3, 3]
            inside = np.zeros(len(xyz), dtype=bool)
            for box in (b for b, d in zip(boxes, is_dynamic, strict=True) if d):
                local = (xyz_city - box.center_m(t_s)) @ box.rotation
                inside |= np.all(np.abs(local) <= box.dims_m / 2 + 0.5, axis=1)
            hits, hit_flagged = hits + hit.sum(), hit_flagged + (hit & flag).sum()
            flagged, rule, rule_flagged = (
                flagged + flag.sum(),
                rule + inside.sum(),
                rule_flagged + (inside & flag).sum(),
            )
    assert hits > 1000 and hit_flagged == hits  # recall on the points that hit dynamic objects
    assert rule_flagged / rule > 0.999 and rule_flagged / flagged > 0.999  # the rule, up to float16 sources
    assert hit_flagged / flagged > 0.7  # the rest: ground and parked neighbours within the 0.5 m margin


def test_opv2v_dynamic_flag_matches_the_generators_truth(opv2v):
    speeds = opv2v.truth.actor_speed_mps
    moving = {actor for actor, speed in speeds.items() if speed > 0}
    moving_hits = flagged_moving = parked_hits = flagged_parked = 0
    for agent_id, agent in opv2v.truth.agents.items():
        for key, flag in zip(opv2v.truth.keys, _flags(opv2v.loader("default", agent_id), "lidar_top"), strict=True):
            actor = agent.hit_actor[key]
            on_moving = np.isin(actor, list(moving))
            on_parked = (actor >= 0) & ~on_moving
            moving_hits, flagged_moving = moving_hits + on_moving.sum(), flagged_moving + flag[on_moving].sum()
            parked_hits, flagged_parked = parked_hits + on_parked.sum(), flagged_parked + flag[on_parked].sum()
    assert moving_hits > 500 and flagged_moving == moving_hits
    assert parked_hits > 100 and flagged_parked <= 0.01 * parked_hits


def test_opv2v_dynamic_tracks_come_from_carlas_speeds(opv2v):
    """OPV2V boxes carry CARLA's exact speeds: they decide, and their maximum is recorded; the static
    tracks' median boxes are in world_global, where the scenario's labels are merged."""
    speeds = opv2v.truth.actor_speed_mps
    meta = _cuboids_meta(opv2v.loader("default", next(iter(opv2v.truth.agents))))
    dynamic, annotated = meta[contract.DYNAMIC_TRACKS], set(meta[contract.SOURCE_CLASS_BY_TRACK])
    assert set(dynamic) == {str(a) for a, v in speeds.items() if v > 1 / 3.6} & annotated and dynamic
    for track, figures in dynamic.items():
        assert figures["max_speed_mps"] == pytest.approx(speeds[int(track)], abs=1e-3)
    assert "measured speeds" in meta["dynamic_rule"]
    static = meta[contract.STATIC_POSES]
    assert static["frame"] == "world_global" and set(static["tracks"]) == annotated - set(dynamic) != set()


def test_tbv_flags_what_the_lidar_saw_move_and_says_so(tbv):
    """TbV has no cuboids: its dynamic_flag comes from the lidar itself (tests/test_motion.py scores it)."""
    meta = tbv.reader.open_component_readers(LidarSensorComponent.Reader)
    for unit in UNITS:
        assert tbv.loader.get_point_clouds_source(unit).has_pc_generic_data(0, "dynamic_flag")
        note = meta[unit].generic_meta_data["dynamic_flag"]
        assert note.startswith("written: int8 per point, 1 = on a mover the lidar itself saw move"), note


# --- clip window and world_global ------------------------------------------------------------------


def _cli(*args: str) -> subprocess.CompletedProcess:
    return run_cli("--no-progress", *args)


def test_av2_clip_window(tmp_path):
    root, out = tmp_path / "src", tmp_path / "clip"
    truth = write_log(UPath(root / "val"), SynthConfig(seconds=2.0, seed=7, camera_fps=5, pictures=2, camera_scale=4))
    done = _cli(
        "--root-dir",
        str(root),
        "--output-dir",
        str(out),
        "argoverse2-v4",
        "--split",
        "val",
        "--seek-sec",
        "0.55",
        "--duration-sec",
        "0.6",
    )
    assert done.returncode == 0, done.stdout + done.stderr
    sweeps_us = np.array([s.timestamp_ns for s in truth.sweeps]) // 1000
    images_us = np.array([t for t in _image_times_us(truth)])
    start = min(sweeps_us.min(), images_us.min()) + 550_000
    end = start + 600_000
    loader = open_sequence(out / truth.log_id, truth.log_id)
    clip = loader.generic_meta_data[contract.CLIP]
    assert (clip["start_us"], clip["end_us"], clip["seek_sec"], clip["duration_sec"]) == (start, end, 0.55, 0.6)
    kept = sweeps_us[(sweeps_us >= start) & (sweeps_us <= end)]
    for unit in UNITS:
        frames = loader.get_lidar_sensor(unit).frames_timestamps_us
        assert len(frames) == len(kept) == 6
    for camera_id in loader.camera_ids:
        frames = loader.get_camera_sensor(camera_id).frames_timestamps_us.astype(np.int64)
        assert len(frames) and frames.min() >= start and frames.max() <= end
    cuboid_times = {o.timestamp_us for o in loader.get_cuboid_track_observations()}
    assert cuboid_times == set(kept.tolist())
    poses = loader._reader.open_component_readers(PosesComponent.Reader)["default"]
    T_rig_world, pose_us = poses.get_dynamic_pose("rig", "world")
    frames_us = np.concatenate([loader.get_lidar_sensor(u).frames_timestamps_us for u in UNITS]).astype(np.int64)
    assert np.allclose(T_rig_world[0], np.eye(4), atol=1e-6)  # world: the first pose of the window
    assert pose_us[0] <= frames_us.min() and pose_us[-1] >= frames_us.max()
    assert pose_us[-1] - pose_us[0] < 1_000_000  # cut: not the whole 2 s
    report = json.loads((out / "conversion-report.json").read_text())
    assert report["logs"][truth.log_id]["fingerprint"]["options"]["seek_sec"] == 0.55
    assert report["logs"][truth.log_id]["validation"]["ok"]  # validated against the source, window known
    source_check = validate_sequence(UPath(out / truth.log_id / f"{truth.log_id}.json"), UPath(root))
    assert source_check.ok and any(c.name == "frames and cuboids within the clip window" for c in source_check.checks)
    outside = _cli(
        "--root-dir",
        str(root),
        "--output-dir",
        str(tmp_path / "late"),
        "argoverse2-v4",
        "--split",
        "val",
        "--seek-sec",
        "30",
    )
    last = max(sweeps_us.max(), images_us.max())
    lasts = f"the log lasts {(last - min(sweeps_us.min(), images_us.min())) / 1e6:.3f} s"
    assert outside.returncode == 2 and lasts in outside.stdout and "--seek-sec 30" in outside.stdout, outside.stdout
    assert not (tmp_path / "late" / truth.log_id).exists()


def _image_times_us(truth) -> list[int]:
    return [int(p.stem) // 1000 for p in truth.image_paths]


def test_opv2v_clip_window_cuts_frames_labels_and_noise(tmp_path):
    config = synth_opencood.SynthConfig(dataset="opv2v", frames=10, seed=8, lidar_columns=64, render_step=8)
    (truth,) = synth_opencood.write_dataset(UPath(tmp_path / "src"), config)
    done = _cli(
        "--root-dir",
        str(tmp_path / "src"),
        "--output-dir",
        str(tmp_path / "out"),
        "opv2v-v4",
        "--split",
        "test",
        "--seek-sec",
        "0.2",
        "--duration-sec",
        "0.3",
        "--loc-err",
        "--xyz-std",
        "0.5",
    )
    assert done.returncode == 0, done.stdout + done.stderr
    ticks_us = np.array([int(k) for k in truth.keys]) * round(config.fixed_delta_seconds * 1e6)
    start, end = ticks_us[0] + 200_000, ticks_us[0] + 500_000
    kept = ticks_us[(ticks_us >= start) & (ticks_us <= end)]
    for agent_id in truth.agents:
        loader = open_sequence(tmp_path / "out" / truth.scenario / agent_id, f"{truth.scenario}_agent{agent_id}")
        assert loader.get_lidar_sensor("lidar_top").frames_timestamps_us[:, 1].tolist() == kept.tolist()
        assert {o.timestamp_us for o in loader.get_cuboid_track_observations()} == set(kept.tolist())
        noisy = open_sequence_instance(tmp_path / "out" / truth.scenario / agent_id, truth.scenario, agent_id)
        assert noisy["pose_noise_timestamps_us"].tolist() == kept.tolist()
        assert set(noisy["delay_ego_timestamps_us"].tolist()) <= set(kept.tolist())


def open_sequence_instance(agent_dir: Path, scenario: str, agent_id: str) -> dict[str, np.ndarray]:
    """The generic data of the sequence's noise poses instance (named after its model)."""
    reader = SequenceComponentGroupsReader([UPath(agent_dir / f"{scenario}_agent{agent_id}.json")])
    instance = reader.open_component_readers(PosesComponent.Reader)["opencood"]
    return {name: instance.get_generic_data(name) for name in ("pose_noise_timestamps_us", "delay_ego_timestamps_us")}


@pytest.mark.parametrize("mode", ["localized", "identity", "none"])
def test_world_global_modes(mode, av2, tmp_path):
    run = av2["default"]
    root = run.seq_dir.parent.parent / "src"
    out = tmp_path / mode
    options = Argoverse2Options(split="val", world_global_mode=mode, camera_ids=())
    convert_log(UPath(root), UPath(out), run.truth.log_id, options)
    loader = open_sequence(out, run.truth.log_id)
    record = loader.generic_meta_data[contract.WORLD_GLOBAL]
    T_city = run.loader.pose_graph.evaluate_poses("world", "world_global", np.zeros(1, dtype=np.uint64))[0]
    assert record["mode"] == mode and np.allclose(record["T_world_dataset_global"], T_city, atol=1e-9)
    if mode == "none":
        assert "world_global" not in loader.pose_graph.nodes
    else:
        edge = loader.pose_graph.evaluate_poses("world", "world_global", np.zeros(1, dtype=np.uint64))[0]
        assert np.allclose(edge, np.eye(4) if mode == "identity" else T_city, atol=1e-9)
    assert validate_sequence(UPath(out / f"{run.truth.log_id}.json"), UPath(root)).ok
    # the dataset's global frame stays reachable: the same points in it whatever the mode
    np.testing.assert_allclose(
        world_points(loader, "up_lidar", 0, "world_global")[0],
        world_points(run.loader, "up_lidar", 0, "world_global")[0],
        atol=1e-6,
    )


def test_tbv_clip_window(tbv, tmp_path):
    """TbV's window cuts to the sweeps and images whose times lie in it, validates against the source."""
    truth = tbv.truth
    root = tbv.seq_dir.parent / "src"
    options = Argoverse2Options(split=None, seek_sec=0.2, duration_sec=0.25, ego_masks="none")
    convert_log(UPath(root), UPath(tmp_path / "out"), truth.log_id, options)
    loader = open_sequence(tmp_path / "out", truth.log_id)
    clip = loader.generic_meta_data[contract.CLIP]
    sweeps_us = np.array([s.timestamp_ns for s in truth.sweeps]) // 1000
    images_us = np.array(_image_times_us(truth))
    start = min(sweeps_us.min(), images_us.min()) + 200_000
    assert (clip["start_us"], clip["end_us"]) == (start, start + 250_000)
    kept = sweeps_us[(sweeps_us >= start) & (sweeps_us <= start + 250_000)]
    assert all(loader.get_lidar_sensor(u).frames_count == len(kept) >= 2 for u in UNITS)
    assert validate_sequence(UPath(tmp_path / "out" / f"{truth.log_id}.json"), UPath(root)).ok
