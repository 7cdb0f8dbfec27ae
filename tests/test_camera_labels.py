"""Depth labels (``transforms.camera_labels.depth_z``) against the generator's truth.

One world: the synthetic AV2 scene (ground, buildings, parked and moving cars, pedestrians). A
VLP-32C on the roof fires one 100 ms sweep through it (``synth.argoverse2.simulate_unit``); a
camera 1.6 m ahead of and 0.5 m below the lidar, at its own time inside the sweep, labels the
sweep's points. The truth of a labelled pixel is the ray cast from the camera through the pixel's
centre at the frame's time (``synth.scene.cast_rays``): the surface the camera really sees there.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import Converted, open_sequence, synth_and_convert
from ncore.impl.data.types import LabelSource, LabelType
from upath import UPath

from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
from ncore_convert.synth.argoverse2 import R_EGO_CAM_FORWARD, SynthConfig, simulate_unit, write_log
from ncore_convert.synth.scene import cast_rays, make_scene
from ncore_convert.transforms.camera_labels import DYNAMIC_DT_US, depth_z
from ncore_convert.transforms.camera_models import Pinhole
from ncore_convert.transforms.dynamic import HOLD_S
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.transforms.visibility import CameraView
from ncore_convert.validate.sequence import validate_sequence

T0_NS = 1_000_000_000
SWEEP_S = (0.5, 0.6)  #: the sweep, seconds from the log start
CAMERA_S = 0.55  #: the camera frame's time
LABEL_SLACK_M = 0.5  #: as the AV2 converter gives its annotated boxes


def _T(R: np.ndarray, t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


T_LIDAR_EGO = _T(np.eye(3), (0.0, 0.0, 1.9))  # lidar -> ego
T_CAMERA_EGO = _T(R_EGO_CAM_FORWARD, (1.6, 0.0, 1.4))  # camera -> ego (OpenCV axes)
PINHOLE = Pinhole((1680.0, 1680.0), (1024.0, 775.0), (2048, 1550))  # an AV2 ring camera


@pytest.fixture(scope="module", params=[5, 6, 7])
def world(request):
    return _world(request.param)


def _world(seed: int, pinhole: Pinhole = PINHOLE):
    """The scene, the sweep's points (city frame, times, moving or not), the camera view, its label."""
    scene = make_scene(np.random.default_rng(seed), 2.0, np.random.default_rng([seed, 1]))
    window_ns = (T0_NS + round(SWEEP_S[0] * 1e9), T0_NS + round(SWEEP_S[1] * 1e9))
    hits = simulate_unit("up_lidar", window_ns, T0_NS, scene, lambda t_s: scene.ego.T_ego_city(t_s) @ T_LIDAR_EGO)
    moving = np.array([bool(np.any(b.velocity_mps)) for b in scene.boxes] + [False])
    dynamic = moving[hits["box_index"]]  # -1 (the ground): the appended False
    times_us = (hits["time_ns"] - T0_NS) // 1000
    T_camera_city = scene.ego.T_ego_city(np.array([CAMERA_S]))[0] @ T_CAMERA_EGO
    solids = [b for b in scene.boxes if b.annotated]
    view = CameraView(
        "ring_front_center",
        round(CAMERA_S * 1e6),
        invert_se3(T_camera_city),
        pinhole,
        solids=(np.stack([b.T_box_city(CAMERA_S) for b in solids]), np.stack([b.dims_m / 2 for b in solids])),
        solids_slack_m=LABEL_SLACK_M,
    )
    label = depth_z(view, hits["xyz_city_m"], times_us, dynamic)
    return scene, hits, times_us, dynamic, T_camera_city, view, label


def _true_depth(scene, T_camera_city: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """z of the surface the camera sees through image points (``u``, ``v``: px, float [K]) at the
    frame's time, m [K]."""
    (fx, fy), (cx, cy) = PINHOLE.focal_length_px, PINHOLE.principal_point_px
    d_camera = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(len(u))], axis=1)
    d_city = d_camera @ T_camera_city[:3, :3].T
    norm = np.linalg.norm(d_city, axis=1)
    origins = np.broadcast_to(T_camera_city[:3, 3], d_city.shape)
    distance, _, _ = cast_rays(origins, d_city / norm[:, None], np.full(len(u), CAMERA_S), scene, 500.0)
    return distance / norm  # along the ray -> along the optical axis (z = 1 per unit of d_camera)


