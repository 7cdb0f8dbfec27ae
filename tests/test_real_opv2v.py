"""The real OPV2V agent (``opv2v-agent-sample`` of ``tests/samples.toml``: scenario 2021_08_18_19_48_05
of OPV2V's validate split, agent 1045, ticks 68-74, with YAMLs, camera PNGs and data_protocol.yaml),
end to end: its YAML through the reader, the command ``opv2v-v4`` with validation, the view, and the
export back to OpenCOOD's layout.

The generator's YAMLs were written from OpenCDA's code and OpenCOOD's readers; these checks hold them
against what OpenCDA really wrote. The lidar model on these frames is in ``test_carla_lidar.py``, the
depth labels against OpenCOOD's projection in ``test_camera_labels_opencood.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import (
    OPV2V_SAMPLE_AGENT,
    OPV2V_SAMPLE_KEYS,
    OPV2V_SAMPLE_SCENARIO,
    find_opv2v_agent,
    find_opv2v_sample,
    open_sequence,
    run_cli,
)
from test_opencood_view import _same_tree_but_pcds, assert_same_points, assert_same_pose, opencood_pcd
from upath import UPath

from ncore_convert.sources import opencood as ocd
from ncore_convert.synth import carla as synth_carla
from ncore_convert.transforms.carla import carla_pose_matrix

KEYS = [f"{key:06d}" for key in OPV2V_SAMPLE_KEYS]
#: OpenCDA's CAV lidar mount (vehicle frame, CARLA axes: x forward, y right, z up), which the
#: generator uses too (``synth.opencood.CAV_LIDAR_M``)
LIDAR_MOUNT_M = np.array([-0.5, 0.0, 1.9])


def _in_vehicle_frame(pose: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
    """The position of CARLA pose ``pose`` ([x, y, z, roll, yaw, pitch]) in the vehicle frame of
    ``vehicle`` (same form), m [3]."""
    T_world_vehicle = np.linalg.inv(carla_pose_matrix(vehicle))
    return T_world_vehicle[:3, :3] @ pose[:3] + T_world_vehicle[:3, 3]


def test_the_real_yaml_through_the_reader():
    """Every tick's YAML read by ``sources.opencood`` as OpenCDA wrote it:

    - each camera's ``extrinsic`` (lidar -> camera) is ``cords``' pose inverted times
      ``lidar_pose``'s, to 1e-9: the pose convention the converter uses (``carla_pose_matrix``) is
      OpenCDA's, and the reader may take the cameras from ``cords``;
    - ``lidar_pose`` and ``true_ego_pos`` belong to the same tick: the lidar sits at OpenCDA's mount
      in the vehicle frame within 1 cm at every tick, while the car speeds up from 18 to 24 km/h (a
      pose one tick older would be 0.25-0.35 m off);
    - the intrinsics are CARLA's 100 deg pinhole on the 800 x 600 PNGs (the generator's);
    - the vehicles are the others (not the agent), each with a speed in km/h."""
    agent_dir = UPath(find_opv2v_agent())
    speeds = []
    for key in KEYS:
        frame = ocd.read_agent_frame(agent_dir, key)
        raw = ocd.load_yaml(agent_dir / f"{key}.yaml")
        np.testing.assert_array_equal(frame.lidar_pose, raw["lidar_pose"])
        assert sorted(frame.camera_cords) == [0, 1, 2, 3]
        T_lidar_world = carla_pose_matrix(frame.lidar_pose)
        for index, cords in frame.camera_cords.items():
            extrinsic = np.array(raw[f"camera{index}"]["extrinsic"])
            np.testing.assert_allclose(np.linalg.inv(carla_pose_matrix(cords)) @ T_lidar_world, extrinsic, atol=1e-9)
            K = frame.camera_intrinsic[index]
            width, height = ocd.png_size(ocd.read_png(agent_dir, key, index))
            assert (width, height) == (synth_carla.WIDTH, synth_carla.HEIGHT)
            generated = [[synth_carla.FOCAL_PX, 0, width / 2], [0, synth_carla.FOCAL_PX, height / 2], [0, 0, 1]]
            np.testing.assert_allclose(K, generated, rtol=1e-12)
        mount = _in_vehicle_frame(frame.lidar_pose, frame.true_ego_pos)
        assert np.abs(mount - LIDAR_MOUNT_M).max() < 0.01, mount
        assert len(frame.vehicles) >= 15 and int(OPV2V_SAMPLE_AGENT) not in frame.vehicles.actor_ids
        assert np.all(np.isfinite(frame.vehicles.speed_kmh)) and np.all(frame.vehicles.extent > 0)
        speeds.append(frame.ego_speed_kmh)
    assert 18.0 < speeds[0] < speeds[-1] < 25.0, speeds


def test_the_real_protocol_through_the_reader():
    """``data_protocol.yaml``: CARLA's tick and the CAV lidar block the model is built from."""
    protocol = ocd.read_protocol(UPath(find_opv2v_agent().parent))
    assert protocol.fixed_delta_seconds == 0.05 and protocol.rsu_lidars == ()
    lidar = protocol.cav_lidar
    assert (lidar["channels"], lidar["upper_fov"], lidar["lower_fov"]) == (64, 2, -25)
    assert (lidar["rotation_frequency"], lidar["points_per_second"]) == (20, 1300000)


