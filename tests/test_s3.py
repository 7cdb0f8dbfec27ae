"""Object storage: read a log from a bucket and write its sequence to a bucket on a real
S3-compatible server (moto's server mode on 127.0.0.1), through fsspec/s3fs; and runs that share a
bucket output (claims and the report by conditional writes)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import pytest
from conftest import av2_args, av2_command, run_cli
from upath import UPath

from ncore_convert.synth.argoverse2 import SynthConfig, write_log


def convert(env, root: str, out: str, *extra):
    return subprocess.run(av2_command(root, out, *extra), capture_output=True, text=True, timeout=600, env=env)


def test_a_log_in_a_bucket_converts_into_a_bucket_as_it_does_locally(s3_env, tmp_path):
    import s3fs
    from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4

    truth = write_log(UPath(tmp_path / "src" / "val"), SynthConfig(seconds=0.3, seed=41, camera_fps=5, camera_scale=4))
    fs = s3fs.S3FileSystem()
    fs.mkdir("datasets")
    fs.mkdir("converted")
    fs.put(str(tmp_path / "src" / "val") + "/", "datasets/av2/val/", recursive=True)
    assert len(fs.find(f"datasets/av2/val/{truth.log_id}")) == sum(
        1 for p in Path(truth.log_dir.path).rglob("*") if p.is_file()
    )

    local = run_cli(*av2_args(tmp_path / "src", tmp_path / "out"))  # no bucket: in this process
    remote = convert(s3_env, "s3://datasets/av2", "s3://converted/v4", "--workers", "1")
    for result in (local, remote):
        assert result.returncode == 0 and "1 converted, 0 skipped, 0 failed" in result.stdout, result.stderr

    fs.invalidate_cache()
    names = sorted(p.name for p in (tmp_path / "out" / truth.log_id).iterdir())
    assert sorted(Path(p).name for p in fs.ls(f"converted/v4/{truth.log_id}")) == names
    for name in names:
        local_bytes = (tmp_path / "out" / truth.log_id / name).read_bytes()
        assert fs.cat_file(f"converted/v4/{truth.log_id}/{name}") == local_bytes, name
    assert not [p for p in fs.ls("converted/v4") if Path(p).name.startswith(".")]

    report = json.loads(fs.cat_file("converted/v4/conversion-report.json"))["logs"][truth.log_id]
    assert report["status"] == "ok" and report["error"] is None
    assert report["input_bytes"] == sum(p.stat().st_size for p in Path(truth.log_dir.path).rglob("*") if p.is_file())
    assert report["output_bytes"] == sum(len(fs.cat_file(f"converted/v4/{truth.log_id}/{n}")) for n in names)

    seq = UPath(f"s3://converted/v4/{truth.log_id}/{truth.log_id}.json")
    loader = SequenceLoaderV4(SequenceComponentGroupsReader([seq]))
    assert loader.get_lidar_sensor("up_lidar").frames_count == len(truth.sweeps)
    assert sum(loader.get_camera_sensor(c).frames_count for c in loader.camera_ids) == truth.n_images

    rerun = convert(s3_env, "s3://datasets/av2", "s3://converted/v4")
    assert rerun.returncode == 0 and "0 converted, 1 skipped, 0 failed" in rerun.stdout, rerun.stderr


def test_a_missing_bucket_prefix_is_a_usage_error(s3_env, tmp_path):
    result = convert(s3_env, "s3://no-such-bucket/av2", str(tmp_path / "out"))
    assert result.returncode == 2 and "--root-dir s3://no-such-bucket/av2: folder not found" in result.stderr


def _ok_logs(output: str) -> list[str]:
    return re.findall(r"^ok    ([0-9a-f-]+):", output, flags=re.M)


@pytest.fixture(scope="module")
def three_logs(tmp_path_factory):
    """Three small local logs (0.3 s, images of one camera) for runs that share a bucket output."""
    root = tmp_path_factory.mktemp("s3-shared")
    cameras = ("ring_front_center",)
    configs = [
        SynthConfig(seconds=0.3, seed=s, camera_fps=10, pictures=2, image_cameras=cameras, camera_scale=4)
        for s in (43, 44, 45)
    ]
    return root, sorted(write_log(UPath(root / "val"), config).log_id for config in configs)


@pytest.mark.parametrize("runs", [2, 3])
def test_runs_sharing_a_bucket_output_convert_every_log_once(s3_env, three_logs, runs):
    """Two and three runs started together on one s3:// output: claims by conditional writes
    (If-None-Match), the report merged by writes conditional on its ETag."""
    import s3fs

    root, ids = three_logs
    bucket = f"shared-{runs}"
    s3fs.S3FileSystem().mkdir(bucket)
    command = av2_command(root, f"s3://{bucket}/v4", "--workers", "1")
    procs = [subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=s3_env) for _ in range(runs)]
    outputs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0] * runs, outputs
    assert sorted(log for output in outputs for log in _ok_logs(output)) == ids, outputs
    fs = s3fs.S3FileSystem()
    logs = json.loads(fs.cat_file(f"{bucket}/v4/conversion-report.json"))["logs"]
    assert {k: v["status"] for k, v in logs.items()} == dict.fromkeys(ids, "ok")
    assert sorted(Path(p).name for p in fs.ls(f"{bucket}/v4")) == sorted([*ids, "conversion-report.json"])


def test_a_run_killed_while_it_holds_a_bucket_claim_is_taken_over(s3_env, three_logs):
    import s3fs

    root, ids = three_logs
    fs = s3fs.S3FileSystem()
    fs.mkdir("killed")
    proc = subprocess.Popen(av2_command(root, "s3://killed/v4", "--workers", "1"), env=s3_env)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        fs.invalidate_cache()
        if fs.exists("killed/v4") and [p for p in fs.ls("killed/v4") if p.endswith(".claim")]:
            break
        time.sleep(0.05)
    else:
        pytest.fail("no claim object appeared")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    rerun = convert(s3_env, str(root), "s3://killed/v4")
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert len(_ok_logs(rerun.stdout)) + rerun.stdout.count("skip  ") == len(ids)
    fs.invalidate_cache()
    assert sorted(Path(p).name for p in fs.ls("killed/v4")) == sorted([*ids, "conversion-report.json"])
