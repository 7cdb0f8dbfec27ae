"""OPV2V / V2XSet conversion against synthetic scenarios with known truth (CARLA conventions are
stated independently in the generator: scipy Euler angles, UE4 camera projection)."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import run_cli
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from ncore.impl.common.transformations import is_within_3d_bboxes
from ncore.impl.sensors.camera import camera_model_from_parameters
from upath import UPath

from ncore_convert.converters.opencood import OpenCoodOptions, ScenarioSummary, convert_scenario
from ncore_convert.errors import SourceError
from ncore_convert.sources import opencood as src
from ncore_convert.synth.carla import PILLAR_DIMS_M, carla_pose_matrix, carla_rotation
from ncore_convert.synth.opencood import ScenarioTruth, SynthConfig, write_dataset

#: 80 ms between dumped frames: timestamps must come from the keys and data_protocol.yaml, not 100 ms
CONFIG = SynthConfig(
    dataset="v2xset", frames=4, seed=3, cavs=2, lidar_columns=360, fixed_delta_seconds=0.04, keep_truth=True
)
MIRROR = np.array([1.0, -1.0, 1.0])


@dataclass
class Converted:
    truth: ScenarioTruth
    summary: ScenarioSummary
    out: Path  #: the scenario's output folder

    def loader(self, agent_id: str | None = None) -> SequenceLoaderV4:
        name = f"{agent_id}/{self.truth.scenario}_agent{agent_id}.json" if agent_id else f"{self.truth.scenario}.json"
        return SequenceLoaderV4(SequenceComponentGroupsReader([UPath(self.out / name)]))


def _convert(tmp: Path, layout: str) -> Converted:
    (truth,) = write_dataset(UPath(tmp / "src"), CONFIG)
    out = tmp / "out" / truth.scenario
    options = OpenCoodOptions(dataset="v2xset", split=CONFIG.split, layout=layout)
    summary = convert_scenario(UPath(tmp / "src"), UPath(out), truth.scenario, options)
    return Converted(truth, summary, out)


@pytest.fixture(scope="module")
def agents(tmp_path_factory) -> Converted:
    return _convert(tmp_path_factory.mktemp("opencood"), "agents")


@pytest.fixture(scope="module")
def scenario(tmp_path_factory) -> Converted:
    return _convert(tmp_path_factory.mktemp("opencood-scenario"), "scenario")


def world_global_points(loader: SequenceLoaderV4, lidar_id: str, frame: int) -> np.ndarray:
    """A lidar frame's points (sensor frame at the tick) in world_global, through the pose graph."""
    lidar = loader.get_lidar_sensor(lidar_id)
    xyz = lidar.get_frame_point_cloud(frame, motion_compensation=False, with_start_points=False).xyz_m_end
    T = lidar.get_frames_T_sensor_target("world_global", frame)
    return xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]


def box_surface_distance(xyz: np.ndarray, center: np.ndarray, dims: np.ndarray) -> np.ndarray:
    """Unsigned distance of points [N,3] from the surface of an axis-aligned box."""
    q = np.abs(xyz - center) - np.asarray(dims) / 2
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return np.abs(np.where(np.all(q <= 0, axis=1), q.max(axis=1), outside))


def test_every_agent_is_a_sequence_with_every_point_and_its_intensity(agents):
    assert sorted(agents.summary.agents, key=int) == sorted(agents.truth.agents, key=int)
    for agent_id, truth in agents.truth.agents.items():
        loader = agents.loader(agent_id)
        assert loader.lidar_ids == [src.LIDAR]
        assert sorted(loader.camera_ids) == sorted(src.CAMERAS)
        lidar = loader.get_lidar_sensor(src.LIDAR)
        assert lidar.frames_count == len(agents.truth.keys)
        for i, key in enumerate(agents.truth.keys):
            assert lidar.get_frame_ray_bundle_count(i) == truth.n_points[key]
            intensity = lidar.get_frame_ray_bundle_return_intensity(i)
            np.testing.assert_array_equal(intensity, truth.intensity_u8[key] / np.float32(255.0))
            direction = lidar.get_frame_ray_bundle_direction(i)
            np.testing.assert_allclose(np.linalg.norm(direction, axis=1), 1.0, atol=1e-6)


