"""GPS error and communication delay (issue 7): the models against known truth, and the converted
data against a re-statement of OpenCOOD's formulas written here."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ncore.data.v4 import PosesComponent, SequenceComponentGroupsReader, SequenceLoaderV4
from scipy.spatial.transform import Rotation
from upath import UPath

from ncore_convert.cli import noise_settings
from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.errors import SourceError
from ncore_convert.sources import opencood as src
from ncore_convert.sources.noise_config import check_unique, make_setting, read_noise_config
from ncore_convert.synth.carla import carla_pose_matrix
from ncore_convert.synth.opencood import ScenarioTruth, SynthConfig, write_dataset
from ncore_convert.transforms import noise
from ncore_convert.transforms.noise import NoiseSetting

MIRROR = np.diag([1.0, -1.0, 1.0, 1.0])
#: OpenCOOD's documented example block (data-preparation page), as a user would paste it.
DOC_BLOCK = """
wild_setting:
  async: true
  async_mode: 'sim'
  async_overhead: 100
  backbone_delay: 10
  data_size: 1.06
  loc_err: true
  ryp_std: 0.2
  seed: 25
  transmission_speed: 27
  xyz_std: 0.2
"""


# --- OpenCOOD, re-stated from its code (DerrickXuNu/OpenCOOD, opencood/data_utils/datasets/basedataset.py:
# time_delay_calculation, retrieve_base_data, reform_param and add_loc_noise) ----------------------


class OpenCoodRestatement:
    """What OpenCOOD's loader does with a ``wild_setting`` block, frame by frame, on numpy's global
    generator: delay in whole 100 ms frames, a localisation offset re-seeded on every call."""

    def __init__(self, wild: dict, max_cav: int = 7):
        self.wild = {"async_mode": "sim", "data_size": 0, "transmission_speed": 27, "backbone_delay": 0, **wild}
        self.max_cav = max_cav

    def delay_frames(self, is_ego: bool) -> tuple[float, int]:
        if is_ego:
            return 0.0, 0
        w = self.wild
        if w["async_mode"] == "real":
            jitter_ms = np.random.uniform(0, w["async_overhead"])
            transfer_ms = w["data_size"] / w["transmission_speed"] * 1000
            delay_ms = int(jitter_ms + transfer_ms + w["backbone_delay"])
        else:
            delay_ms = np.abs(w["async_overhead"])
        return (delay_ms, delay_ms // 100) if w["async"] else (0.0, 0)

    def with_loc_error(self, pose: list[float]) -> list[float]:
        np.random.seed(self.wild["seed"])
        d_xyz = np.random.normal(0, self.wild["xyz_std"], 3)
        d_ryp = np.random.normal(0, self.wild["ryp_std"], 3)
        return [pose[0] + d_xyz[0], pose[1] + d_xyz[1], pose[2] + d_xyz[2], pose[3], pose[4] + d_ryp[1], pose[5]]

    def run(self, folders: list[str], lidar_poses: dict[str, list[list[float]]], n_frames: int) -> list[dict]:
        """Per ego frame: agent -> (delay_ms, frames behind, delayed index, noisy delayed lidar pose)."""
        order = sorted(folders)
        if int(order[0]) < 0:
            order = order[1:] + [order[0]]
        order = order[: self.max_cav]
        np.random.seed(self.wild["seed"])  # the converter's stated generator state on entering a scenario
        frames = []
        for i in range(n_frames):
            per_agent = {}
            for rank, agent in enumerate(order):
                delay_ms, d = self.delay_frames(rank == 0)
                if i - d <= 0:
                    d = i
                j = max(0, i - d)
                delayed, current = lidar_poses[agent][j], lidar_poses[agent][i]
                if rank != 0 and self.wild["loc_err"]:
                    delayed = self.with_loc_error(delayed)
                    current = self.with_loc_error(current)
                per_agent[agent] = (delay_ms, d, j, delayed)
            frames.append(per_agent)
        return frames


def opencood_setting(wild: dict, max_cav: int = 7) -> NoiseSetting:
    return make_setting({"name": "oc", **wild, "max_cav": max_cav})


OPENCOOD_CASES = [
    dict(seed=25, **{"async": True}, async_overhead=100, loc_err=True, xyz_std=0.2, ryp_std=0.2),
    dict(seed=0, **{"async": True}, async_overhead=250, loc_err=True, xyz_std=1.0, ryp_std=1.0),
    dict(seed=7, **{"async": True}, async_overhead=60, loc_err=False, xyz_std=0.5, ryp_std=0.5),
    dict(
        seed=25,
        **{"async": True},
        async_mode="real",
        async_overhead=100,
        backbone_delay=10,
        data_size=1.06,
        transmission_speed=27,
        loc_err=True,
        xyz_std=0.2,
        ryp_std=0.2,
    ),
    dict(seed=1234, **{"async": True}, async_mode="real", async_overhead=300, loc_err=False, xyz_std=0, ryp_std=0),
    dict(seed=99, **{"async": False}, async_mode="real", async_overhead=300, loc_err=False, xyz_std=0.1, ryp_std=0),
    dict(
        seed=5,
        **{"async": True},
        async_mode="real",
        async_overhead=200,
        data_size=2.0,
        transmission_speed=10,
        loc_err=True,
        xyz_std=0.3,
        ryp_std=0.1,
    ),
]


@pytest.mark.parametrize("wild", OPENCOOD_CASES)
@pytest.mark.parametrize("max_cav", [7, 2])
def test_opencood_model_matches_the_restatement_draw_for_draw(wild, max_cav):
    folders = ["650", "1732", "-1", "41", "2004"]
    rng = np.random.default_rng(0)
    poses = {a: rng.normal(0, 50, (30, 6)).tolist() for a in folders}
    expected = OpenCoodRestatement(wild, max_cav).run(folders, poses, 30)
    setting = opencood_setting(wild, max_cav)
    order = src.opencood_order(folders)
    assert order[:2] == ["1732", "2004"] and order[-1] == "-1"
    loaded = order[:max_cav]
    delays = noise.opencood_delays(setting, 30, loaded, order[0])
    offset = noise.opencood_loc_offset(setting)
    for i, frame in enumerate(expected):
        assert sorted(frame) == sorted(loaded)
        for agent, (delay_ms, d, j, noisy_delayed) in frame.items():
            assert delays[agent][0][i] == delay_ms
            assert delays[agent][1][i] == d and i - d == j
            applied = np.asarray(poses[agent][j]) + (offset if agent != order[0] else 0.0)
            np.testing.assert_array_equal(applied, noisy_delayed)
    if wild["async"] and wild.get("async_mode") == "real":
        # real mode draws a delay per agent and frame: OpenCOOD's 0..overhead/100 frames, not a constant
        assert len({delays[a][0][i] for a in loaded[1:] for i in range(30)}) > 1


def test_opencood_real_mode_doc_defaults_give_0_or_1_frame_about_half_the_time():
    """Worked from OpenCOOD's delay formula (no public source states the number): U(0,100) ms + 1.06/27 s
    + 10 ms -> 1 frame with P = 0.4926."""
    wild = dict(OPENCOOD_CASES[3], loc_err=False)
    agents = [str(a) for a in range(1, 8)]
    delays = noise.opencood_delays(opencood_setting(wild), 4000, agents, agents[0])
    frames = np.concatenate([delays[a][1][1:] for a in agents[1:]])
    assert set(frames.tolist()) == {0, 1}
    assert abs(frames.mean() - (1 - 50.74 / 100)) < 4 * np.sqrt(0.25 / len(frames))


def test_opencood_offset_is_one_constant_per_seed_on_x_y_z_and_yaw_only():
    a = noise.opencood_loc_offset(opencood_setting(OPENCOOD_CASES[0]))
    b = noise.opencood_loc_offset(opencood_setting(dict(OPENCOOD_CASES[0], seed=26)))
    assert np.all(a[[0, 1, 2, 4]] != 0) and a[3] == 0 and a[5] == 0
    assert not np.allclose(a, b)
    assert np.all(noise.opencood_loc_offset(opencood_setting(OPENCOOD_CASES[2] | {"loc_err": False})) == 0)


# --- realistic model statistics ----------------------------------------------------------------


def lag1(x: np.ndarray) -> float:
    x = x - x.mean()
    return float(np.sum(x[1:] * x[:-1]) / np.sum(x * x))


def realistic(**values) -> NoiseSetting:
    base = {
        "name": "r",
        "model": "realistic",
        "seed": 3,
        "async": True,
        "async_overhead": 0,
        "loc_err": True,
        "xyz_std": 0.0,
        "ryp_std": 0.0,
    }
    return make_setting(base | values)


@pytest.mark.parametrize("tau_s", [0.5, 3.0])
def test_gauss_markov_has_the_configured_std_and_lag1_autocorrelation(tau_s):
    n, dt_us = 60_000, 100_000
    t_us = np.arange(n, dtype=np.int64) * dt_us
    setting = realistic(xyz_std=0.5, ryp_std=2.0, process="gauss_markov", correlation_time_s=tau_s)
    pose_rng, _ = noise.agent_rngs(setting, "scn", "17")
    e = noise.realistic_pose_noise(setting, pose_rng, t_us)
    phi = np.exp(-0.1 / tau_s)
    n_eff = n * (1 - phi) / (1 + phi)
    for k, std in enumerate([0.5] * 3 + [2.0] * 3):
        assert abs(e[:, k].mean()) < 5 * std / np.sqrt(n_eff)
        assert abs(e[:, k].std() / std - 1) < 5 / np.sqrt(2 * n_eff)
        assert abs(lag1(e[:, k]) - phi) < 5 * np.sqrt((1 - phi**2) / n)


def test_white_process_is_uncorrelated_in_time_and_between_agents():
    n = 50_000
    t_us = np.arange(n, dtype=np.int64) * 100_000
    setting = realistic(xyz_std=0.3, ryp_std=0.1)
    streams = [noise.realistic_pose_noise(setting, noise.agent_rngs(setting, "scn", a)[0], t_us) for a in ("1", "2")]
    bound = 5 / np.sqrt(n)
    for e in streams:
        assert abs(e[:, 0].std() - 0.3) < 0.3 * 5 / np.sqrt(2 * n)
        assert abs(lag1(e[:, 0])) < bound and abs(lag1(e[:, 5])) < bound
    assert abs(np.corrcoef(streams[0][:, 0], streams[1][:, 0])[0, 1]) < bound
    # the agents' delay streams are independent too
    d = [
        noise.realistic_delays_ms(
            realistic(async_mode="real", async_overhead=100), noise.agent_rngs(setting, "scn", a)[1], n
        )
        for a in ("1", "2")
    ]
    assert abs(np.corrcoef(d[0], d[1])[0, 1]) < bound


def test_gauss_markov_streams_of_two_agents_are_independent():
    n = 40_000
    t_us = np.arange(n, dtype=np.int64) * 100_000
    setting = realistic(xyz_std=1.0, process="gauss_markov", correlation_time_s=1.0)
    a, b = (noise.realistic_pose_noise(setting, noise.agent_rngs(setting, "scn", x)[0], t_us)[:, 0] for x in "ab")
    phi = np.exp(-0.1)
    n_eff = n * (1 - phi) / (1 + phi)
    assert abs(np.corrcoef(a, b)[0, 1]) < 5 / np.sqrt(n_eff)


def test_bias_is_constant_per_agent_with_the_configured_spread_and_xy_yaw_leaves_z_roll_pitch():
    t_us = np.arange(20, dtype=np.int64) * 100_000
    setting = realistic(bias_xyz_std=0.8, bias_ryp_std=0.4, dof="xy_yaw")
    biases = []
    for agent in range(3000):
        e = noise.realistic_pose_noise(setting, noise.agent_rngs(setting, "scn", str(agent))[0], t_us)
        assert np.all(e == e[0])
        assert np.all(e[:, [2, 3, 4]] == 0)
        biases.append(e[0])
    biases = np.array(biases)
    for k, std in [(0, 0.8), (1, 0.8), (5, 0.4)]:
        assert abs(biases[:, k].mean()) < 5 * std / np.sqrt(3000)
        assert abs(biases[:, k].std() / std - 1) < 5 / np.sqrt(2 * 3000)


def test_realistic_delay_is_unquantised_with_the_configured_distribution():
    n = 100_000
    setting = realistic(async_mode="real", async_overhead=120, data_size=1.06, transmission_speed=27, backbone_delay=10)
    d = noise.realistic_delays_ms(setting, np.random.default_rng(1), n)
    mean = 60 + 1.06 / 27 * 1000 + 10
    assert abs(d.mean() - mean) < 5 * 120 / np.sqrt(12 * n)
    assert abs(d.std() - 120 / np.sqrt(12)) < 0.02 * 120 / np.sqrt(12)
    assert np.mean(d != np.round(d)) > 0.99  # milliseconds, not whole frames or integers
    np.testing.assert_array_equal(noise.realistic_delays_ms(realistic(async_overhead=130), None, 5), np.full(5, 130.0))
    np.testing.assert_array_equal(noise.realistic_delays_ms(realistic(**{"async": False}), None, 3), np.zeros(3))


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.integers(0, 10**7), min_size=1, max_size=30, unique=True),
    st.lists(st.tuples(st.integers(0, 10**7), st.floats(0, 5000, allow_nan=False)), min_size=1, max_size=30),
)
def test_latest_source_is_the_newest_frame_old_enough(agent_t, ego):
    agent_t = np.sort(np.array(agent_t, dtype=np.int64))
    ego_t = np.array([e[0] for e in ego], dtype=np.int64)
    delay_ms = np.array([e[1] for e in ego])
    index = noise.latest_source(agent_t, ego_t, delay_ms)
    for k in range(len(ego_t)):
        old_enough = np.flatnonzero(agent_t <= ego_t[k] - delay_ms[k] * 1000.0)
        if len(old_enough):
            assert index[k] == old_enough[-1]
        elif agent_t[0] <= ego_t[k]:
            assert index[k] == 0  # the start of the scenario: OpenCOOD's clamp
        else:
            assert index[k] == noise.NO_SOURCE


def test_perturbation_moves_and_turns_about_the_world_axes():
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, :3, :3] = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    T[:, :3, 3] = [[1, 2, 3], [4, 5, 6]]
    e = np.array([[0.1, -0.2, 0.3, 0, 0, 90.0], [0, 0, 0, 1.0, 2.0, 3.0]])
    out = noise.perturb_poses(T, e)
    np.testing.assert_allclose(out[:, :3, 3], T[:, :3, 3] + e[:, :3])
    np.testing.assert_allclose(out[0, :3, 0], [0, 1, 0], atol=1e-12)  # x axis yawed +90 deg about world z
    turn = out[1, :3, :3] @ T[1, :3, :3].T
    np.testing.assert_allclose(Rotation.from_matrix(turn).as_euler("xyz", degrees=True), [1, 2, 3], atol=1e-9)


# --- settings: files and flags -----------------------------------------------------------------


def test_the_documented_wild_setting_block_is_read_with_opencood_names(tmp_path):
    path = tmp_path / "v2xvit_test.yaml"
    path.write_text("train_params:\n  max_cav: 5\n" + DOC_BLOCK)
    s = read_noise_config(UPath(path))
    assert (s.name, s.model, s.seed, s.async_, s.async_mode, s.max_cav) == (
        "v2xvit_test",
        "opencood",
        25,
        True,
        "sim",
        5,
    )
    assert (s.async_overhead, s.backbone_delay, s.data_size, s.transmission_speed) == (100, 10, 1.06, 27)
    assert (s.loc_err, s.xyz_std, s.ryp_std) == (True, 0.2, 0.2)
    assert s.as_dict()["async"] is True and "process" not in s.as_dict()


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("  seed: 25\n", ""), "wild_setting lacks seed"),
        (lambda t: t.replace("ryp_std", "rpy_std"), "the key is ryp_std"),
        (lambda t: t.replace("async_mode: 'sim'", "async_mode: 'fast'"), "async_mode must be one of sim, real"),
        (lambda t: t.replace("xyz_std: 0.2", "xyz_std: -1"), "xyz_std must be a finite number >= 0"),
        (lambda t: t + "  dof: xy_yaw\n", "only apply to the realistic model"),
        (lambda t: t + "  sead: 3\n", "unknown key(s) sead"),
        (lambda t: t + "  name: default\n", "not be 'default'"),
        (lambda t: t.replace("wild_setting:", "wild_settings:"), "no wild_setting mapping"),
        (lambda t: t + "  seed: !!python/object/apply:os.system ['true']\n", "not valid YAML"),
    ],
)
def test_a_bad_noise_config_is_one_line_naming_the_file(tmp_path, edit, message):
    path = tmp_path / "bad.yaml"
    path.write_text(edit(DOC_BLOCK))
    with pytest.raises(SourceError) as err:
        read_noise_config(UPath(path))
    assert str(err.value).startswith(str(path)) and message in str(err.value) and "\n" not in str(err.value)


def test_flags_make_the_same_setting_as_the_file(tmp_path):
    path = tmp_path / "doc.yaml"
    path.write_text(DOC_BLOCK)
    flags = {
        "noise_name": "doc",
        "noise_model": None,
        "noise_seed": 25,
        "async_": True,
        "async_mode": "sim",
        "async_overhead": 100.0,
        "backbone_delay": 10.0,
        "data_size": 1.06,
        "transmission_speed": 27.0,
        "loc_err": True,
        "xyz_std": 0.2,
        "ryp_std": 0.2,
        "max_cav": None,
        "gps_process": None,
        "correlation_time_s": None,
        "bias_xyz_std": None,
        "bias_ryp_std": None,
        "gps_dof": None,
        "perturb_ego": None,
    }
    (from_flags,) = noise_settings((), flags)
    assert from_flags == read_noise_config(UPath(path))
    with pytest.raises(ValueError, match="used more than once: doc"):
        check_unique([from_flags, read_noise_config(UPath(path))])


# --- converted scenarios -----------------------------------------------------------------------

CONFIG = SynthConfig(dataset="v2xset", frames=8, seed=11, cavs=3, infrastructure=True, lidar_columns=90, render_step=8)
#: The converted opencood settings, as a user writes them in the wild_setting block.
WILD = {"opencood_test": OPENCOOD_CASES[0], "opencood_real": {**OPENCOOD_CASES[6], "async_overhead": 300}}
SETTINGS = (
    *(make_setting({"name": name, **wild}) for name, wild in WILD.items()),
    make_setting(
        {
            "name": "gm_drift",
            "model": "realistic",
            "seed": 8,
            "async": True,
            "async_mode": "real",
            "async_overhead": 150,
            "loc_err": True,
            "xyz_std": 0.5,
            "ryp_std": 0.5,
            "process": "gauss_markov",
            "correlation_time_s": 2.0,
            "bias_xyz_std": 0.3,
        }
    ),
)


@dataclass
class Converted:
    truth: ScenarioTruth
    out: Path

    @property
    def manifest(self) -> dict:
        return json.loads((self.out / "scenario.json").read_text())

    def reader(self, agent_id: str) -> SequenceComponentGroupsReader:
        return SequenceComponentGroupsReader(
            [UPath(self.out / agent_id / f"{self.truth.scenario}_agent{agent_id}.json")]
        )

    def loader(self, agent_id: str, instance: str = "default") -> SequenceLoaderV4:
        return SequenceLoaderV4(self.reader(agent_id), poses_component_group_name=instance)

    def pose_data(self, agent_id: str, instance: str) -> PosesComponent.Reader:
        return self.reader(agent_id).open_component_readers(PosesComponent.Reader)[instance]


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> tuple[Path, ScenarioTruth]:
    """The synthetic scenario (``CONFIG``), written once: every conversion here reads this one input."""
    root = tmp_path_factory.mktemp("noise-src")
    (truth,) = write_dataset(UPath(root), CONFIG)
    return root, truth


def convert(source: tuple[Path, ScenarioTruth], tmp: Path, settings_=SETTINGS, layout: str = "agents") -> Converted:
    root, truth = source
    out = tmp / "out" / truth.scenario
    options = OpenCoodOptions(dataset="v2xset", split=CONFIG.split, layout=layout, noise=settings_)
    convert_scenario(UPath(root), UPath(out), truth.scenario, options)
    return Converted(truth, out)


@pytest.fixture(scope="module")
def converted(tmp_path_factory, source) -> Converted:
    return convert(source, tmp_path_factory.mktemp("noise"))


def lidar_world_global(loader: SequenceLoaderV4, t_us: int) -> np.ndarray:
    return loader.pose_graph.evaluate_poses(src.LIDAR, "world_global", np.array([t_us], dtype=np.uint64))[0]


@pytest.mark.parametrize("name", ["opencood_test", "opencood_real"])
def test_converted_opencood_setting_gives_opencoods_transformation_matrices(converted, name):
    """For every ego frame and agent: the stored delay and source frame are OpenCOOD's, and the
    noisy source pose composed with the ego's true pose is OpenCOOD's ``transformation_matrix``."""
    truth = converted.truth
    wild = WILD[name]
    folders = list(truth.agents)
    poses = {a: [truth.agents[a].lidar_pose[k] for k in truth.keys] for a in folders}
    expected = OpenCoodRestatement(wild).run(folders, poses, len(truth.keys))
    ego = converted.manifest["ego"]["agent_id"]
    assert str(ego) == src.opencood_ego(folders)
    dt_us = round(truth.fixed_delta_seconds * 1e6)
    times = [int(k) * dt_us for k in truth.keys]
    ego_loader = converted.loader(str(ego))
    checked_delayed = 0
    for agent in folders:
        data = converted.pose_data(agent, name)
        noisy = converted.loader(agent, name)
        np.testing.assert_array_equal(data.get_generic_data("delay_ego_timestamps_us"), times)
        for i, frame in enumerate(expected):
            delay_ms, d, j, noisy_delayed = frame[agent]
            assert data.get_generic_data("delay_frames")[i] == d
            assert data.get_generic_data("delay_ms")[i] == delay_ms
            assert data.get_generic_data("delay_source_keys")[i] == int(truth.keys[j])
            assert data.get_generic_data("delay_source_timestamps_us")[i] == times[j]
            # OpenCOOD: x1_to_x2(noisy delayed cav pose, current ego pose), in CARLA's left-handed frames
            opencood_T = np.linalg.inv(carla_pose_matrix(np.array(poses[str(ego)][i]))) @ carla_pose_matrix(
                np.array(noisy_delayed)
            )
            ours = np.linalg.inv(lidar_world_global(ego_loader, times[i])) @ lidar_world_global(noisy, times[j])
            np.testing.assert_allclose(ours[:3, :3], (MIRROR @ opencood_T @ MIRROR)[:3, :3], atol=2e-5)
            np.testing.assert_allclose(ours[:3, 3], (MIRROR @ opencood_T @ MIRROR)[:3, 3], atol=2e-3)
            checked_delayed += j != i
    assert checked_delayed > 0


def test_ego_is_unperturbed_and_others_are_where_opencood_leaves_them(converted):
    ego = str(converted.manifest["ego"]["agent_id"])
    dt_us = round(converted.truth.fixed_delta_seconds * 1e6)
    t = np.array([int(k) * dt_us for k in converted.truth.keys], dtype=np.uint64)
    for agent in converted.truth.agents:
        default = converted.loader(agent).pose_graph.evaluate_poses("rig", "world_global", t)
        for s in SETTINGS:
            noisy = converted.loader(agent, s.name).pose_graph.evaluate_poses("rig", "world_global", t)
            moved = np.linalg.norm(noisy[:, :3, 3] - default[:, :3, 3], axis=1)
            if agent == ego:
                np.testing.assert_array_equal(noisy, default)
                assert np.all(converted.pose_data(agent, s.name).get_generic_data("delay_ms") == 0)
            else:
                assert np.all(moved > 1e-3), (agent, s.name)


def test_realistic_setting_stores_the_error_it_applied_and_the_newest_sendable_frame(converted):
    ego = str(converted.manifest["ego"]["agent_id"])
    for agent in converted.truth.agents:
        data = converted.pose_data(agent, "gm_drift")
        t = data.get_generic_data("pose_noise_timestamps_us")
        e = data.get_generic_data("pose_noise")
        true = converted.loader(agent).pose_graph.evaluate_poses("rig", "world_global", t)
        noisy = converted.loader(agent, "gm_drift").pose_graph.evaluate_poses("rig", "world_global", t)
        np.testing.assert_allclose(noisy[:, :3, 3] - true[:, :3, 3], e[:, :3], atol=2e-4)
        turn = Rotation.from_matrix(noisy[:, :3, :3] @ np.transpose(true[:, :3, :3], (0, 2, 1)))
        np.testing.assert_allclose(turn.as_euler("xyz", degrees=True), e[:, 3:], atol=2e-3)
        ego_t = data.get_generic_data("delay_ego_timestamps_us").astype(np.int64)
        delay_ms = data.get_generic_data("delay_ms")
        source_t = data.get_generic_data("delay_source_timestamps_us")
        if agent == ego:
            assert np.all(e == 0) and np.all(delay_ms == 0) and np.all(source_t == ego_t)
            continue
        assert np.all((delay_ms >= 0) & (delay_ms <= 150)) and np.any(delay_ms != np.round(delay_ms))
        old_enough = source_t <= ego_t - delay_ms * 1000
        assert np.all(old_enough | (source_t == t[0]))  # or the first frame, at the scenario's start
        nxt = np.searchsorted(t, source_t, side="right")
        newer = t[np.minimum(nxt, len(t) - 1)]
        assert np.all((nxt == len(t)) | (newer > ego_t - delay_ms * 1000))


def test_setting_model_and_seed_are_recorded_in_metadata(converted):
    manifest = converted.manifest
    assert [s["name"] for s in manifest["noise_settings"]] == [s.name for s in SETTINGS]
    agent = next(iter(converted.truth.agents))
    for s in SETTINGS:
        meta = converted.pose_data(agent, s.name).generic_meta_data
        assert meta["noise_setting"] == s.as_dict() and meta["noise_model"] == s.model and meta["noise_seed"] == s.seed
    assert converted.loader(agent).generic_meta_data["noise_settings"]["gm_drift"]["correlation_time_s"] == 2.0


def test_cuboids_and_calibration_are_shared_by_every_poses_instance(converted):
    agent = next(a for a in converted.truth.agents if a != str(converted.manifest["ego"]["agent_id"]))
    default, noisy = converted.loader(agent), converted.loader(agent, "gm_drift")
    boxes_default = list(default.get_cuboid_track_observations())
    assert boxes_default and boxes_default == list(noisy.get_cuboid_track_observations())
    assert all(b.reference_frame_id == "rig" for b in boxes_default)
    for sensor in [src.LIDAR, *src.CAMERAS]:
        np.testing.assert_array_equal(
            default.pose_graph.evaluate_poses(sensor, "rig", np.zeros(1, np.uint64)),
            noisy.pose_graph.evaluate_poses(sensor, "rig", np.zeros(1, np.uint64)),
        )


def test_scenario_layout_holds_every_agent_in_the_noisy_instance(tmp_path, converted, source):
    scenario = convert(source, tmp_path, SETTINGS[:1], layout="scenario")
    reader = SequenceComponentGroupsReader([UPath(scenario.out / f"{scenario.truth.scenario}.json")])
    loader = SequenceLoaderV4(reader, poses_component_group_name="opencood_test")
    data = reader.open_component_readers(PosesComponent.Reader)["opencood_test"]
    t = np.array([int(converted.truth.keys[2]) * round(CONFIG.fixed_delta_seconds * 1e6)], dtype=np.uint64)
    for agent in scenario.truth.agents:
        separate = converted.loader(agent, "opencood_test").pose_graph.evaluate_poses("rig", "world_global", t)
        together = loader.pose_graph.evaluate_poses(f"agent{agent}_rig", "world_global", t)
        np.testing.assert_allclose(together, separate, atol=2e-4)
        np.testing.assert_array_equal(
            data.get_generic_data(f"agent{agent}_delay_frames"),
            converted.pose_data(agent, "opencood_test").get_generic_data("delay_frames"),
        )


def test_same_seed_same_output_other_seed_other_output(tmp_path, converted, source):
    again = convert(source, tmp_path / "again", SETTINGS[1:])
    reseeded = convert(source, tmp_path / "reseeded", (make_setting({**SETTINGS[2].as_dict(), "seed": 9}),))
    for agent in converted.truth.agents:
        for s in SETTINGS[1:]:
            a, b = converted.pose_data(agent, s.name), again.pose_data(agent, s.name)
            assert a.get_generic_data_names() == b.get_generic_data_names()
            for name in a.get_generic_data_names():
                np.testing.assert_array_equal(a.get_generic_data(name), b.get_generic_data(name))
            for edge, (poses, stamps) in a.get_dynamic_poses():
                other = dict(b.get_dynamic_poses())[edge]
                np.testing.assert_array_equal(poses, other[0])
                np.testing.assert_array_equal(stamps, other[1])
    agent = next(a for a in converted.truth.agents if a != str(converted.manifest["ego"]["agent_id"]))
    other = reseeded.pose_data(agent, "gm_drift")
    assert other.generic_meta_data["noise_seed"] == 9
    first = converted.pose_data(agent, "gm_drift").get_generic_data("pose_noise")
    assert np.all(np.abs(other.get_generic_data("pose_noise") - first)[:, :3] > 0)
    shutil.rmtree(tmp_path / "again")


def test_the_command_rejects_a_bad_noise_config_naming_the_file(tmp_path):
    from click.testing import CliRunner

    from ncore_convert.cli import cli

    bad = tmp_path / "typo.yaml"
    bad.write_text(DOC_BLOCK.replace("ryp_std", "rpy_std"))
    args = ["--root-dir", str(tmp_path), "--output-dir", str(tmp_path / "out"), "v2xset-v4", "--split", "test"]
    result = CliRunner().invoke(cli, [*args, "--noise-config", str(bad)])
    assert result.exit_code == 2 and f"{bad}: wild_setting: OpenCOOD does not read rpy_std" in result.output
    result = CliRunner().invoke(cli, [*args, "--noise-model", "opencood", "--gps-dof", "xy_yaw"])
    assert result.exit_code == 2 and "only apply to the realistic model" in result.output
    assert not (tmp_path / "out").exists()