#: Where in a pixel the truth is sampled: an 8 x 8 grid (an eighth of a pixel apart: on the ground
#: 50 m ahead the depth changes by about 0.8 m from one pixel row to the next).
SUBPIXEL = (np.arange(8) + 0.5) / 8


def test_depth_labels_hold_the_surface_the_camera_sees(world):
    """Each labelled pixel holds the depth of a surface the camera sees in that pixel: the truth is
    sampled on an 8 x 8 grid over the pixel (a label is one point somewhere in it: on a road 20 m
    ahead the depth changes by about 3 cm across a full-resolution pixel), and the error is the
    smallest against those samples. Median <= 1 cm; at most 0.5 % occlusion errors (the label more
    than 0.5 m behind everything the pixel shows: a surface seen through a foreground object)."""
    scene, _, _, _, T_camera_city, _, label = world
    lines, cols = np.nonzero(label)
    assert len(lines) > 3000
    du, dv = (a.reshape(-1) for a in np.meshgrid(SUBPIXEL, SUBPIXEL))
    u = (cols[:, None] + du[None, :]).reshape(-1)
    v = (lines[:, None] + dv[None, :]).reshape(-1)
    truth = _true_depth(scene, T_camera_city, u, v).reshape(len(lines), -1)
    error = label[lines, cols][:, None] - truth
    smallest = np.abs(error).min(axis=1)
    assert np.all(np.isfinite(smallest))
    assert np.median(smallest) <= 0.01, np.median(smallest)
    behind_all = np.all(error > 0.5, axis=1)
    assert np.mean(behind_all) <= 0.005, np.mean(behind_all)


def test_depth_labels_cover_the_points_the_camera_sees(world):
    """>= 95 % of the pixels hit by a usable lidar point that is visible from the camera in truth
    (static, or within DYNAMIC_DT_US of the frame; nothing between the camera and the point) are
    labelled; none of the pixels hit only by moving points from other times."""
    scene, hits, times_us, dynamic, T_camera_city, view, label = world
    xyz_camera = hits["xyz_city_m"] @ view.T_world_camera[:3, :3].T + view.T_world_camera[:3, 3]
    ahead = xyz_camera[:, 2] > 0.3
    u, v = PINHOLE.project(np.where(ahead[:, None], xyz_camera, 1.0))
    width, height = PINHOLE.resolution_px
    inside = ahead & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    usable = inside & (~dynamic | (np.abs(times_us - view.timestamp_us) <= DYNAMIC_DT_US))
    idx = np.flatnonzero(usable)
    towards = hits["xyz_city_m"][idx] - T_camera_city[:3, 3]
    distance_m = np.linalg.norm(towards, axis=1)
    origins = np.broadcast_to(T_camera_city[:3, 3], towards.shape)
    first_m, _, _ = cast_rays(origins, towards / distance_m[:, None], np.full(len(idx), CAMERA_S), scene, 500.0)
    visible = idx[first_m >= distance_m - 0.05]
    assert len(visible) > 3000
    pixels = np.unique(v[visible].astype(np.int64) * width + u[visible].astype(np.int64))
    covered = np.mean(label.reshape(-1)[pixels] > 0)
    assert covered >= 0.95, covered
    stale = inside & dynamic & (np.abs(times_us - view.timestamp_us) > DYNAMIC_DT_US)
    only_stale = np.setdiff1d(
        v[stale].astype(np.int64) * width + u[stale].astype(np.int64),
        v[inside & ~stale].astype(np.int64) * width + u[inside & ~stale].astype(np.int64),
    )
    assert not np.any(label.reshape(-1)[only_stale] > 0)


# --- the converter's labels (``--camera-labels depth``) on a synthetic AV2 log --------------------

