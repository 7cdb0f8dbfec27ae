"""``preview``: the projected lidar points of a known box fall inside that box's outline, projected
independently from the generator's truth (camera pose, intrinsics, box)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.path import Path as PolyPath
from PIL import Image
from scipy.spatial import ConvexHull
from upath import UPath

from ncore_convert.cli import cli
from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.preview import preview_scenario, preview_sequence
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.noise_config import make_setting
from ncore_convert.sources.opencood import load_yaml
from ncore_convert.synth.opencood import SynthConfig as OpenCoodConfig
from ncore_convert.synth.opencood import write_dataset

MARGIN_M = 0.05  #: lidar hits lie on box faces: the box is grown by this on every side, outline too
EDGE_SAMPLES = 2  #: points per box edge projected for the truth outline (its corners: pinhole keeps lines straight)


def truth_pixels(xyz_city: np.ndarray, city_SE3_cam: np.ndarray, intr: av2.CameraIntrinsics) -> np.ndarray:
    """Ideal pinhole projection (AV2 images are rectified; k1..k3 describe the original lens), written
    out here: [N,2] px."""
    xyz_cam = (xyz_city - city_SE3_cam[:3, 3]) @ city_SE3_cam[:3, :3]
    assert np.all(xyz_cam[:, 2] > 0.5), "the box must lie in front of the camera"
    xy = xyz_cam[:, :2] / xyz_cam[:, 2:]
    return np.column_stack([intr.fx_px * xy[:, 0] + intr.cx_px, intr.fy_px * xy[:, 1] + intr.cy_px])


def box_edges_city(box, t_s: float, margin_m: float = MARGIN_M) -> np.ndarray:
    """Points along the 12 edges of a generator box (grown by margin_m) at time t_s, city, [12*EDGE_SAMPLES, 3]."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    pairs = [(i, j) for i in range(8) for j in range(i + 1, 8) if np.sum(corners[i] != corners[j]) == 1]
    s = np.linspace(0, 1, EDGE_SAMPLES)[:, None]
    local = np.concatenate([corners[i] + s * (corners[j] - corners[i]) for i, j in pairs]) * (box.dims_m / 2 + margin_m)
    T = box.T_box_city(t_s)
    return local @ T[:3, :3].T + T[:3, 3]


def inside_box(xyz_city: np.ndarray, box, t_s: float, margin_m: float = MARGIN_M) -> np.ndarray:
    T = box.T_box_city(t_s)
    local = (xyz_city - T[:3, 3]) @ T[:3, :3]
    return np.all(np.abs(local) <= box.dims_m / 2 + margin_m, axis=1)


@pytest.fixture(scope="module")
def previewed(synth_log, tmp_path_factory):
    out = tmp_path_factory.mktemp("preview")
    (meta,) = synth_log.seq_dir.glob("*.json")
    return preview_sequence(UPath(meta), UPath(out), frame=5)


def test_projected_box_points_fall_inside_the_boxs_projected_outline(synth_log, previewed):
    truth = synth_log.truth
    intrinsics = av2.read_intrinsics(truth.log_dir)
    T_global_world = synth_log.loader.pose_graph.evaluate_poses("world", "world_global", np.array([0], np.uint64))[0]
    checked_boxes, checked_points = 0, 0
    for projection in previewed.cameras:
        t_ns = projection.timestamp_us * 1000
        t_s = (t_ns - truth.t0_ns) * 1e-9
        city_SE3_cam = truth.T_ego_city(np.array([t_ns]))[0] @ truth.T_sensor_ego[projection.camera_id]
        xyz_city = projection.xyz_world_m @ T_global_world[:3, :3].T + T_global_world[:3, 3]  # AV2: world_global = city
        for box in truth.scene.boxes:
            if not box.annotated or np.any(box.velocity_mps):  # static boxes: the lidar and camera times agree
                continue
            hits = inside_box(xyz_city, box, t_s)
            if hits.sum() < 5:
                continue
            outline = truth_pixels(box_edges_city(box, t_s), city_SE3_cam, intrinsics[projection.camera_id])
            hull = PolyPath(outline[ConvexHull(outline).vertices])
            inside = hull.contains_points(projection.pixels[hits], radius=2.0) | hull.contains_points(
                projection.pixels[hits], radius=-2.0
            )
            assert inside.all(), (projection.camera_id, box.track_uuid, projection.pixels[hits][~inside][:5])
            checked_boxes += 1
            checked_points += int(hits.sum())
    assert checked_boxes >= 3 and checked_points >= 100, (checked_boxes, checked_points)


