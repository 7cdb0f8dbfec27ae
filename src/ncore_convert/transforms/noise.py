"""GPS-error and communication-delay models: pure numpy functions of a setting and the frame times.

A setting (:class:`NoiseSetting`) is OpenCOOD's ``wild_setting`` block; ``sources.noise_config``
reads and checks it. Two models (docs/noise.md):
- ``opencood`` restates OpenCOOD's ``BaseDataset`` (``time_delay_calculation``, ``add_loc_noise``,
  ``retrieve_base_data``) draw for draw: numpy's legacy generator, re-seeded with the setting's seed
  inside every localisation-noise call, so every non-ego agent gets the same offset in every frame;
  noise on the lidar pose's x, y, z (m) and yaw (deg) in CARLA's frame; delay quantised to whole
  100 ms frames.
- ``realistic``: independent streams per (seed, scenario, agent); white or first-order Gauss-Markov
  pose error with an optional constant bias, in 6 DoF or x/y/yaw; delay in ms, not quantised.
"""

from __future__ import annotations

import zlib
from dataclasses import asdict, dataclass
from typing import get_args

import numpy as np
from scipy.spatial.transform import Rotation

from ncore_convert.contract import AsyncMode, GpsDof, GpsProcess, NoiseModel

MODELS, ASYNC_MODES = get_args(NoiseModel), get_args(AsyncMode)
PROCESSES, DOFS = get_args(GpsProcess), get_args(GpsDof)
#: Keys only the ``realistic`` model reads.
REALISTIC_ONLY = ("process", "correlation_time_s", "bias_xyz_std", "bias_ryp_std", "dof", "perturb_ego")


@dataclass(frozen=True)
class NoiseSetting:
    """One named GPS-error / delay setting. Field names are OpenCOOD's ``wild_setting`` keys
    (``async_`` for ``async``, a Python keyword).

    Units: ``async_overhead`` and ``backbone_delay`` ms, ``data_size`` Mb, ``transmission_speed``
    Mb/s, ``xyz_std`` and ``bias_xyz_std`` m, ``ryp_std`` and ``bias_ryp_std`` degrees,
    ``correlation_time_s`` s. ``max_cav`` is OpenCOOD's ``train_params.max_cav`` (default 7): the
    ``opencood`` model leaves agents past it in OpenCOOD's order out, as OpenCOOD does.
    """

    name: str
    model: NoiseModel = "opencood"
    seed: int = 25
    async_: bool = False
    async_mode: AsyncMode = "sim"
    async_overhead: float = 0.0
    backbone_delay: float = 0.0
    data_size: float = 0.0
    transmission_speed: float = 27.0
    loc_err: bool = False
    xyz_std: float = 0.0
    ryp_std: float = 0.0
    process: GpsProcess = "white"
    correlation_time_s: float = 10.0
    bias_xyz_std: float = 0.0
    bias_ryp_std: float = 0.0
    dof: GpsDof = "6dof"
    perturb_ego: bool = False
    max_cav: int = 7

    def as_dict(self) -> dict:
        """The setting with OpenCOOD's key names (``async``), for metadata."""
        out = asdict(self)
        out["async"] = out.pop("async_")
        for key in REALISTIC_ONLY if self.model == "opencood" else ("max_cav",):
            out.pop(key)
        return out


#: OpenCOOD turns a delay into frames as ``delay_ms // 100`` ("the data is 10 hz").
OPENCOOD_FRAME_MS = 100
NO_SOURCE = -1


@dataclass(frozen=True)
class Delays:
    """One agent's delay at each ego frame.

    Attributes:
        delay_ms: the modelled delay, float64 [T] (0 when ``async`` is off).
        source_index: index into the agent's frames whose data is used, int64 [T]; ``NO_SOURCE``
            when the agent has no frame to send.
        delay_frames: OpenCOOD's ``time_delay`` (frames behind in the ego's frame list, after its
            clamp), int64 [T]; None for the realistic model.
    """

    delay_ms: np.ndarray
    source_index: np.ndarray
    delay_frames: np.ndarray | None = None