def test_timestamps_follow_the_carla_frame_keys(agents):
    dt = agents.truth.fixed_delta_seconds
    expected = np.array([round(int(k) * dt * 1e6) for k in agents.truth.keys], dtype=np.uint64)
    assert np.all(np.diff(expected) == 80_000)  # keys step by 2, 0.04 s per tick
    for agent_id in agents.truth.agents:
        loader = agents.loader(agent_id)
        for sensor in [loader.get_lidar_sensor(src.LIDAR)] + [loader.get_camera_sensor(c) for c in src.CAMERAS]:
            np.testing.assert_array_equal(sensor.get_frames_timestamps_us(), expected)
            np.testing.assert_array_equal(sensor.frames_timestamps_us[:, 0], expected)  # no skew: start = end


def test_a_carla_point_lands_at_x_minus_y_z_in_world_global(agents):
    """docs/opv2v-v2xset.md: world_global (x, y, z) = CARLA (x, -y, z); checked on the raw PCD text for every agent."""
    key = agents.truth.keys[1]
    for agent_id, truth in agents.truth.agents.items():
        raw = np.loadtxt(agents.truth.scenario_dir / agent_id / f"{key}.pcd", skiprows=11, dtype=np.float32)
        T_world_lidar = carla_pose_matrix(np.array(truth.lidar_pose[key]))
        carla_world = raw[:, :3].astype(np.float64) @ T_world_lidar[:3, :3].T + T_world_lidar[:3, 3]
        converted = world_global_points(agents.loader(agent_id), src.LIDAR, 1)
        np.testing.assert_allclose(converted, carla_world * MIRROR, atol=2e-3)


def test_agents_coregister_on_the_same_pillars(agents):
    """Points that hit a pillar lie on that pillar's surface in world_global (<= 2 cm) from every
    agent, and some pillar is seen by two agents."""
    pillars = agents.truth.pillars_m * MIRROR
    seen_by: dict[int, set] = {}
    for agent_id, truth in agents.truth.agents.items():
        loader = agents.loader(agent_id)
        for i, key in enumerate(agents.truth.keys):
            xyz = world_global_points(loader, src.LIDAR, i)[truth.hit_actor[key] == -2]
            nearest = np.argmin(np.linalg.norm(xyz[:, None, :2] - pillars[None, :, :2], axis=2), axis=1)
            distance = box_surface_distance(xyz, pillars[nearest], PILLAR_DIMS_M)
            assert len(xyz) > 50 and distance.max() <= 0.02, (agent_id, key, distance.max())
            for p in np.unique(nearest):
                seen_by.setdefault(int(p), set()).add(agent_id)
    assert max(len(s) for s in seen_by.values()) >= 2


def test_pillars_project_onto_their_marker_pixels(agents):
    """Each pillar centre projects (pose graph + stored camera model) onto the pixel the generator
    computed in CARLA's own camera convention (<= 1 px), and the stored image has its marker there."""
    pillars = agents.truth.pillars_m * MIRROR
    checked = 0
    for agent_id, truth in agents.truth.agents.items():
        loader = agents.loader(agent_id)
        for index, camera_id in enumerate(src.CAMERAS):
            camera = loader.get_camera_sensor(camera_id)
            model = camera_model_from_parameters(camera.model_parameters, device="cpu", dtype=torch.float64)
            for i, key in enumerate(agents.truth.keys[:2]):
                markers = truth.markers[key][index]
                if not markers:
                    continue
                T_cam_wg = camera.get_frames_T_sensor_target("world_global", i)
                ids = sorted(markers)
                xyz_cam = (pillars[ids] - T_cam_wg[:3, 3]) @ T_cam_wg[:3, :3]
                uv = model.camera_rays_to_image_points(xyz_cam).image_points.numpy()
                expected = np.array([markers[p] for p in ids])
                assert np.abs(uv - expected).max() <= 1.0, (agent_id, camera_id, key)
                image = np.asarray(camera.get_frame_handle(i).get_data().get_decoded_image())
                for u, v in uv:
                    assert tuple(image[int(v), int(u)]) == (255, 0, 0)
                checked += len(ids)
    assert checked > 20


def test_images_are_byte_identical(agents):
    for agent_id in agents.truth.agents:
        loader = agents.loader(agent_id)
        for index, camera_id in enumerate(src.CAMERAS):
            camera = loader.get_camera_sensor(camera_id)
            for i, key in enumerate(agents.truth.keys):
                data = camera.get_frame_handle(i).get_data()
                assert data.get_encoded_image_format() == "png"
                path = agents.truth.scenario_dir / agent_id / f"{key}_camera{index}.png"
                assert data.get_encoded_image_data() == path.read_bytes()