def test_a_wrong_camera_pose_would_be_caught(synth_log, previewed):
    """The check above can fail: with the truth camera moved 0.5 m sideways, box points leave the outline."""
    truth = synth_log.truth
    intrinsics = av2.read_intrinsics(truth.log_dir)
    T_global_world = synth_log.loader.pose_graph.evaluate_poses("world", "world_global", np.array([0], np.uint64))[0]
    outside = 0
    for projection in previewed.cameras:
        t_ns = projection.timestamp_us * 1000
        t_s = (t_ns - truth.t0_ns) * 1e-9
        city_SE3_cam = truth.T_ego_city(np.array([t_ns]))[0] @ truth.T_sensor_ego[projection.camera_id]
        city_SE3_cam[:3, 3] += city_SE3_cam[:3, 0] * 0.5
        xyz_city = projection.xyz_world_m @ T_global_world[:3, :3].T + T_global_world[:3, 3]
        for box in truth.scene.boxes:
            hits = inside_box(xyz_city, box, t_s)
            if not box.annotated or np.any(box.velocity_mps) or hits.sum() < 5:
                continue
            outline = truth_pixels(box_edges_city(box, t_s), city_SE3_cam, intrinsics[projection.camera_id])
            outside += int(
                (~PolyPath(outline[ConvexHull(outline).vertices]).contains_points(projection.pixels[hits])).sum()
            )
    assert outside > 50


def test_preview_writes_readable_pngs_for_every_camera_and_the_bev(synth_log, previewed):
    assert {p.camera_id for p in previewed.cameras} == set(synth_log.loader.camera_ids)
    for png in [previewed.bev] + [p.png for p in previewed.cameras]:
        with Image.open(str(png)) as image:
            assert image.format == "PNG" and image.size[0] >= 800
    ranges = np.concatenate([p.range_m for p in previewed.cameras])
    assert ranges.min() > 0 and np.all(np.isfinite(ranges))


def test_camera_titles_name_the_lidar_frame_of_the_file_names(synth_log, tmp_path, monkeypatch):
    """Each camera picture is the camera's frame nearest the lidar frame of the file name
    (``_f0005_``); its title says both."""
    titles: list[str] = []
    set_title = Axes.set_title
    monkeypatch.setattr(
        Axes, "set_title", lambda ax, label, *a, **k: titles.append(label) or set_title(ax, label, *a, **k)
    )
    (meta,) = synth_log.seq_dir.glob("*.json")
    written = preview_sequence(UPath(meta), UPath(tmp_path), frame=5)
    assert all("_f0005_" in p.png.name for p in written.cameras)
    cameras = [t for t in titles if "bird's-eye" not in t]
    assert len(cameras) >= len(written.cameras) and all("(at lidar frame 5)" in t for t in cameras), cameras


def test_cooperative_preview_and_the_command(tmp_path):
    config = OpenCoodConfig(dataset="v2xset", frames=4, seed=6, cavs=2, infrastructure=True, lidar_columns=180)
    (truth,) = write_dataset(UPath(tmp_path / "src"), config)
    noise = make_setting({"name": "gps", "loc_err": True, "xyz_std": 1.0, "ryp_std": 2.0})
    out = tmp_path / "out" / truth.scenario
    convert_scenario(
        UPath(tmp_path / "src"),
        UPath(out),
        truth.scenario,
        OpenCoodOptions(dataset="v2xset", split=config.split, noise=(noise,)),
    )
    drawn: list[int] = []  # footprints per line collection: one per agent and panel
    add_collection = Axes.add_collection

    def count(ax, collection, **kwargs):
        if isinstance(collection, LineCollection):
            drawn.append(len(collection.get_segments()))
        return add_collection(ax, collection, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Axes, "add_collection", count)
        png = preview_scenario(UPath(out / "scenario.json"), UPath(tmp_path / "png"))
    with Image.open(str(png)) as image:
        assert image.size[0] > 1.8 * image.size[1]  # ground truth and the noisy instance side by side
    # every agent's cuboids in both panels: at least the vehicles its YAML labels at the shown tick
    # (the middle of the ticks all agents share) plus the CAVs' own boxes
    key = truth.keys[len(truth.keys) // 2]
    labelled = [len(load_yaml(UPath(truth.scenario_dir) / a / f"{key}.yaml")["vehicles"]) for a in sorted(truth.agents)]
    assert len(drawn) == 2 * len(truth.agents) and min(drawn) >= min(labelled) > 0, (drawn, labelled)
    manifest = json.loads((out / "scenario.json").read_text())
    sequence = out / manifest["agents"][0]["sequence"]
    result = CliRunner().invoke(cli, ["preview", str(sequence), "--out", str(tmp_path / "cmd"), "--frame", "1"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name.split("_f0001_")[1] for p in (tmp_path / "cmd").glob("*.png"))[0] == "bev.png"
    bad = CliRunner().invoke(cli, ["preview", str(sequence), "--out", str(tmp_path / "cmd"), "--frame", "99"])
    assert bad.exit_code == 2 and "frame 99 outside" in bad.output