LABEL_CAMERAS = ("ring_front_center", "ring_side_left")


@pytest.fixture(scope="module")
def labelled(tmp_path_factory) -> Converted:
    """A 1 s synthetic log (10 fps cameras), two cameras, converted with every camera label."""
    config = SynthConfig(seconds=1.0, seed=21, camera_fps=10, keep_truth=True, image_cameras=LABEL_CAMERAS)
    options = Argoverse2Options(
        split="val", camera_ids=LABEL_CAMERAS, camera_labels=("depth", "dynamic", "instance"), ego_masks="none"
    )
    return synth_and_convert(tmp_path_factory.mktemp("labels"), config, options)


def test_one_depth_label_per_camera_frame_read_back_by_the_library(labelled):
    """Each camera has ``depth.z@<camera>``: NCore's DEPTH_Z_M type, one label per camera frame at
    the frame's end time, the camera's size, float32 metres (0 or positive), found by the loader's
    own ``query_camera_labels``; and the sequence validates."""
    loader = labelled.loader
    kinds = ("depth.z", "mask.dynamic", "segmentation.instance")
    assert sorted(loader.camera_labels_ids) == sorted(f"{kind}@{cam}" for cam in LABEL_CAMERAS for kind in kinds)
    for cam in LABEL_CAMERAS:
        (labels,) = loader.query_camera_labels(cam, label_type=LabelType.DEPTH_Z_M)
        assert labels.label_descriptor.label_source == LabelSource.EXTERNAL
        frames_end_us = loader.get_camera_sensor(cam).frames_timestamps_us[:, 1]
        np.testing.assert_array_equal(np.sort(labels.label_timestamps_us), np.sort(frames_end_us))
        width, height = loader.get_camera_sensor(cam).model_parameters.resolution
        lidar_us = [loader.get_lidar_sensor(lidar).frames_timestamps_us for lidar in loader.lidar_ids]
        first_us = min(int(t[0, 0]) for t in lidar_us)
        last_us = max(int(t[-1, 1]) for t in lidar_us)
        empty = 0
        for ts in labels.label_timestamps_us:
            label = labels.get_label(int(ts))
            depth = label.get_data()
            assert depth.dtype == np.float32 and depth.shape == (height, width)
            beyond = ts < first_us - HOLD_S * 1e6 or ts > last_us + HOLD_S * 1e6
            if beyond:  # the cameras run on after the lidar: no moving objects known there
                assert not np.any(depth) and "no lidar sweep within" in label.generic_meta_data["no_measurement"]
                empty += 1
            else:
                assert np.all(depth >= 0) and np.count_nonzero(depth) > 1000
        assert 0 < empty < len(labels.label_timestamps_us) // 2  # this log's cameras end 0.3 s after its lidar
    assert validate_sequence(UPath(labelled.seq_dir / f"{labelled.truth.log_id}.json")).ok


