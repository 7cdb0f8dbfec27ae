"""Resumable runs and the run report: skip on rerun, --overwrite, --retry-failed, report contents."""

from __future__ import annotations

import json
import shutil

import pytest
from click.testing import CliRunner
from upath import UPath

from ncore_convert import __version__
from ncore_convert.cli import cli
from ncore_convert.synth.argoverse2 import SynthConfig, write_log


@pytest.fixture(scope="module")
def two_logs(tmp_path_factory):
    """Two 0.2 s synthetic logs without images."""
    root = tmp_path_factory.mktemp("resume")
    truths = [write_log(UPath(root / "val"), SynthConfig(seconds=0.2, seed=s, camera_fps=0)) for s in (21, 22)]
    return root, truths


def run(root, out, *extra, log_id=None):
    args = ["--no-progress", "--root-dir", str(root), "--output-dir", str(out), *extra, "argoverse2-v4"]
    args += ["--split", "val"] + (["--log-id", log_id] if log_id else [])
    return CliRunner().invoke(cli, args, catch_exceptions=False)


def report(out, name: str = "conversion-report.json") -> dict:
    return json.loads((out / name).read_text())


def store_mtimes(out, log_id) -> dict:
    return {p.name: p.stat().st_mtime_ns for p in (out / log_id).iterdir()}


def test_rerun_skips_converted_logs_and_overwrite_redoes_them(two_logs, tmp_path):
    root, truths = two_logs
    out = tmp_path / "out"
    assert run(root, out).exit_code == 0
    first = {t.log_id: store_mtimes(out, t.log_id) for t in truths}
    result = run(root, out)
    assert result.exit_code == 0 and result.output.count("skip  ") == 2
    assert "0 converted, 2 skipped, 0 failed" in result.output
    assert {t.log_id: store_mtimes(out, t.log_id) for t in truths} == first
    assert {e["status"] for e in report(out)["logs"].values()} == {"skipped"}
    result = run(root, out, "--overwrite")
    assert result.exit_code == 0 and "2 converted, 0 skipped" in result.output, result.output
    assert {e["status"] for e in report(out)["logs"].values()} == {"ok"}
    # different options are a different conversion: no skip
    result = run(root, out, "--lidar-id", "up_lidar")
    assert "2 converted, 0 skipped" in result.output
    # a converted folder that disappeared is converted again
    shutil.rmtree(out / truths[0].log_id)
    assert "1 converted, 1 skipped" in run(root, out, "--lidar-id", "up_lidar").output


def test_retry_failed_redoes_only_the_failures(two_logs, tmp_path):
    root, truths = two_logs
    src = tmp_path / "root"
    shutil.copytree(root, src)
    broken = src / "val" / truths[1].log_id / "city_SE3_egovehicle.feather"
    good_bytes = broken.read_bytes()
    broken.write_bytes(b"not feather")
    out = tmp_path / "out"
    result = run(src, out)
    assert result.exit_code == 1 and "1 converted, 0 skipped, 1 failed" in result.output
    entry = report(out)["logs"][truths[1].log_id]
    assert entry["status"] == "failed" and entry["error"]["file"] == str(broken)
    assert "not a readable feather table" in entry["error"]["reason"]
    broken.write_bytes(good_bytes)
    first_good = store_mtimes(out, truths[0].log_id)
    result = run(src, out, "--retry-failed")
    assert result.exit_code == 0, result.output
    assert f"skip  {truths[0].log_id}: converted by an earlier run, not a failure" in result.output
    assert f"ok    {truths[1].log_id}" in result.output
    assert "1 converted, 1 skipped, 0 failed;" in result.output  # the skipped log is the converted one
    assert store_mtimes(out, truths[0].log_id) == first_good
    assert {e["status"] for e in report(out)["logs"].values()} == {"ok"}
    assert "exclude each other" in run(src, out, "--retry-failed", "--overwrite").output


def test_retry_failed_counts_the_logs_it_never_attempted_apart(two_logs, tmp_path):
    """A log no earlier run attempted is neither skipped as converted nor converted: it is counted
    apart, and its report entry is not written."""
    root, truths = two_logs
    out = tmp_path / "out"
    assert run(root, out, log_id=truths[1].log_id).exit_code == 0
    result = run(root, out, "--retry-failed")
    assert result.exit_code == 0, result.output
    assert f"skip  {truths[0].log_id}: never attempted" in result.output
    assert f"skip  {truths[1].log_id}: converted by an earlier run" in result.output
    assert "0 converted, 1 skipped, 0 failed, 1 never attempted;" in result.output, result.output
    assert set(report(out)["logs"]) == {truths[1].log_id}


