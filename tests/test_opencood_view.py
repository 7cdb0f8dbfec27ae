"""Issue 29, first part: a converted cooperative scenario read back as OpenCOOD reads its raw files
(``views.opencood``), against the raw files themselves: the lidar points as OpenCOOD's PCD reader
returns them, and each frame's ``lidar_pose``, on synthetic V2XSet (CAVs and infrastructure, both
layouts) and on the five real OPV2V frames."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import find_opv2v_sample
from upath import UPath

from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.sources.opencood import load_yaml
from ncore_convert.sources.pcd import read_pcd
from ncore_convert.synth import opencood as synth
from ncore_convert.transforms.carla import carla_pose_matrix
from ncore_convert.views.opencood import OpenCoodScenario


def opencood_pcd(path: Path) -> np.ndarray:
    """OpenCOOD's ``pcd_to_np`` restated: Open3D's points, and as intensity the red channel of the
    packed ``rgb`` float (its bits as uint32, byte 2) over 255; [N,4]."""
    columns = read_pcd(UPath(path))
    red = (np.asarray(columns["rgb"], dtype=np.float32).view(np.uint32) >> 16) & 0xFF
    return np.stack([columns["x"], columns["y"], columns["z"], red / 255.0], axis=1)


def assert_same_points(got: np.ndarray, raw: np.ndarray) -> None:
    """Equal to float32 precision, in the file's order (every raw point has a range here)."""
    assert got.dtype == np.float32 and got.shape == raw.shape
    error_m = np.abs(got[:, :3] - raw[:, :3]).max(axis=1)
    assert np.all(error_m <= 4 * np.finfo(np.float32).eps * np.linalg.norm(raw[:, :3], axis=1)), error_m.max()
    np.testing.assert_allclose(got[:, 3], raw[:, 3], rtol=1e-6, atol=0)


def assert_same_pose(got: np.ndarray, yaml_pose: list[float]) -> None:
    """The YAML's pose: positions within 1e-6 relative, the angles the same rotation to 1e-6 (NCore
    stores the dynamic poses in float32: ~1e-7 m and 1e-7 rad were seen in the scenario layout)."""
    np.testing.assert_allclose(got[:3], yaml_pose[:3], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(carla_pose_matrix(got)[:3, :3], carla_pose_matrix(np.array(yaml_pose))[:3, :3],
                               atol=1e-6)  # fmt: skip


@pytest.fixture(scope="module")
def v2xset(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("view-v2xset")
    (truth,) = synth.write_dataset(UPath(tmp / "src"), synth.SynthConfig(dataset="v2xset", frames=3, seed=5))
    outs = {}
    for layout in ("agents", "scenario"):
        out = tmp / layout / truth.scenario
        convert_scenario(UPath(tmp / "src"), UPath(out), truth.scenario, OpenCoodOptions("v2xset", "test", layout))
        outs[layout] = out / "scenario.json"
    return truth, outs


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
            assert_same_pose(view.lidar_pose(agent_id, key), load_yaml(UPath(agent_dir / f"{key}.yaml"))["lidar_pose"])


def test_unknown_agents_keys_and_settings_are_named(v2xset):
    truth, manifests = v2xset
    view = OpenCoodScenario.open(manifests["agents"])
    with pytest.raises(KeyError, match="no written agent '999'"):
        view.lidar_points("999", truth.keys[0])
    with pytest.raises(KeyError, match="has no lidar frame '000001'"):
        view.lidar_points(view.ego_agent_id, "000001")
    with pytest.raises(ValueError, match="no noise setting 'gps' \\(stored: none\\)"):
        OpenCoodScenario.open(manifests["agents"], poses="gps")


def test_the_real_opv2v_frames_read_back_as_the_pcd_reader_reads_them(tmp_path):
    """The five real frames put in a synthetic agent's place (their keys 000070-000078): every point
    back in file order, to float32 precision."""
    config = synth.SynthConfig(dataset="opv2v", frames=5, seed=7, cavs=1, first_key=70, key_step=2)
    (truth,) = synth.write_dataset(UPath(tmp_path / "src"), config)
    (agent_id,) = truth.agents
    real = sorted(find_opv2v_sample().glob("*.pcd"))
    assert [p.stem for p in real] == truth.keys
    for path in real:
        shutil.copyfile(path, Path(truth.scenario_dir) / agent_id / path.name)
    out = tmp_path / "out" / truth.scenario
    convert_scenario(UPath(tmp_path / "src"), UPath(out), truth.scenario, OpenCoodOptions("opv2v", "test"))
    view = OpenCoodScenario.open(out / "scenario.json")
    for path in real:
        raw = opencood_pcd(path)
        assert len(raw) > 50_000 and np.all(np.linalg.norm(raw[:, :3], axis=1) > 0)
        assert_same_points(view.lidar_points(agent_id, path.stem), raw)
