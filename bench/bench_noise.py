"""Benchmark GPS error and communication delay. Not a test.

1. The models alone: ``plan_noise`` for a long OPV2V-sized scenario (7 agents x 700 frames, the
   longest OPV2V scenarios) under the opencood (sim), opencood (real mode with loc_err) and
   realistic (Gauss-Markov, real-mode delay) settings.
2. The cost in a conversion: ``ncore-convert opv2v-v4`` of a synthetic 60-frame, 3-CAV scenario
   without noise and with those three settings, interleaved in one run, and the ratio; plus the
   bytes the settings add.

Figures are medians over --repeat runs.

    python bench/bench_noise.py [--work /tmp/ncore-bench] [--repeat 5]
"""

from __future__ import annotations

import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from bench_argoverse2 import bench_parser, cached, work_dir
from upath import UPath

from ncore_convert.converters.opencood import AgentPlan
from ncore_convert.converters.opencood.noise import plan_noise
from ncore_convert.sources import opencood as src
from ncore_convert.sources.noise_config import make_setting
from ncore_convert.sources.opencood import key_timestamps_us

COMMON = {"seed": 25, "async": True, "loc_err": True, "xyz_std": 0.2, "ryp_std": 0.2}
SETTINGS = {
    "opencood_sim": {**COMMON, "async_overhead": 100},
    "opencood_real": {**COMMON, "async_mode": "real", "async_overhead": 300},
    "gm_drift": {
        **COMMON,
        "model": "realistic",
        "async_mode": "real",
        "async_overhead": 100,
        "process": "gauss_markov",
        "correlation_time_s": 5.0,
        "bias_xyz_std": 0.1,
    },
}


def stand_in_agents(n_agents: int, n_frames: int) -> tuple[dict[str, AgentPlan], list[str]]:
    """Agent plans with moving poses (only what the noise models read)."""
    rng = np.random.default_rng(0)
    keys = [f"{69 + 2 * i:06d}" for i in range(n_frames)]
    agents = {}
    for a in range(n_agents):
        agent_id = str(100 + 37 * a)
        pose = np.zeros((n_frames, 6))
        pose[:, 0] = np.linspace(0, 700, n_frames) + rng.normal(0, 50)
        pose[:, 4] = rng.uniform(-180, 180)
        T_rig = np.tile(np.eye(4), (n_frames, 1, 1))
        T_rig[:, :3, 3] = pose[:, :3]
        agents[agent_id] = AgentPlan(
            agent_id=agent_id,
            agent_dir=UPath("/nonexistent"),
            keys=keys,
            timestamps_us=key_timestamps_us(keys, 0.05),
            lidar_pose_carla=pose,
            T_rig_world_global=T_rig,
            T_sensor_rig={src.LIDAR: np.eye(4)},
            intrinsics={},
            camera_index={},
            lidar_ids=[src.LIDAR],
            mounts={},
        )
    return agents, keys


def model_times(repeat: int) -> dict[str, float]:
    agents, keys = stand_in_agents(7, 700)
    folders = list(agents)
    ego_t = key_timestamps_us(keys, 0.05)
    out = {}
    for name, values in SETTINGS.items():
        setting = make_setting({"name": name, **values})
        runs = []
        for _ in range(repeat):
            started = time.perf_counter()
            plan_noise(setting, "scenario", agents, folders, keys, ego_t)
            runs.append(time.perf_counter() - started)
        out[name] = statistics.median(runs)
    return out


def convert(root: Path, out: Path, configs: list[Path]) -> float:
    shutil.rmtree(out, ignore_errors=True)
    cli = Path(sys.executable).parent / "ncore-convert"
    flags = [arg for path in configs for arg in ("--noise-config", str(path))]
    started = time.perf_counter()
    subprocess.run(
        [
            str(cli),
            "--no-progress",
            "--no-validate",
            "--workers",
            "1",
            "--root-dir",
            str(root),
            "--output-dir",
            str(out),
            "opv2v-v4",
            "--split",
            "test",
            *flags,
        ],
        check=True,
        capture_output=True,
    )
    return time.perf_counter() - started


def main() -> None:
    args = bench_parser(__doc__, repeat=5).parse_args()
    work = work_dir(args)
    print(f"GPS error and delay; medians of {args.repeat}", flush=True)
    for name, seconds in model_times(args.repeat).items():
        print(
            f"  plan_noise, 7 agents x 700 frames, {name}: {seconds * 1e3:.1f} ms"
            f" ({seconds / 4900 * 1e6:.1f} us per agent-frame)",
            flush=True,
        )

    from ncore_convert.synth.opencood import SynthConfig, write_dataset

    root = work / "opencood-noise-60"
    config = SynthConfig(dataset="opv2v", frames=60, cavs=3, lidar_columns=256)
    cached(root, "the scenario", lambda r: write_dataset(UPath(r), config)[0].scenario)
    configs = []
    for name, values in SETTINGS.items():
        configs.append(work / f"{name}.yaml")
        configs[-1].write_text(yaml.safe_dump({"wild_setting": {"name": name, **values}}))
    times: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(args.repeat):
        for noise in (False, True):
            times[noise].append(convert(root, work / f"noise-out-{noise}", configs if noise else []))
    plain, noisy = statistics.median(times[False]), statistics.median(times[True])
    size = {n: sum(p.stat().st_size for p in (work / f"noise-out-{n}").rglob("*") if p.is_file()) for n in times}
    print(
        f"  conversion, 60 frames x 3 CAVs, whole command: {plain:.2f} s without noise, {noisy:.2f} s with the"
        f" three settings, ratio {noisy / plain:.3f}; output {size[False] / 1e6:.1f} MB ->"
        f" {size[True] / 1e6:.1f} MB (+{(size[True] - size[False]) / 1e3:.0f} kB)",
        flush=True,
    )


if __name__ == "__main__":
    main()