def test_report_records_status_times_bytes_and_the_converter(two_logs, tmp_path):
    root, truths = two_logs
    out = tmp_path / "out"
    assert run(root, out).exit_code == 0
    data = report(out)
    assert data["converter"]["version"] == __version__ and data["converter"]["command"] == "argoverse2-v4"
    assert data["converter"]["options"]["lidar_model_source"] == "empirical"
    for truth in truths:
        entry = data["logs"][truth.log_id]
        in_bytes = sum(p.stat().st_size for p in (root / "val" / truth.log_id).rglob("*") if p.is_file())
        out_bytes = sum(p.stat().st_size for p in (out / truth.log_id).rglob("*") if p.is_file())
        assert entry["status"] == "ok" and entry["error"] is None and entry["seconds"] > 0
        assert entry["input_bytes"] == in_bytes and entry["output_bytes"] == out_bytes
        assert isinstance(entry["warnings"], list) and entry["fingerprint"] == data["converter"]
    assert not list(out.glob(".*"))  # no temporary report or partial folder left


def _children(pid: int) -> list[int]:
    """Child pids of `pid` from /proc; threads and processes that end while being read are skipped."""
    import os

    out = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except FileNotFoundError:
        return out
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(c) for c in f.read().split()]
        except (FileNotFoundError, ProcessLookupError):
            continue
    return out


def test_a_run_killed_mid_log_is_completed_by_the_rerun(tmp_path):
    """SIGKILL a worker while a log is being written: that log fails, nothing looks finished, and the
    rerun converts it correctly."""
    import os
    import signal
    import subprocess
    import time

    from conftest import av2_args, av2_command, open_sequence, run_cli

    root = tmp_path / "root"
    truth = write_log(UPath(root / "val"), SynthConfig(seconds=1.0, seed=23, camera_fps=20, pictures=2, camera_scale=4))
    out = tmp_path / "out"
    proc = subprocess.Popen(
        av2_command(root, out, "--workers", "2"), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    deadline, workers = time.monotonic() + 60, []
    while not (workers and list(out.glob(f".{truth.log_id}.*partial"))) and time.monotonic() < deadline:
        time.sleep(0.02)
        workers = [w for server in _children(proc.pid) for w in _children(server)]
    assert workers, "no worker processes found"
    os.kill(workers[0], signal.SIGKILL)
    output, _ = proc.communicate(timeout=120)
    assert proc.returncode == 1, output
    assert f"FAIL  {truth.log_id}: WorkerDied: a worker process died" in output
    assert not (out / truth.log_id).exists() and not list(out.glob(f".{truth.log_id}.*partial"))
    rerun = run_cli(*av2_args(root, out))
    assert rerun.returncode == 0 and f"ok    {truth.log_id}" in rerun.stdout, rerun.stdout + rerun.stderr
    loader = open_sequence(out / truth.log_id, truth.log_id)
    assert loader.get_lidar_sensor("up_lidar").frames_count == len(truth.sweeps)
    assert sum(loader.get_camera_sensor(c).frames_count for c in loader.camera_ids) == truth.n_images


def test_shards_split_the_logs_and_keep_their_own_reports(two_logs, tmp_path):
    root, truths = two_logs
    out = tmp_path / "out"
    ids = sorted(t.log_id for t in truths)
    for index in (0, 1):
        result = run(root, out, "--shard", f"{index}/2")
        assert result.exit_code == 0 and "1 converted, 0 skipped" in result.output
        assert list(report(out, f"conversion-report-shard-{index}-of-2.json")["logs"]) == [ids[index]]
    assert all((out / log_id).is_dir() for log_id in ids)
    assert not (out / "conversion-report.json").exists()
    for bad in ("2/2", "x/2", "1"):
        result = run(root, out, "--shard", bad)
        assert result.exit_code == 2 and "--shard" in result.output


def test_one_log_per_worker_writes_the_same_bytes_as_workers_sharing_a_log(two_logs, tmp_path):
    """Two logs on two workers run as one job per log; a single log has its stores spread over them."""
    root, truths = two_logs
    one, two = tmp_path / "one", tmp_path / "two"
    for truth in truths:
        assert run(root, one, "--workers", "2", log_id=truth.log_id).exit_code == 0
    result = run(root, two, "--workers", "2")
    assert result.exit_code == 0 and "2 converted, 0 skipped, 0 failed" in result.output
    for truth in truths:
        files = sorted(p.name for p in (one / truth.log_id).iterdir())
        assert files == sorted(p.name for p in (two / truth.log_id).iterdir())
        for name in files:
            assert (one / truth.log_id / name).read_bytes() == (two / truth.log_id / name).read_bytes(), name
    assert {e["status"] for e in report(two)["logs"].values()} == {"ok"}