@pytest.fixture(scope="module")
def converted(tmp_path_factory) -> Path:
    """The real scenario converted by the command with its defaults (validation included)."""
    out = tmp_path_factory.mktemp("real-opv2v") / "out"
    root = find_opv2v_sample()
    result = run_cli(
        "--no-progress", "--root-dir", str(root), "--output-dir", str(out), "opv2v-v4", "--split", "validate"
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"ok    {OPV2V_SAMPLE_SCENARIO}: 1 agents ({OPV2V_SAMPLE_AGENT}), 4 lidar frames" in result.stdout
    assert "16 images" in result.stdout and "validated:" in result.stdout, result.stdout
    return out / OPV2V_SAMPLE_SCENARIO


def test_the_real_agent_opens_with_the_library_defaults(converted):
    """The agent's sequence opens with ``SequenceLoaderV4``'s default instances: one lidar with the
    four ticks, four 800 x 600 cameras with a picture per tick, and as cuboids the YAMLs' vehicles
    and the agent's own box (which its YAML lacks)."""
    loader = open_sequence(converted / OPV2V_SAMPLE_AGENT, f"{OPV2V_SAMPLE_SCENARIO}_agent{OPV2V_SAMPLE_AGENT}")
    (lidar_id,) = loader.lidar_ids
    assert loader.get_lidar_sensor(lidar_id).frames_count == 4
    assert len(loader.camera_ids) == 4
    for cam in loader.camera_ids:
        camera = loader.get_camera_sensor(cam)
        assert camera.frames_count == 4
        assert tuple(camera.model_parameters.resolution) == (synth_carla.WIDTH, synth_carla.HEIGHT)
    tracks = {int(OPV2V_SAMPLE_AGENT)}
    for key in KEYS:
        tracks |= set(ocd.read_agent_frame(UPath(find_opv2v_agent()), key).vehicles.actor_ids.tolist())
    observations = list(loader.get_cuboid_track_observations())
    written = {str(o.track_id) for o in observations}
    assert OPV2V_SAMPLE_AGENT in written and written <= {str(t) for t in tracks} and len(observations) > 50


def test_the_view_reads_every_real_point_and_pose_back(converted):
    """The OpenCOOD view of the converted agent: every raw point in file order, bit for bit with its
    intensity byte, each tick's lidar pose, and the whole YAML as OpenCOOD loads it."""
    from ncore_convert.views.opencood import OpenCoodScenario

    view = OpenCoodScenario.open(converted / "scenario.json")
    assert view.agent_ids == [OPV2V_SAMPLE_AGENT] and view.keys(OPV2V_SAMPLE_AGENT) == KEYS
    for key in KEYS:
        raw_points = opencood_pcd(find_opv2v_agent() / f"{key}.pcd")
        assert len(raw_points) > 57_000
        assert_same_points(view.lidar_points(OPV2V_SAMPLE_AGENT, key), raw_points)
        raw_yaml = ocd.load_yaml(UPath(find_opv2v_agent() / f"{key}.yaml"))
        assert_same_pose(view.lidar_pose(OPV2V_SAMPLE_AGENT, key), raw_yaml["lidar_pose"])
        assert view.params(OPV2V_SAMPLE_AGENT, key) == raw_yaml


def test_the_export_gives_the_real_scenario_back(converted, tmp_path):
    """``export-opencood``: the same files as OpenCDA wrote them, the YAMLs, PNGs and
    data_protocol.yaml byte for byte, every point bit for bit in file order with its intensity."""
    result = run_cli("export-opencood", str(converted / "scenario.json"), "--out", str(tmp_path / "export"))
    assert result.returncode == 0, result.stderr
    exported = tmp_path / "export" / OPV2V_SAMPLE_SCENARIO
    raw = find_opv2v_agent().parent
    pcds = _same_tree_but_pcds(raw, exported)
    assert len(pcds) == 4
    for name in pcds:
        raw_points, back = opencood_pcd(raw / name), opencood_pcd(exported / name)
        assert_same_points(back.astype(np.float32), raw_points)
        np.testing.assert_array_equal(np.round(back[:, 3] * 255), np.round(raw_points[:, 3] * 255))
