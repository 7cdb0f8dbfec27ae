"""Issue 38: cooperative scenarios as real files come: a single tick (OpenCOOD's and OpenCDA's own
sample data, snapshots cut to one frame), and scenarios where some agents have one tick and others
many. Every agent with a readable frame is written; its pose is the tick's, followed 1 µs later by
the ego_speed extrapolation NCore's two-pose minimum needs; everything round-trips exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import component_meta
from ncore.data.v4 import LidarSensorComponent
from test_opencood_view import NOISE, _same_tree_but_pcds, assert_same_points, opencood_pcd
from upath import UPath

from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.evaluate import evaluate_lidar_model
from ncore_convert.sources.opencood import load_yaml
from ncore_convert.synth import opencood as synth
from ncore_convert.transforms import carla
from ncore_convert.transforms.geometry import invert_se3
from ncore_convert.validate.readback import open_sequence
from ncore_convert.validate.report import summarise
from ncore_convert.validate.tree import validate_tree
from ncore_convert.views.opencood import OpenCoodScenario
from ncore_convert.views.opencood_export import export_opencood


def convert_both_layouts(tmp: Path, truth, dataset: str = "v2xset", noise=()) -> dict[str, Path]:
    outs = {}
    for layout in ("agents", "scenario"):
        out = tmp / layout / truth.scenario
        summary = convert_scenario(
            UPath(tmp / "src"), UPath(out), truth.scenario, OpenCoodOptions(dataset, "test", layout, noise=noise)
        )
        assert summary.agents and not [w for w in summary.warnings if "not written" in w], summary.warnings
        outs[layout] = out
    return outs


def assert_valid_and_exact(tmp: Path, truth, outs: dict[str, Path]) -> None:
    """Every sequence opens, passes ``validate --source``; the export is the raw scenario, every
    non-PCD file byte for byte and every point bit for bit."""
    for layout, out in outs.items():
        target = out / "scenario.json" if layout == "scenario" else out  # validate takes either
        reports = validate_tree(UPath(target), UPath(tmp / "src"))
        assert len(reports) >= 2 and summarise(reports)["ok"], summarise(reports)["failed"]  # sequences + manifest
        exported = Path(export_opencood(UPath(out / "scenario.json"), UPath(tmp / f"export-{layout}"))[0])
        for name in _same_tree_but_pcds(Path(truth.scenario_dir), exported):
            raw, back = opencood_pcd(Path(truth.scenario_dir) / name), opencood_pcd(exported / name)
            assert_same_points(back.astype(np.float32), raw)


@pytest.fixture(scope="module")
def one_tick(tmp_path_factory):
    """The shape of a real V2XSet scenario that failed before issue 38: one tick, three CAVs and an
    RSU, CAV lidars on 32 rings of 1,563 columns with CARLA's range noise and drop-off, and a
    data_protocol.yaml from another run that says 64 channels."""
    tmp = tmp_path_factory.mktemp("one-tick")
    lidar = {"lidar_channels": 32, "lidar_columns": 1563, "lidar_noise_stddev": 0.02, "lidar_dropoff_rate": 0.1}
    config = synth.SynthConfig(
        dataset="v2xset", frames=1, seed=11, cavs=3, protocol_lidar=(("channels", 64),), render_step=8, **lidar
    )
    (truth,) = synth.write_dataset(UPath(tmp / "src"), config)
    return tmp, truth, convert_both_layouts(tmp, truth, noise=(NOISE,))


def test_a_one_tick_scenario_converts_validates_and_round_trips(one_tick):
    tmp, truth, outs = one_tick
    assert len(truth.keys) == 1 and any(int(a) < 0 for a in truth.agents)
    assert_valid_and_exact(tmp, truth, outs)


def test_the_one_tick_pose_rule(one_tick):
    """The tick's pose at the tick, and 1 µs later moved by ego_speed along the rig's forward axis
    (a CAV: 8 m/s gives 8 µm; infrastructure: held); the lidar frame spans [t, t]."""
    tmp, truth, outs = one_tick
    (key,) = truth.keys
    for agent_id in truth.agents:
        loader = open_sequence(UPath(outs["agents"] / agent_id / f"{truth.scenario}_agent{agent_id}.json")).loader
        lidar = loader.get_lidar_sensor("lidar_top")
        t_us = int(lidar.frames_timestamps_us[0, 1])
        assert lidar.frames_count == 1 and int(lidar.frames_timestamps_us[0, 0]) == t_us
        T = loader.pose_graph.evaluate_poses("rig", "world_global", np.array([t_us, t_us + 1], dtype=np.uint64))
        step_rig = (invert_se3(T[0]) @ T[1])[:3, 3]
        speed_mps = load_yaml(UPath(Path(truth.scenario_dir) / agent_id / f"{key}.yaml"))["ego_speed"] / 3.6
        np.testing.assert_allclose(step_rig, [speed_mps * 1e-6, 0.0, 0.0], atol=2e-6)
        T_lidar = loader.pose_graph.evaluate_poses("lidar_top", "world_global", np.array([t_us], dtype=np.uint64))[0]
        pose = carla.carla_pose_from_matrix(carla.mirror_transform(T_lidar))
        np.testing.assert_allclose(pose[:3], truth.agents[agent_id].lidar_pose[key][:3], atol=1e-3)


def test_the_cav_lidars_get_their_model_from_the_points(one_tick):
    """The protocol's 64 channels do not fit: 32 lasers x 1,563 columns measured from one tick's
    points, within 0.01 deg of every far ray; the RSU's own protocol block fits and is used."""
    _, truth, outs = one_tick
    for agent_id in truth.agents:
        loader = open_sequence(UPath(outs["agents"] / agent_id / f"{truth.scenario}_agent{agent_id}.json")).loader
        params = loader.get_lidar_sensor("lidar_top").model_parameters
        assert (params.n_rows, params.n_columns) == (32, 1563)  # the RSU's block: 32 channels too
        report = evaluate_lidar_model(loader, "lidar_top")
        assert report.far_points > 1000 and report.far_mean_deg <= 0.01
        meta = component_meta(loader, LidarSensorComponent, "lidar_top")["lidar_model"]
        assert meta["model_source"] == ("protocol" if int(agent_id) < 0 else "points")


