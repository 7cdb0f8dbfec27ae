"""Shared fixtures: synthetic AV2 logs with truth, the real AV2 sample, and their conversions."""

from __future__ import annotations

import os
import pickle
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import samples
from click.testing import CliRunner
from filelock import FileLock
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from upath import UPath

from ncore_convert.cli import cli
from ncore_convert.converters.argoverse2 import Argoverse2Options, LogSummary, convert_log
from ncore_convert.synth.argoverse2 import SynthConfig, SynthTruth, write_log
from ncore_convert.transforms.geometry import Trajectory, invert_se3, transform_points

REPO = Path(__file__).resolve().parents[1]
#: The slowest test files, slowest first (per-file seconds in docs/tests.md). ``make test`` hands
#: whole files to the workers in this order, then the rest: the long ones start first, so no worker
#: is left with one at the end. A stale list costs balance, never a test.
SLOW_FIRST = (
    "test_ego_masks",
    "test_camera_labels",
    "test_validate",
    "test_object_reads",
    "test_bad_input",
    "test_camera_labels_opencood",
    "test_dynamic_tracks",
    "test_point_colours",
    "test_shared_runs",
    "test_motion",
    "test_s3",
    "test_consumers",
    "test_fuzz_readers",
    "test_determinism",
    "test_stop",
    "test_ray",
    "test_presets",
    "test_resume",
    "test_preview",
    "test_opencood_view",
)
#: Tests whose cases each build their own data and are slow: each case goes to whichever worker is
#: free, instead of staying with its file.
OWN_SCOPE = ("tests/test_ego_masks.py::test_realistic_bodies[",)


def pytest_collection_modifyitems(config, items) -> None:
    """Files in ``SLOW_FIRST`` order, then the rest; a file's tests keep their order."""
    rank = {name: i for i, name in enumerate(SLOW_FIRST)}
    items.sort(key=lambda item: rank.get(item.module.__name__, len(rank)))