def opencood_loc_offset(setting: NoiseSetting) -> np.ndarray:
    """OpenCOOD's ``add_loc_noise`` offset, the same in every call: float64 [6], in the order of a
    CARLA pose ``[x, y, z, roll, yaw, pitch]`` (m, deg); only x, y, z and yaw are non-zero.
    Zero when ``loc_err`` is off."""
    offset = np.zeros(6)
    if setting.loc_err:
        rs = np.random.RandomState(setting.seed)
        xyz = rs.normal(0, setting.xyz_std, 3)
        ryp = rs.normal(0, setting.ryp_std, 3)
        offset[:3], offset[4] = xyz, ryp[1]
    return offset


def opencood_delays(setting: NoiseSetting, n_ego_frames: int, agent_order: list[str], ego: str) -> dict:
    """OpenCOOD's per-frame delays of every agent, drawing in OpenCOOD's order.

    For each ego frame ``i`` (OpenCOOD's timestamp index) and each agent in ``agent_order`` (its
    scenario-database order: ego first), a non-ego agent draws ``U(0, async_overhead)`` in ``real``
    mode (even with ``async`` off), then, with ``loc_err``, two ``add_loc_noise`` calls re-seed the
    generator and draw 2×3 normals each. The generator state on entering a scenario is
    ``seed(setting.seed)``: in OpenCOOD it is whatever the loader drew before (point shuffling,
    augmentation, other scenarios), which no converter can know.

    Returns:
        agent id -> (delay_ms float64 [T], delay_frames int64 [T]), after OpenCOOD's clamp
        ``if i - d <= 0: d = i``; the ego's are zero.
    """
    rs = np.random.RandomState(setting.seed)
    tc_ms = setting.data_size / setting.transmission_speed * 1000
    out = {a: (np.zeros(n_ego_frames), np.zeros(n_ego_frames, dtype=np.int64)) for a in agent_order}
    for i in range(n_ego_frames):
        for agent in agent_order:
            if agent == ego:
                continue
            if setting.async_mode == "real":
                delay_ms = float(int(rs.uniform(0, setting.async_overhead) + tc_ms + setting.backbone_delay))
            else:
                delay_ms = abs(setting.async_overhead)
            frames = int(delay_ms // OPENCOOD_FRAME_MS) if setting.async_ else 0
            out[agent][0][i] = delay_ms if setting.async_ else 0.0
            out[agent][1][i] = i if i - frames <= 0 else frames
            if setting.loc_err:  # add_loc_noise (delayed pose, then current pose): both re-seed, so one call's
                rs.seed(setting.seed)  # draws leave the generator where the two leave it
                rs.normal(0, setting.xyz_std, 3)
                rs.normal(0, setting.ryp_std, 3)
    return out


def agent_rngs(setting: NoiseSetting, scenario: str, agent_id: str) -> tuple[np.random.Generator, np.random.Generator]:
    """The realistic model's (pose, delay) generators of one agent: independent of every other agent's
    and scenario's, and of the order agents are converted in."""
    key = (zlib.crc32(scenario.encode()), zlib.crc32(agent_id.encode()))
    pose, delay = (np.random.SeedSequence(setting.seed, spawn_key=(*key, stream)) for stream in (0, 1))
    return np.random.default_rng(pose), np.random.default_rng(delay)


def gauss_markov(
    rng: np.random.Generator, timestamps_us: np.ndarray, std: np.ndarray, correlation_time_s: float | None
) -> np.ndarray:
    """A stationary first-order Gauss-Markov process sampled at ``timestamps_us`` (int [N], increasing).

    ``e_0 ~ N(0, std²)``, ``e_k = φ_k e_(k-1) + std·sqrt(1 - φ_k²)·w_k`` with
    ``φ_k = exp(-Δt_k / correlation_time_s)``; ``correlation_time_s=None`` gives white noise (φ = 0).

    Args:
        std: per-component standard deviation [K]. Returns [N,K] in the units of ``std``.
    """
    std = np.asarray(std, dtype=np.float64)
    w = rng.standard_normal((len(timestamps_us), len(std)))
    if correlation_time_s is None:
        return w * std
    phi = np.exp(-np.diff(np.asarray(timestamps_us, dtype=np.float64)) * 1e-6 / correlation_time_s)
    scale = np.sqrt(1.0 - phi**2)
    e = np.empty_like(w)
    e[0] = w[0]
    for k in range(1, len(w)):  # sequential by definition; N is a log's frame count
        e[k] = phi[k - 1] * e[k - 1] + scale[k - 1] * w[k]
    return e * std


def realistic_pose_noise(setting: NoiseSetting, rng: np.random.Generator, timestamps_us: np.ndarray) -> np.ndarray:
    """Per-frame rig pose error [N,6]: ``(dx, dy, dz)`` in metres along world_global's axes and
    ``(droll, dpitch, dyaw)`` in degrees about them. Bias (drawn once) plus a white or Gauss-Markov
    process; with ``dof="xy_yaw"``, z, roll and pitch stay zero."""
    mask = np.array([1, 1, 1, 1, 1, 1.0]) if setting.dof == "6dof" else np.array([1, 1, 0, 0, 0, 1.0])
    std = np.repeat([setting.xyz_std, setting.ryp_std], 3) * mask
    bias = rng.standard_normal(6) * np.repeat([setting.bias_xyz_std, setting.bias_ryp_std], 3) * mask
    tau = setting.correlation_time_s if setting.process == "gauss_markov" else None
    return bias + gauss_markov(rng, timestamps_us, std, tau)


def perturb_poses(T_x_world: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """Apply :func:`realistic_pose_noise` to poses ``T_x_world`` [N,4,4] (frame x -> world): the
    translation moves by ``noise[:, :3]`` and the rotation turns by the extrinsic x-y-z Euler angles
    ``noise[:, 3:]`` (deg) about the world axes, at the posed frame's origin."""
    out = np.array(T_x_world, dtype=np.float64)
    turn = Rotation.from_euler("xyz", noise[:, 3:], degrees=True).as_matrix()
    out[:, :3, :3] = turn @ out[:, :3, :3]
    out[:, :3, 3] += noise[:, :3]
    return out


def realistic_delays_ms(setting: NoiseSetting, rng: np.random.Generator, n_ego_frames: int) -> np.ndarray:
    """Delay per ego frame in ms, float64 [T], unquantised: ``|async_overhead|`` in ``sim`` mode;
    ``U(0, async_overhead) + data_size / transmission_speed · 1000 + backbone_delay`` in ``real``
    mode; zero with ``async`` off."""
    if not setting.async_:
        return np.zeros(n_ego_frames)
    if setting.async_mode == "sim":
        return np.full(n_ego_frames, abs(setting.async_overhead))
    tc_ms = setting.data_size / setting.transmission_speed * 1000
    return rng.uniform(0, setting.async_overhead, n_ego_frames) + tc_ms + setting.backbone_delay


def latest_source(agent_timestamps_us: np.ndarray, ego_timestamps_us: np.ndarray, delay_ms: np.ndarray) -> np.ndarray:
    """Index of the agent's newest frame taken at or before ``t_ego - delay`` (int64 [T]).

    Before the agent's first frame, the first frame is used if it is not newer than the ego frame
    (OpenCOOD's clamp at the start of a scenario); otherwise ``NO_SOURCE``.
    """
    agent_t = np.asarray(agent_timestamps_us, dtype=np.float64)
    ego_t = np.asarray(ego_timestamps_us, dtype=np.float64)
    index = np.searchsorted(agent_t, ego_t - delay_ms * 1000.0, side="right") - 1
    clamp = (index < 0) & (agent_t[0] <= ego_t)
    return np.where(clamp, 0, np.where(index < 0, NO_SOURCE, index)).astype(np.int64)
