"""--executor ray on a real local Ray cluster (started here, 127.0.0.1, 2 CPUs): same output as the
local executor, per-log failures reported, and a clear usage error without a cluster."""

from __future__ import annotations

import json
import subprocess

import pytest
from conftest import BIN, av2_args, av2_command, free_port, run_cli
from upath import UPath

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth.argoverse2 import SynthConfig, write_log


@pytest.fixture(scope="module")
def ray_address():
    port = free_port()
    start = [
        str(BIN / "ray"),
        "start",
        "--head",
        "--node-ip-address",
        "127.0.0.1",
        "--port",
        str(port),
        "--num-cpus",
        "2",
        "--include-dashboard",
        "false",
        "--object-store-memory",
        str(100 * 2**20),
        "--disable-usage-stats",
    ]
    subprocess.run(start, check=True, capture_output=True, timeout=180)
    try:
        yield f"127.0.0.1:{port}"
    finally:  # stopping takes ~6 s of waiting for its processes: the worker goes on meanwhile
        subprocess.Popen(
            [str(BIN / "ray"), "stop", "--force"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )


@pytest.fixture(scope="module")
def three_logs(tmp_path_factory):
    """Three short synthetic logs with images; the third has a corrupt JPEG."""
    root = tmp_path_factory.mktemp("ray")
    truths = [
        write_log(UPath(root / "val"), SynthConfig(seconds=0.3, seed=s, camera_fps=5, camera_scale=4))
        for s in (31, 32, 33)
    ]
    log_dir = UPath(truths[2].log_dir)
    bad = av2.image_path(log_dir, "ring_rear_left", int(av2.list_image_timestamps_ns(log_dir, "ring_rear_left")[0]))
    bad.write_bytes(b"not a jpeg")
    return root, truths, bad


def convert(root, out, *extra):
    return subprocess.run(av2_command(root, out, *extra), capture_output=True, text=True, timeout=600)


def test_ray_executor_writes_what_the_local_executor_writes(ray_address, three_logs, tmp_path):
    root, truths, bad = three_logs
    local = run_cli(*av2_args(root, tmp_path / "local", "--workers", "2"))
    on_ray = convert(root, tmp_path / "ray", "--executor", "ray", "--ray-address", ray_address)
    for result in (local, on_ray):
        assert result.returncode == 1, result.stdout + result.stderr  # the corrupt log fails, the others do not
        assert "2 converted, 0 skipped, 1 failed" in result.stdout
    fail = [line for line in on_ray.stdout.splitlines() if line.startswith("FAIL")]
    assert fail == [f"FAIL  {truths[2].log_id}: {bad}: not a JPEG file (missing SOI marker)"], on_ray.stdout
    for truth in truths[:2]:
        names = sorted(p.name for p in (tmp_path / "local" / truth.log_id).iterdir())
        assert names == sorted(p.name for p in (tmp_path / "ray" / truth.log_id).iterdir())
        for name in names:
            a = (tmp_path / "local" / truth.log_id / name).read_bytes()
            assert a == (tmp_path / "ray" / truth.log_id / name).read_bytes(), name
    assert not (tmp_path / "ray" / truths[2].log_id).exists()
    assert sorted(p.name for p in (tmp_path / "ray").iterdir() if p.name.startswith(".")) == []
    report = json.loads((tmp_path / "ray" / "conversion-report.json").read_text())["logs"]
    assert {log: e["status"] for log, e in report.items()} == {
        truths[0].log_id: "ok",
        truths[1].log_id: "ok",
        truths[2].log_id: "failed",
    }
    assert report[truths[2].log_id]["error"]["file"] == str(bad)
    assert all(report[t.log_id]["output_bytes"] > 0 and report[t.log_id]["seconds"] > 0 for t in truths[:2])
    rerun = convert(root, tmp_path / "ray", "--executor", "ray", "--ray-address", ray_address)
    assert "0 converted, 2 skipped, 1 failed" in rerun.stdout, rerun.stdout + rerun.stderr


def test_no_cluster_at_the_address_is_a_usage_error(three_logs, tmp_path):
    root, _, _ = three_logs
    result = run_cli(
        *av2_args(root, tmp_path / "out", "--executor", "ray", "--ray-address", f"127.0.0.1:{free_port()}")
    )
    assert result.returncode == 2 and "--ray-address 127.0.0.1:" in result.stderr, result.stderr
    assert not (tmp_path / "out").exists()