def _label_errors(run: Converted, cam: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every third stored depth label of ``cam`` against the generator's scene seen from the camera
    at the label's time, sampled over each labelled pixel as above: per labelled pixel, the smallest
    |error| (m), whether the label lies more than 0.5 m behind everything the pixel shows (seen
    through something), and more than 0.5 m in front of it (a surface no longer there: a moving
    object's point from another time)."""
    truth, loader = run.truth, run.loader
    (labels,) = loader.query_camera_labels(cam, label_type=LabelType.DEPTH_Z_M)
    f, cx, cy = truth.intrinsics[cam]  # AV2's convention: pixel centres at integers
    du, dv = (a.reshape(-1) for a in np.meshgrid(SUBPIXEL, SUBPIXEL))
    smallest, behind, ahead = [np.zeros(0)], [np.zeros(0, bool)], [np.zeros(0, bool)]
    for ts in labels.label_timestamps_us[1::3]:
        depth = labels.get_label(int(ts)).get_data()
        lines, cols = np.nonzero(depth)
        if not len(lines):  # an empty label beyond the lidar's time (the test above)
            continue
        t_s = (int(ts) * 1000 - truth.t0_ns) * 1e-9
        T_camera_city = truth.scene.ego.T_ego_city(np.array([t_s]))[0] @ truth.T_sensor_ego[cam]
        u = (cols[:, None] + du - 0.5).reshape(-1)  # NCore pixel corners -> AV2 pixel centres
        v = (lines[:, None] + dv - 0.5).reshape(-1)
        d_camera = np.stack([(u - cx) / f, (v - cy) / f, np.ones(len(u))], axis=1)
        d_city = d_camera @ T_camera_city[:3, :3].T
        norm = np.linalg.norm(d_city, axis=1)
        origins = np.broadcast_to(T_camera_city[:3, 3], d_city.shape)
        hit_m, _, _ = cast_rays(origins, d_city / norm[:, None], np.full(len(u), t_s), truth.scene, 500.0)
        error = depth[lines, cols][:, None] - (hit_m / norm).reshape(len(lines), -1)
        smallest.append(np.abs(error).min(axis=1))
        behind.append(np.all(error > 0.5, axis=1))
        ahead.append(np.all(error < -0.5, axis=1))
    return np.concatenate(smallest), np.concatenate(behind), np.concatenate(ahead)


def test_stored_depth_labels_hold_the_surfaces_the_camera_sees(labelled):
    """Through the whole chain (source poses and calibration, the stored trajectory, label times,
    NCore's quantization): each labelled pixel's depth against the generator's scene seen from the
    camera at the label's time, sampled over the pixel as above. Median <= 1 cm, <= 0.5 % occlusion
    errors, <= 0.1 % stale surfaces (a moving object's point from another time), per camera."""
    for cam in LABEL_CAMERAS:
        smallest, behind, ahead = _label_errors(labelled, cam)
        assert len(smallest) > 3000, cam
        assert np.median(smallest) <= 0.01, (cam, np.median(smallest))
        assert np.mean(behind) <= 0.005, (cam, "occlusion errors", np.mean(behind))
        assert np.mean(ahead) <= 0.001, (cam, "stale surfaces", np.mean(ahead))


def test_tbv_depth_labels_use_only_points_near_the_frame(tmp_path):
    """TbV has no cuboids, so which points move is unknown: every point labels only frames within
    5 ms of it. The labels are sparser but right (the same bounds against the truth, passing cars
    included: with every point used at any time, 0.23 % of the labelled pixels showed a car where it
    had been, against 0.04 % now), and their metadata says why."""
    cam = "ring_front_center"
    truth = write_log(
        UPath(tmp_path / "src"),
        SynthConfig(seconds=1.0, seed=22, camera_fps=10, tbv=True, keep_truth=True, image_cameras=(cam,)),
    )
    options = Argoverse2Options(split=None, camera_ids=(cam,), camera_labels=("depth",), ego_masks="none")
    summary = convert_log(UPath(tmp_path / "src"), UPath(tmp_path / "out"), truth.log_id, options)
    run = Converted(truth, summary, tmp_path / "out", open_sequence(tmp_path / "out", truth.log_id))
    (labels,) = run.loader.query_camera_labels(cam, label_type=LabelType.DEPTH_Z_M)
    assert "unknown (no cuboids)" in labels.labels_generic_meta_data["moving_objects"]
    smallest, behind, ahead = _label_errors(run, cam)
    assert len(smallest) > 500
    assert np.median(smallest) <= 0.01 and np.mean(behind) <= 0.005, (np.median(smallest), np.mean(behind))
    assert np.mean(ahead) <= 0.001, ("stale surfaces", np.mean(ahead))


class _Labels:
    """What the label check reads of one label component (the library's ``CameraLabels``)."""

    def __init__(self, stamps_us, data, descriptor):
        self.label_timestamps_us, self._data, self.label_descriptor = np.array(stamps_us, np.uint64), data, descriptor

    def get_label(self, ts):
        data = self._data(ts)
        return type("Handle", (), {"get_data": lambda self: data, "generic_meta_data": {}})()


class _Loader:
    """A camera with 10 frames, 40 x 30 px, and the given label components."""

    def __init__(self, labels):
        frames = np.stack([np.arange(10) * 50_000, np.arange(10) * 50_000], axis=1).astype(np.uint64)
        params = type("Params", (), {"resolution": np.array([40, 30])})()
        self._camera = type("Camera", (), {"frames_timestamps_us": frames, "model_parameters": params})()
        self._labels = labels

    def get_camera_sensor(self, camera_id):
        return self._camera

    def query_camera_labels(self, camera_id):
        return self._labels


@pytest.mark.parametrize(
    "fault, failed",
    [
        (None, []),
        ("a frame without a label", ["one per camera frame"]),
        ("a label of the wrong size", ["decodes, the camera's size, valid values"]),
        ("a negative depth", ["decodes, the camera's size, valid values"]),
        ("a label that does not decode", ["decodes, the camera's size, valid values"]),
    ],
)
def test_the_label_checks_find_planted_faults(fault, failed):
    from ncore.impl.data.types import CameraLabelDescriptor, LabelEncoding, LabelSchema

    from ncore_convert.validate.labels import check_camera_labels
    from ncore_convert.validate.report import Report

    descriptor = CameraLabelDescriptor(
        "cam", LabelType.DEPTH_Z_M, LabelSchema(np.dtype("float32"), encoding=LabelEncoding.RAW), LabelSource.EXTERNAL
    )
    stamps = list(np.arange(10) * 50_000)
    good = np.full((30, 40), 0.0, np.float32)
    good[10, 10] = 12.5

    def data(ts):
        if fault == "a label of the wrong size" and ts == stamps[-1]:
            return good[:, :20]
        if fault == "a negative depth" and ts == stamps[0]:
            return good - 1.0
        if fault == "a label that does not decode" and ts == stamps[0]:
            raise ValueError("broken chunk")
        return good

    if fault == "a frame without a label":
        stamps = stamps[:-1]
    report = Report("planted")
    check_camera_labels(report, _Loader([_Labels(stamps, data, descriptor)]), "cam")
    assert len(report.checks) == 2
    assert [c.name.split(": ")[-1] for c in report.checks if not c.ok] == failed, [
        (c.name, c.detail) for c in report.checks
    ]


def test_preview_draws_the_depth_labels(labelled, tmp_path):
    """``preview`` writes ``<stem>_<camera>_depth.png`` for each camera with depth labels: the
    camera's picture at its size with the labelled pixels over it; the lidar projections as before."""
    import PIL.Image

    from ncore_convert.preview import preview_sequence

    shown = preview_sequence(UPath(labelled.seq_dir / f"{labelled.truth.log_id}.json"), UPath(tmp_path))
    assert {p.name for p in shown.depth_labels} == {c.png.name[:-4] + "_depth.png" for c in shown.cameras}
    for png in shown.depth_labels:
        with PIL.Image.open(str(png)) as image:
            assert image.width >= 1000 and image.height > 0


@pytest.mark.parametrize(
    "command, value, message",
    [
        ("argoverse2-v4", "depth,foo", "unknown camera label 'foo'"),
        ("tbv-v4", "depth,instance", "instance: made from the annotated boxes, and TbV has no cuboids"),
        ("tbv-v4", "dynamic", "dynamic: made from the annotated boxes, and TbV has no cuboids"),
    ],
)
def test_camera_labels_unknown_or_impossible_are_usage_errors(tmp_path, command, value, message):
    """A label kind that does not exist, or that the dataset cannot make (TbV has no boxes for
    masks), stops the command before any work, naming it (never a silent run without the labels
    asked for)."""
    from click.testing import CliRunner

    from ncore_convert.cli import cli

    args = ["--root-dir", str(tmp_path), "--output-dir", str(tmp_path / "out"), command]
    args += ["--split", "val"] if command == "argoverse2-v4" else []
    result = CliRunner().invoke(cli, [*args, "--camera-labels", value])
    assert result.exit_code == 2 and message in " ".join(result.output.split()), result.output
    assert not (tmp_path / "out").exists()