def test_cuboids_contain_their_points_and_match_the_carla_labels(agents):
    inside_checked = 0
    for agent_id, truth in agents.truth.agents.items():
        loader = agents.loader(agent_id)
        lidar = loader.get_lidar_sensor(src.LIDAR)
        T_lidar_rig = lidar.T_sensor_rig
        observations = list(loader.get_cuboid_track_observations())
        assert {o.source.name for o in observations} == {"GT_SYNTHETIC"}
        assert {o.class_id for o in observations} == {"car"}  # --class-names ncore: CARLA's vehicles are cars
        for i, key in enumerate(agents.truth.keys):
            t_us = int(lidar.get_frames_timestamps_us()[i])
            boxes = {o.track_id: o for o in observations if o.timestamp_us == t_us}
            assert all(o.reference_frame_id == "rig" for o in boxes.values())
            xyz = lidar.get_frame_point_cloud(i, motion_compensation=False, with_start_points=False).xyz_m_end
            xyz_rig = xyz @ T_lidar_rig[:3, :3].T + T_lidar_rig[:3, 3]
            hit = truth.hit_actor[key]
            for actor in np.unique(hit[hit >= 0]):
                box = boxes[str(actor)].bbox3
                grown = np.array([[*box.centroid, *(np.array(box.dim) + 0.04), *box.rot]])
                assert is_within_3d_bboxes(xyz_rig[hit == actor], grown).all(), (agent_id, key, actor)
                inside_checked += 1
            if int(agent_id) > 0:  # a CAV's own box, missing from its YAML, is in its sequence
                own = boxes[agent_id].bbox3
                np.testing.assert_allclose(own.centroid, np.array(src.CAV_BOX_CENTER_M) * MIRROR, atol=1e-4)
                np.testing.assert_allclose(own.dim, 2 * np.array(src.CAV_BOX_EXTENT_M), atol=1e-6)
    assert inside_checked > 10


def test_a_label_becomes_the_documented_world_box(agents):
    """World centre = mirror(location + R(angle) · center), size = 2 · extent, from the raw YAML."""
    key = agents.truth.keys[0]
    agent_id = next(a for a in agents.truth.agents if int(a) > 0)
    label_id, label = next(
        iter(src.load_yaml(agents.truth.scenario_dir / agent_id / f"{key}.yaml")["vehicles"].items())
    )
    center = np.array(label["location"]) + carla_rotation(np.array(label["angle"])) @ np.array(label["center"])
    loader = agents.loader(agent_id)
    (obs,) = [
        o
        for o in loader.get_cuboid_track_observations()
        if o.track_id == str(label_id) and o.timestamp_us == round(int(key) * CONFIG.fixed_delta_seconds * 1e6)
    ]
    T_rig_wg = loader.pose_graph.evaluate_poses("rig", "world_global", np.array(obs.timestamp_us, dtype=np.uint64))
    np.testing.assert_allclose(T_rig_wg[:3, :3] @ obs.bbox3.centroid + T_rig_wg[:3, 3], center * MIRROR, atol=2e-3)
    np.testing.assert_allclose(obs.bbox3.dim, 2 * np.array(label["extent"]), atol=1e-9)


def test_manifest_links_the_agents(agents):
    manifest = json.loads((agents.out / "scenario.json").read_text())
    folders = sorted(agents.truth.agents)
    assert manifest["ego"]["agent_id"] == int(src.opencood_ego(folders))
    by_id = {str(a["agent_id"]): a for a in manifest["agents"]}
    assert set(by_id) == set(folders)
    for agent_id, entry in by_id.items():
        assert entry["kind"] == ("infrastructure" if int(agent_id) < 0 else "cav")
        assert (agents.out / entry["sequence"]).is_file()
    assert manifest["fixed_delta_seconds"] == CONFIG.fixed_delta_seconds


def test_scenario_layout_holds_every_agent_and_matches_the_agent_sequences(agents, scenario):
    loader = scenario.loader()
    ego = src.opencood_ego(sorted(scenario.truth.agents))
    for agent_id in scenario.truth.agents:
        assert f"agent{agent_id}_{src.LIDAR}" in loader.lidar_ids
        assert all(f"agent{agent_id}_{c}" in loader.camera_ids for c in src.CAMERAS)
        both = world_global_points(loader, f"agent{agent_id}_{src.LIDAR}", 2)
        single = world_global_points(agents.loader(agent_id), src.LIDAR, 2)
        np.testing.assert_allclose(both, single, atol=2e-3)
    observations = list(loader.get_cuboid_track_observations())
    assert observations and {o.reference_frame_id for o in observations} == {f"agent{ego}_rig"}
    # world is the OpenCOOD ego's first pose
    first = loader.pose_graph.evaluate_poses(
        f"agent{ego}_rig",
        "world",
        np.array(loader.get_lidar_sensor(f"agent{ego}_{src.LIDAR}").get_frames_timestamps_us()[0], dtype=np.uint64),
    )
    np.testing.assert_allclose(first, np.eye(4), atol=1e-6)