def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` (a file's tests on one worker, so its module fixtures are built once),
    except that each case of an ``OWN_SCOPE`` test is scheduled on its own. (pytest-xdist's
    ``loadgroup`` marks would say this, but they are ignored with pytest 9.2: pytest-xdist#1386.)"""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class FilesAndOwnScopes(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return nodeid if nodeid.startswith(OWN_SCOPE) else super()._split_scope(nodeid)

    return FilesAndOwnScopes(config, log)


BIN = Path(sys.executable).parent  #: the venv's scripts: ncore-convert, ray, moto_server
AV2_SAMPLE_LOG = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def naive_compensate(
    xyz_sensor_m: np.ndarray, times_ns: np.ndarray, ref_ns: int, traj: Trajectory, T_sensor_rig: np.ndarray
) -> np.ndarray:
    """Sensor points at their own times -> rig at ``ref_ns``, one 4x4 chain per point:
    ``T_rig_world(ref)^-1 · T_rig_world(t) · T_sensor_rig`` (the reference the vectorised code is held to)."""
    T_t = traj.interpolate(traj.relative_seconds(times_ns))
    T_ref = traj.interpolate(traj.relative_seconds(np.array([ref_ns])))[0]
    return transform_points(invert_se3(T_ref)[None] @ T_t @ T_sensor_rig[None], xyz_sensor_m)


def find_av2_sample() -> Path:
    """The real AV2 sample's folder (``<it>/val/<AV2_SAMPLE_LOG>``), in the samples cache (tests/samples.py)."""
    return samples.ensure()["av2-sample"]


#: The real OPV2V sample: one agent of one scenario of the validate split, ticks 68-74.
OPV2V_SAMPLE_SCENARIO, OPV2V_SAMPLE_AGENT, OPV2V_SAMPLE_KEYS = "2021_08_18_19_48_05", "1045", (68, 70, 72, 74)


def find_opv2v_sample() -> Path:
    """The real OPV2V sample's dataset root (``<it>/validate/<scenario>/<agent>/000068.pcd`` ...), in
    the samples cache (tests/samples.py)."""
    return samples.ensure()["opv2v-agent-sample"]


def find_opv2v_agent() -> Path:
    """The real OPV2V agent's folder: ``000068.pcd`` ... ``000074.pcd``, their YAMLs and camera PNGs."""
    return find_opv2v_sample() / "validate" / OPV2V_SAMPLE_SCENARIO / OPV2V_SAMPLE_AGENT


@pytest.hookimpl(tryfirst=True)
def pytest_sessionstart(session) -> None:
    """The real samples, checked (and fetched if need be) before any test runs, by the controller and
    then by each xdist worker (a file lock in the cache): a sample no source can give stops the run
    with one line, instead of failing every test that reads it."""
    try:
        samples.ensure()
    except samples.SampleUnavailable as error:
        pytest.exit(str(error), returncode=4)


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """``ncore-convert ARGS`` in this process (click's runner), as a finished process: its exit code,
    stdout and stderr. Tests that need a process of their own (signals, kills, determinism across
    processes, terminal detection) start the installed command instead (:data:`BIN`)."""
    result = CliRunner().invoke(cli, list(args))
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return subprocess.CompletedProcess(list(args), result.exit_code, result.stdout, result.stderr)


def av2_args(root, out, *group_options) -> list[str]:
    """``ncore-convert``'s arguments converting ``<root>/val`` into ``out`` (for :func:`run_cli`)."""
    return [
        "--no-progress",
        "--root-dir",
        str(root),
        "--output-dir",
        str(out),
        *group_options,
        "argoverse2-v4",
        "--split",
        "val",
    ]


def av2_command(root, out, *group_options) -> list[str]:
    """The installed ``ncore-convert`` command converting ``<root>/val`` into ``out`` (for subprocesses)."""
    return [str(BIN / "ncore-convert"), *av2_args(root, out, *group_options)]


@dataclass
class Converted:
    truth: SynthTruth | None
    summary: LogSummary
    seq_dir: Path
    loader: SequenceLoaderV4

    @property
    def reader(self) -> SequenceComponentGroupsReader:
        return self.loader._reader


def open_sequence(seq_dir: Path, sequence_id: str) -> SequenceLoaderV4:
    return SequenceLoaderV4(SequenceComponentGroupsReader([UPath(seq_dir / f"{sequence_id}.json")]))


def component_meta(loader: SequenceLoaderV4, component, instance: str) -> dict:
    """A component instance's generic metadata (``component``: e.g. ``CameraSensorComponent``)."""
    return loader._reader.open_component_readers(component.Reader)[instance].generic_meta_data


def synth_and_convert(tmp: Path, config: SynthConfig, options: Argoverse2Options | None = None) -> Converted:
    """Synthesise ``config`` into ``tmp/src/val`` and convert it into ``tmp/out``."""
    truth = write_log(UPath(tmp / "src" / "val"), config)
    return convert_synthetic(truth, tmp / "out", options or Argoverse2Options(split="val"))


def convert_synthetic(truth: SynthTruth, out: Path, options: Argoverse2Options) -> Converted:
    """Convert the synthetic AV2 log of ``truth`` (written under ``<root>/val``) into ``out``."""
    seq_dir = out / truth.log_id
    summary = convert_log(UPath(truth.log_dir.parent.parent), UPath(seq_dir), truth.log_id, options)
    return Converted(truth, summary, seq_dir, open_sequence(seq_dir, truth.log_id))


def shared_by_workers(tmp_path_factory, name: str, make: Callable[[Path], Converted]) -> Converted:
    """``make(folder)`` once per test run, by whichever pytest-xdist worker asks first; the others
    wait for it (a file lock in the run's base directory, which the workers share) and read the
    same files. The tests must not change them (they copy what they corrupt)."""
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / f"shared-{name}"
    state = folder / "converted.pickle"
    with FileLock(f"{folder}.lock"):
        if not state.is_file():
            run = make(folder)
            state.write_bytes(pickle.dumps((run.truth, run.summary, run.seq_dir)))
            return run
    truth, summary, seq_dir = pickle.loads(state.read_bytes())
    return Converted(truth, summary, seq_dir, open_sequence(seq_dir, seq_dir.name))


@pytest.fixture(scope="session")
def synth_log(tmp_path_factory) -> Converted:
    """A 1 s synthetic log with images at 20 fps, converted with default options (one per test run)."""
    config = SynthConfig(seconds=1.0, seed=1, keep_truth=True, pictures=2)
    return shared_by_workers(tmp_path_factory, "synth", lambda folder: synth_and_convert(folder, config))


@pytest.fixture(scope="session")
def synth_swapped(tmp_path_factory) -> Converted:
    """A synthetic log whose laser_number halves are exchanged (up_lidar owns >= 32)."""
    return synth_and_convert(
        tmp_path_factory.mktemp("swapped"),
        SynthConfig(seconds=0.5, seed=2, swap_lidar_halves=True, camera_fps=0, keep_truth=True),
        Argoverse2Options(split="val", camera_ids=()),
    )


@pytest.fixture(scope="session")
def av2_sample_root() -> Path:
    return find_av2_sample()


@pytest.fixture(scope="session")
def real_log(av2_sample_root, tmp_path_factory) -> Converted:
    """The real sample, converted with default options (one per test run)."""

    def convert(folder: Path) -> Converted:
        seq_dir = folder / AV2_SAMPLE_LOG
        summary = convert_log(UPath(av2_sample_root), UPath(seq_dir), AV2_SAMPLE_LOG, Argoverse2Options(split="val"))
        return Converted(None, summary, seq_dir, open_sequence(seq_dir, AV2_SAMPLE_LOG))

    return shared_by_workers(tmp_path_factory, "real", convert)


@pytest.fixture(scope="module")
def s3_env():
    """A moto S3 server on 127.0.0.1; the environment that points AWS clients (s3fs) at it."""
    port = free_port()
    server = subprocess.Popen(
        [str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    env = {
        "AWS_ACCESS_KEY_ID": "test",
        "AWS_SECRET_ACCESS_KEY": "test",
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}",
    }
    saved = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "moto server did not start"
                time.sleep(0.2)
        yield {**os.environ, **env}
    finally:
        server.terminate()
        server.wait(timeout=30)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
