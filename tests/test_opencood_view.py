"""Issue 29: a converted cooperative scenario read back as OpenCOOD reads its raw files
(``views.opencood``) and written back in OpenCOOD's layout (``export-opencood``), against the raw
files themselves: the lidar points as OpenCOOD's PCD reader returns them, each frame's YAML and
``lidar_pose``, the PNGs, ``data_protocol.yaml``, a noise setting's poses and delays, on synthetic
OPV2V and V2XSet (CAVs and infrastructure, both layouts); the real OPV2V agent's round trip is in
``test_real_opv2v.py``."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import BIN, run_cli
from ncore.data.v4 import PosesComponent
from upath import UPath

from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.sources.noise_config import make_setting
from ncore_convert.sources.opencood import load_yaml
from ncore_convert.sources.pcd import read_pcd, red_from_rgb, write_pcd
from ncore_convert.synth import opencood as synth
from ncore_convert.transforms.carla import carla_pose_matrix
from ncore_convert.validate.readback import open_sequence
from ncore_convert.views.opencood import OpenCoodScenario
from ncore_convert.views.opencood_export import export_opencood

#: A noise setting as a user writes OpenCOOD's wild_setting: 0.2 m / 0.2 deg GPS error, 250 ms delay.
NOISE = make_setting(
    {"name": "wild", "seed": 25, "async": True, "async_overhead": 250, "loc_err": True, "xyz_std": 0.2, "ryp_std": 0.2}
)


def opencood_pcd(path: Path) -> np.ndarray:
    """OpenCOOD's ``pcd_to_np`` restated: Open3D's points, and as intensity the red channel of the
    packed ``rgb`` float (its bits as uint32, byte 2) over 255; [N,4]."""
    columns = read_pcd(UPath(path))
    red = (np.asarray(columns["rgb"], dtype=np.float32).view(np.uint32) >> 16) & 0xFF
    return np.stack([columns["x"], columns["y"], columns["z"], red / 255.0], axis=1)


def assert_same_points(got: np.ndarray, raw: np.ndarray) -> None:
    """The raw file's float32 points bit for bit (issue 38), in the file's order, with the intensity."""
    assert got.dtype == np.float32 and got.shape == raw.shape
    same = got[:, :3].view(np.uint32) == np.ascontiguousarray(raw[:, :3], dtype=np.float32).view(np.uint32)
    assert same.all(), f"{np.mean(same.all(axis=1)):.4%} of points bit-identical"
    np.testing.assert_allclose(got[:, 3], raw[:, 3], rtol=1e-6, atol=0)


def assert_same_pose(got: np.ndarray, yaml_pose: list[float]) -> None:
    """The YAML's pose: positions within 1e-6 relative, the angles the same rotation to 1e-6 (NCore
    stores the dynamic poses in float32: ~1e-7 m and 1e-7 rad were seen in the scenario layout)."""
    np.testing.assert_allclose(got[:3], yaml_pose[:3], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(
        carla_pose_matrix(got)[:3, :3], carla_pose_matrix(np.array(yaml_pose))[:3, :3], atol=1e-6
    )


def convert(tmp: Path, dataset: str, layouts=("agents",), frames: int = 3, seed: int = 5):
    """A synthetic scenario with ``NOISE`` stored, converted in each of ``layouts``:
    (truth, {layout: scenario.json})."""
    config = synth.SynthConfig(dataset=dataset, frames=frames, seed=seed, render_step=8)
    (truth,) = synth.write_dataset(UPath(tmp / "src"), config)
    outs = {}
    for layout in layouts:
        out = tmp / layout / truth.scenario
        options = OpenCoodOptions(dataset, "test", layout, noise=(NOISE,))
        convert_scenario(UPath(tmp / "src"), UPath(out), truth.scenario, options)
        outs[layout] = out / "scenario.json"
    return truth, outs


@pytest.fixture(scope="module")
def v2xset(tmp_path_factory):
    return convert(tmp_path_factory.mktemp("view-v2xset"), "v2xset", ("agents", "scenario"), frames=6)


@pytest.mark.parametrize("layout", ["agents", "scenario"])
def test_points_poses_and_ego_equal_the_raw_files(v2xset, layout):
    truth, manifests = v2xset
    view = OpenCoodScenario.open(manifests[layout])
    assert sorted(view.agent_ids) == sorted(truth.agents) and any(int(a) < 0 for a in view.agent_ids)
    raw_agents = sorted(truth.agents)  # OpenCOOD's ego: first by string sort, infrastructure last
    assert view.ego_agent_id == next(a for a in raw_agents if int(a) > 0)
    for agent_id in view.agent_ids:
        agent_dir = Path(truth.scenario_dir) / agent_id
        assert view.keys(agent_id) == truth.keys
        for key in truth.keys:
            assert_same_points(view.lidar_points(agent_id, key), opencood_pcd(agent_dir / f"{key}.pcd"))
            raw_yaml = load_yaml(UPath(agent_dir / f"{key}.yaml"))
            assert_same_pose(view.lidar_pose(agent_id, key), raw_yaml["lidar_pose"])
            assert view.params(agent_id, key) == raw_yaml  # the whole YAML, as OpenCOOD loads it


def test_unknown_agents_keys_and_settings_are_named(v2xset):
    truth, manifests = v2xset
    view = OpenCoodScenario.open(manifests["agents"])
    with pytest.raises(KeyError, match="no written agent '999'"):
        view.lidar_points("999", truth.keys[0])
    with pytest.raises(KeyError, match="has no lidar frame '000001'"):
        view.lidar_points(view.ego_agent_id, "000001")
    with pytest.raises(ValueError, match="no noise setting 'gps' \\(stored: wild\\)"):
        OpenCoodScenario.open(manifests["agents"], poses="gps")


def _same_tree_but_pcds(raw_dir: Path, exported_dir: Path) -> list[str]:
    """The files of both trees are the same, and every non-PCD file byte-identical; returns the PCDs."""
    names = sorted(str(p.relative_to(raw_dir)) for p in raw_dir.rglob("*") if p.is_file())
    assert names == sorted(str(p.relative_to(exported_dir)) for p in exported_dir.rglob("*") if p.is_file())
    for name in names:
        if not name.endswith(".pcd"):
            assert (raw_dir / name).read_bytes() == (exported_dir / name).read_bytes(), name
    return [n for n in names if n.endswith(".pcd")]


@pytest.mark.parametrize("dataset, layout", [("opv2v", "agents"), ("v2xset", "agents"), ("v2xset", "scenario")])
def test_raw_to_ncore_to_raw_is_exact(tmp_path, dataset, layout, v2xset):
    """export-opencood (the command) gives the raw scenario back: the same files, the YAMLs, PNGs and
    data_protocol.yaml byte for byte, every point equal to float32 precision in file order with its
    intensity byte."""
    truth, manifests = v2xset if dataset == "v2xset" else convert(tmp_path / "conv", dataset)
    result = run_cli("export-opencood", str(manifests[layout]), "--out", str(tmp_path / "export"))
    assert result.returncode == 0, result.stderr
    exported = tmp_path / "export" / truth.scenario
    assert f"wrote {exported}: {len(truth.agents)} agents" in result.stdout
    raw = Path(truth.scenario_dir)
    for name in _same_tree_but_pcds(raw, exported):
        raw_points, back = opencood_pcd(raw / name), opencood_pcd(exported / name)
        assert_same_points(back.astype(np.float32), raw_points)
        np.testing.assert_array_equal(np.round(back[:, 3] * 255), np.round(raw_points[:, 3] * 255))
    assert not list((tmp_path / "export").glob(".*"))  # no partial folder left


def test_a_noise_setting_gives_its_poses_and_delays(tmp_path, v2xset):
    """With ``poses=`` a stored setting: ``lidar_pose`` is the true pose plus the stored error
    (``pose_noise``, x y z roll yaw pitch) for every agent and frame, the rest of the YAML is the
    raw one, the delayed key is the stored one, and the export bakes those poses in."""
    truth, manifests = v2xset
    view = OpenCoodScenario.open(manifests["agents"], poses="wild")
    true_view = OpenCoodScenario.open(manifests["agents"])
    perturbed = delayed = 0
    for agent_id in view.agent_ids:
        opened = open_sequence(manifests["agents"].parent / agent_id / f"{truth.scenario}_agent{agent_id}.json")
        data = opened.reader.open_component_readers(PosesComponent.Reader)["wild"]
        error = data.get_generic_data("pose_noise")
        for i, key in enumerate(truth.keys):
            raw = load_yaml(UPath(Path(truth.scenario_dir) / agent_id / f"{key}.yaml"))
            params = view.params(agent_id, key)
            assert {k: v for k, v in params.items() if k != "lidar_pose"} == {
                k: v for k, v in raw.items() if k != "lidar_pose"
            }
            assert_same_pose(np.array(params["lidar_pose"]), list(np.array(raw["lidar_pose"]) + error[i]))
            perturbed += bool(np.any(error[i]))
            source = data.get_generic_data("delay_source_keys")[i]
            assert view.delayed_key(agent_id, truth.keys[i]) == (None if source < 0 else f"{source:06d}")
            assert true_view.delayed_key(agent_id, key) == key
            delayed += view.delayed_key(agent_id, key) not in (key, None)
    assert perturbed >= len(truth.keys) and delayed >= len(truth.keys)  # the setting did something
    folder = export_opencood(manifests["agents"], UPath(tmp_path / "noisy"), poses="wild")[0]
    for agent_id in view.agent_ids:
        for key in truth.keys:
            written = load_yaml(UPath(Path(folder) / agent_id / f"{key}.yaml"))
            assert written == view.params(agent_id, key)


def opencood_early_fusion(scenario_dir: Path, agents: list[str], key: str, comm_range_m: float = 70.0) -> np.ndarray:
    """OpenCOOD's early fusion restated on the raw files (no delay): each agent in OpenCOOD's order
    within ``comm_range_m`` of the ego, its PCD points moved by ``x1_to_x2(agent lidar_pose, ego
    lidar_pose) = inv(x_to_world(ego)) @ x_to_world(agent)``; [N,4]."""
    order = sorted(agents)
    order = order[1:] + order[:1] if int(order[0]) < 0 else order
    poses = {a: np.array(load_yaml(UPath(scenario_dir / a / f"{key}.yaml"))["lidar_pose"]) for a in order}
    ego = poses[order[0]]
    parts = []
    for agent in order:
        if np.hypot(*(poses[agent][:2] - ego[:2])) > comm_range_m:
            continue
        T = np.linalg.inv(carla_pose_matrix(ego)) @ carla_pose_matrix(poses[agent])
        points = opencood_pcd(scenario_dir / agent / f"{key}.pcd")
        xyz = np.c_[points[:, :3], np.ones(len(points))] @ T.T
        parts.append(np.c_[xyz[:, :3], points[:, 3]])
    return np.concatenate(parts)


@pytest.mark.parametrize("layout", ["agents", "scenario"])
def test_the_early_fusion_cloud_equals_opencoods_from_the_raw_files(v2xset, layout):
    truth, manifests = v2xset
    view = OpenCoodScenario.open(manifests[layout])
    for key in truth.keys[::2]:
        expected = opencood_early_fusion(Path(truth.scenario_dir), list(truth.agents), key)
        got = view.cooperative_points(key)
        assert got.shape == expected.shape and len(got) > 10_000
        assert np.abs(got[:, :3] - expected[:, :3]).max() < 1e-3  # 1 mm
        np.testing.assert_allclose(got[:, 3], expected[:, 3], rtol=1e-6)


def test_base_data_and_the_torch_adapter_follow_opencoods_delays(v2xset):
    """Per ego frame: every agent in OpenCOOD's order, the ego undelayed, the others at their stored
    delayed key with ``time_delay`` frames behind and that frame's points and YAML; the torch
    ``Dataset`` gives the same items."""
    from ncore_convert.views.opencood_torch import OpenCoodBaseDataset

    truth, manifests = v2xset
    view = OpenCoodScenario.open(manifests["agents"], poses="wild")
    dataset = OpenCoodBaseDataset(view)
    assert len(dataset) == len(truth.keys)
    late = dataset[len(dataset) - 1]
    assert list(late) == view.opencood_order and late[view.ego_agent_id]["ego"]
    for agent_id, item in late.items():
        key = view.delayed_key(agent_id, truth.keys[-1])
        assert item["time_delay"] == truth.keys.index(truth.keys[-1]) - truth.keys.index(key)
        assert item["time_delay"] == (0 if item["ego"] else 2)  # 250 ms: 2 frames of 100 ms
        np.testing.assert_array_equal(item["lidar_np"], view.lidar_points(agent_id, key))
        raw_pngs = sorted((Path(truth.scenario_dir) / agent_id).glob(f"{key}_camera*.png"))
        assert item["params"] == view.params(agent_id, key) and len(raw_pngs) == 4
        assert {f"{key}_camera{k}.png": png for k, png in item["camera_png"].items()} == {
            p.name: p.read_bytes() for p in raw_pngs
        }


def test_export_usage_errors_are_one_line_and_write_nothing(tmp_path, v2xset):
    truth, manifests = v2xset
    sequence = next(Path(manifests["agents"]).parent.glob("*/*.json"))
    for args, message in (
        ([str(sequence)], "expected a scenario.json"),
        ([str(manifests["agents"]), "--poses", "nope"], "no noise setting 'nope' (stored: wild)"),
    ):
        result = run_cli("export-opencood", *args, "--out", str(tmp_path / "x"))
        assert result.returncode == 2 and message in result.stderr, result.stderr
        assert "Traceback" not in result.stderr and not (tmp_path / "x").exists()


def test_the_export_shows_progress_only_when_asked(tmp_path, v2xset):
    """No cursor escapes without a terminal; with the group's --progress a bar counts the agent-frames."""
    truth, manifests = v2xset
    runs = {}
    for flag in ("--no-progress", "--progress"):
        runs[flag] = subprocess.run(
            [
                str(BIN / "ncore-convert"),
                flag,
                "export-opencood",
                str(manifests["agents"]),
                "--out",
                str(tmp_path / flag),
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert runs[flag].returncode == 0, runs[flag].stderr
    assert "\r" not in runs["--no-progress"].stderr and "agent-frames" not in runs["--no-progress"].stderr
    frames = len(truth.agents) * len(truth.keys)
    assert "agent-frames: 100%" in runs["--progress"].stderr and f"{frames}/{frames}" in runs["--progress"].stderr


#: OpenCDA's lidar layouts: the PCD's fourth field and DATA binary
LAYOUTS = (("rgb", False), ("intensity", True), ("rgb", True), ("intensity", False))


def test_pcd_layouts_and_points_that_are_not_rays_round_trip_as_they_came(tmp_path):
    """One scenario whose frames come in each of OpenCDA's layouts (a float ``intensity`` field
    instead of the packed ``rgb``, ``DATA binary``), with 1 % of the points on a 0.1 m grid in x,
    and points at zero range, -0.0 and NaN coordinates (no direction, so not rays) in one frame: the
    export writes each PCD back in its own layout, every point in place and bit for bit (NaNs and
    signed zeros too), binary files byte for byte."""
    config = synth.SynthConfig(
        dataset="opv2v", frames=2, seed=9, cavs=2, lidar_columns=256, grid_share=0.01, render_step=8
    )
    (truth,) = synth.write_dataset(UPath(tmp_path / "src"), config)
    pcds = sorted(Path(truth.scenario_dir).glob("*/*.pcd"))
    assert len(pcds) == len(LAYOUTS)
    odd = np.array([[0.0, 0.0, 0.0], [0.0, -0.0, 0.0], [np.nan, 1.0, 2.0], [3.0, np.nan, 1.0]], dtype=np.float32)
    for n, (path, (field, binary)) in enumerate(zip(pcds, LAYOUTS, strict=True)):
        data = read_pcd(UPath(path))
        xyz, red = np.stack([data["x"], data["y"], data["z"]], axis=1), red_from_rgb(data["rgb"])
        if n == 0:
            at = [0, 7, 100, len(xyz)]
            xyz, red = np.insert(xyz, at, odd, axis=0), np.insert(red, at, [1, 2, 3, 4])
        intensity = red if field == "rgb" else red.astype(np.float32) / np.float32(255.0)
        write_pcd(UPath(path), xyz, intensity, field, binary)
    out = tmp_path / "out" / truth.scenario
    summary = convert_scenario(UPath(tmp_path / "src"), UPath(out), truth.scenario, OpenCoodOptions("opv2v", "test"))
    assert any(
        "4 lidar points at zero range or with non-finite coordinates not stored as rays" in w for w in summary.warnings
    )
    exported = Path(export_opencood(UPath(out / "scenario.json"), UPath(tmp_path / "export"))[0])
    assert _same_tree_but_pcds(Path(truth.scenario_dir), exported) == [
        str(p.relative_to(truth.scenario_dir)) for p in pcds
    ]
    on_grid = 0
    for path, (field, binary) in zip(pcds, LAYOUTS, strict=True):
        raw, back = read_pcd(UPath(path)), read_pcd(UPath(exported / path.relative_to(truth.scenario_dir)))
        assert list(back) == ["x", "y", "z", field]
        for name in raw:
            np.testing.assert_array_equal(back[name].view(np.uint32), raw[name].view(np.uint32))
        if binary:
            assert (exported / path.relative_to(truth.scenario_dir)).read_bytes() == path.read_bytes()
        x = raw["x"].astype(np.float64)
        on_grid += int(np.sum(raw["x"] == (np.round(x * 10) / 10).astype(np.float32)))
    assert on_grid > 100  # the grid points are there, and came back
    agent_id, key = pcds[0].parent.name, pcds[0].stem
    raw = opencood_pcd(pcds[0]).astype(np.float32)
    got = OpenCoodScenario.open(out / "scenario.json").lidar_points(agent_id, key)
    np.testing.assert_array_equal(got.view(np.uint32), raw.view(np.uint32))  # the view too