def test_opencood_ego_rule():
    assert src.opencood_ego(["650", "1732", "-1"]) == "1732"  # string sort, not numeric
    assert src.opencood_ego(["-1", "-2", "100"]) == "-2"  # OpenCOOD's rule with two RSUs


def test_yaml_is_loaded_safely_with_opencood_floats(tmp_path):
    path = tmp_path / "000001.yaml"
    path.write_text("a: 1e-06\nb: [1, 2.5e+3]\n")
    assert src.load_yaml(UPath(path)) == {"a": 1e-06, "b": [1, 2500.0]}
    path.write_text("a: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(SourceError, match="000001.yaml: not valid YAML"):
        src.load_yaml(UPath(path))


def test_damaged_frames_are_skipped_and_reported_by_the_cli(tmp_path):
    """A frame missing for one agent, a missing and a corrupt camera file: the scenario converts,
    the rest is kept, and each skip is a warning naming the file in the run report."""
    out = tmp_path / "out"
    synth = ["synth", "opv2v", "--out", str(tmp_path / "src"), "--frames", "4", "--cavs", "3"]
    assert run_cli(*synth, "--lidar-columns", "64", "--seed", "5", "--render-step", "8").returncode == 0
    (scenario_dir,) = (tmp_path / "src" / "test").iterdir()
    a, b, c = sorted((p.name for p in scenario_dir.iterdir() if p.is_dir()), key=int)
    keys = sorted(p.stem for p in (scenario_dir / a).glob("*.yaml"))
    (scenario_dir / a / f"{keys[1]}.yaml").unlink()
    (scenario_dir / b / f"{keys[2]}_camera1.png").unlink()
    (scenario_dir / c / f"{keys[0]}_camera3.png").write_bytes(b"not a png")
    convert = ["--no-progress", "--root-dir", str(tmp_path / "src"), "--output-dir", str(out), "opv2v-v4"]
    run = run_cli(*convert, "--split", "test")
    assert run.returncode == 0, run.stdout + run.stderr
    entry = json.loads((out / "conversion-report.json").read_text())["logs"][scenario_dir.name]
    assert entry["status"] == "ok"
    assert entry["validation"]["ok"] is True  # every skipped file is declared in the sensors' skipped_frames
    text = "\n".join(entry["warnings"])
    assert f"{scenario_dir / a}: no frame for key(s) {keys[1]}" in text
    assert f"{scenario_dir / b / (keys[2] + '_camera1.png')}: file not found; image skipped" in text
    assert f"{scenario_dir / c / (keys[0] + '_camera3.png')}: not a PNG file (missing signature); image skipped" in text
    sequence = out / scenario_dir.name / a / f"{scenario_dir.name}_agent{a}.json"
    loader = SequenceLoaderV4(SequenceComponentGroupsReader([UPath(sequence)]))
    assert loader.get_lidar_sensor(src.LIDAR).frames_count == len(keys) - 1
    manifest = json.loads((out / scenario_dir.name / "scenario.json").read_text())
    assert manifest["dataset"] == "opv2v" and len(manifest["agents"]) == 3
    # an unknown scenario is a usage error
    bad = run_cli(*convert, "--split", "test", "--scenario", "nope")
    assert bad.returncode == 2 and "scenario(s) not found" in bad.stderr
    shutil.rmtree(out)


def test_sensor_selection(agents, tmp_path):
    root = agents.truth.scenario_dir.parent.parent
    options = OpenCoodOptions(dataset="v2xset", split=CONFIG.split, camera_ids=("camera_back",), lidar_ids=())
    summary = convert_scenario(UPath(root), UPath(tmp_path / "sel"), agents.truth.scenario, options)
    assert summary.frames == 0 and summary.images == len(agents.truth.keys) * len(agents.truth.agents)
    for agent_id in agents.truth.agents:
        sequence = tmp_path / "sel" / agent_id / f"{agents.truth.scenario}_agent{agent_id}.json"
        loader = SequenceLoaderV4(SequenceComponentGroupsReader([UPath(sequence)]))
        assert loader.lidar_ids == [] and loader.camera_ids == ["camera_back"]