def test_noise_settings_on_one_tick(one_tick):
    """The noise setting's poses instance and delays exist for the one tick (no delay is possible)."""
    _, truth, outs = one_tick
    view = OpenCoodScenario.open(outs["agents"] / "scenario.json", poses="wild")
    (key,) = truth.keys
    for agent_id in view.agent_ids:
        assert view.delayed_key(agent_id, key) == key
        assert np.all(np.isfinite(view.lidar_pose(agent_id, key)))


def test_an_agent_with_one_tick_beside_agents_with_more(tmp_path):
    """An OPV2V CAV with a single tick beside a 3-tick one: written in both layouts, nothing dropped, its
    sequence (or rig) spans its tick only, and the scenario round-trips."""
    config = synth.SynthConfig(dataset="opv2v", frames=3, seed=12, lidar_columns=256, render_step=8)
    (truth,) = synth.write_dataset(UPath(tmp_path / "src"), config)
    short = next(a for a in truth.agents if int(a) > 0)
    for key in truth.keys[:1] + truth.keys[2:]:
        for path in (Path(truth.scenario_dir) / short).glob(f"{key}*"):
            path.unlink()
    outs = convert_both_layouts(tmp_path, truth, "opv2v")
    view = OpenCoodScenario.open(outs["scenario"] / "scenario.json")
    assert sorted(view.agent_ids) == sorted(truth.agents)
    full = next(a for a in truth.agents if a != short)
    assert view.keys(short) == [truth.keys[1]] and view.keys(full) == truth.keys
    raw = opencood_pcd(Path(truth.scenario_dir) / short / f"{truth.keys[1]}.pcd")
    assert_same_points(view.lidar_points(short, truth.keys[1]), raw)
    assert_valid_and_exact(tmp_path, truth, outs)
