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


def run(root, out, *extra):
    args = ["--no-progress", "--root-dir", str(root), "--output-dir", str(out), *extra]
    return CliRunner().invoke(cli, [*args, "argoverse2-v4", "--split", "val"], catch_exceptions=False)


def report(out) -> dict:
    return json.loads((out / "conversion-report.json").read_text())


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
    assert result.exit_code == 0 and "2 converted, 0 skipped" in result.output
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
    assert f"skip  {truths[0].log_id}: not a failure of the last run" in result.output
    assert f"ok    {truths[1].log_id}" in result.output
    assert store_mtimes(out, truths[0].log_id) == first_good
    assert {e["status"] for e in report(out)["logs"].values()} == {"ok"}
    assert "exclude each other" in run(src, out, "--retry-failed", "--overwrite").output


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
