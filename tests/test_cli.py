"""The command line: conventions, help, usage errors, bad input, output layout and profiles."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
from click.testing import CliRunner
from conftest import open_sequence
from upath import UPath

from ncore_convert.cli import cli
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth.argoverse2 import SynthConfig, write_log


@pytest.fixture(scope="module")
def small_root(tmp_path_factory):
    """A 0.3 s synthetic log without images."""
    root = tmp_path_factory.mktemp("cli")
    truth = write_log(UPath(root / "val"), SynthConfig(seconds=0.3, seed=5, camera_fps=0))
    return root, truth


def run(*args):
    return CliRunner().invoke(cli, ["--no-progress", *args], catch_exceptions=False)


def test_help_documents_every_option_with_its_default():
    import click

    def commands(group, path):
        yield path, group
        for name, sub in getattr(group, "commands", {}).items():
            yield from commands(sub, [*path, name])

    for path, command in commands(cli, []):
        result = CliRunner().invoke(cli, [*path, "--help"])
        assert result.exit_code == 0 and "Usage:" in result.output
        ctx = click.Context(command, info_name=command.name, show_default=True)
        for param in command.params:
            if not isinstance(param, click.Option) or param.name in ("help", "version"):
                continue
            _, text = param.get_help_record(ctx)
            assert param.help, f"{path} {param.name} has no help"
            assert "[default:" in text or param.required, f"{path} {param.name} shows no default"
            assert param.opts[0] in result.output


def test_conversion_writes_the_documented_layout(small_root, tmp_path):
    root, truth = small_root
    out = tmp_path / "out"
    result = run("--root-dir", str(root), "--output-dir", str(out), "argoverse2-v4", "--split", "val")
    assert result.exit_code == 0, result.output
    assert f"ok    {truth.log_id}: 3 sweeps" in result.output
    files = sorted(p.name for p in (out / truth.log_id).iterdir())
    assert files == sorted(
        [f"{truth.log_id}.json"]
        + [f"{truth.log_id}.ncore4{suffix}.zarr.itar" for suffix in ("", "-up_lidar", "-down_lidar")]
    )
    assert not list(out.glob(".*partial"))


@pytest.mark.parametrize(
    "store_type,profile,expected",
    [
        ("directory", "default", [".ncore4.zarr"]),
        (
            "itar",
            "separate-all",
            [".ncore4-poses.zarr.itar", ".ncore4-cuboids.zarr.itar", ".ncore4-up_lidar.zarr.itar"],
        ),
    ],
)
def test_store_types_and_profiles_open_with_the_default_loader(small_root, tmp_path, store_type, profile, expected):
    root, truth = small_root
    result = run(
        "--root-dir", str(root), "--output-dir", str(tmp_path), "--lidar-id", "up_lidar",
        "argoverse2-v4", "--split", "val", "--store-type", store_type, "--profile", profile,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    names = {p.name for p in (tmp_path / truth.log_id).iterdir()}
    for suffix in expected:
        assert truth.log_id + suffix in names
    loader = open_sequence(tmp_path / truth.log_id, truth.log_id)
    assert loader.lidar_ids == ["up_lidar"] and loader.camera_ids == []
    assert len(list(loader.get_cuboid_track_observations())) == truth.n_cuboids


def test_no_sequence_meta_writes_no_json(small_root, tmp_path):
    root, truth = small_root
    result = run("--root-dir", str(root), "--output-dir", str(tmp_path), "--no-lidars",
                 "argoverse2-v4", "--split", "val", "--no-sequence-meta")  # fmt: skip
    assert result.exit_code == 0, result.output
    assert not (tmp_path / truth.log_id / f"{truth.log_id}.json").exists()


@pytest.mark.parametrize(
    "args,message",
    [
        (["argoverse2-v4", "--split", "val"], "--root-dir is required"),
        (["--root-dir", "/nonexistent", "--output-dir", "x", "argoverse2-v4", "--split", "val"], "directory not found"),
        (
            ["--root-dir", "{root}", "--output-dir", "x", "argoverse2-v4", "--split", "val", "--log-id", "nope"],
            "not found",
        ),
        (
            ["--root-dir", "{root}", "--output-dir", "x", "--camera-id", "fisheye", "argoverse2-v4", "--split", "val"],
            "unknown camera",
        ),
        (
            ["--root-dir", "{root}", "--output-dir", "x", "argoverse2-v4", "--split", "train"],
            "split directory not found",
        ),
    ],
)
def test_usage_errors_exit_2(small_root, args, message):
    root, _ = small_root
    result = run(*[a.format(root=root) for a in args])
    assert result.exit_code == 2
    assert message in result.output


def _copy_log(truth, dest):
    import shutil

    shutil.copytree(truth.log_dir.path, dest / "val" / truth.log_id)
    return dest / "val" / truth.log_id


@pytest.mark.parametrize(
    "damage,cause",
    [
        ("drop_offset_ns", "offset_ns"),
        ("truncate_sweep", "not a readable feather table"),
        ("wrong_pose_dtype", "column 'tx_m' has type float"),
        ("no_calibration", "file not found"),
        ("offset_beyond_log", "point times reach outside the log's time range"),
    ],
)
def test_bad_input_fails_that_log_with_one_line_naming_the_file(small_root, tmp_path, damage, cause):
    _, truth = small_root
    log_dir = _copy_log(truth, tmp_path / "root")
    sweep = av2.sweep_path(UPath(log_dir), truth.sweeps[1].timestamp_ns)
    if damage == "drop_offset_ns":
        feather.write_feather(feather.read_table(sweep.path).drop_columns(["offset_ns"]), sweep.path)
        bad = sweep.path
    elif damage == "truncate_sweep":
        data = open(sweep.path, "rb").read()
        open(sweep.path, "wb").write(data[: len(data) // 2])
        bad = sweep.path
    elif damage == "wrong_pose_dtype":
        bad = log_dir / "city_SE3_egovehicle.feather"
        table = feather.read_table(bad)
        table = table.set_column(table.schema.get_field_index("tx_m"), "tx_m", table["tx_m"].cast(pa.float32()))
        feather.write_feather(table, bad)
    elif damage == "offset_beyond_log":  # a middle sweep whose points claim to fire 2 s later
        table = feather.read_table(sweep.path)
        late = pa.array(table["offset_ns"].to_numpy() + 2_000_000_000, pa.int32())
        table = table.set_column(table.schema.get_field_index("offset_ns"), "offset_ns", late)
        feather.write_feather(table, sweep.path)
        bad = sweep.path
    else:
        bad = log_dir / "calibration" / "egovehicle_SE3_sensor.feather"
        bad.unlink()
    out = tmp_path / "out"
    result = run("--root-dir", str(tmp_path / "root"), "--output-dir", str(out), "argoverse2-v4", "--split", "val")
    assert result.exit_code == 1
    fail = [line for line in result.output.splitlines() if line.startswith("FAIL")]
    assert len(fail) == 1 and str(bad) in fail[0] and cause in fail[0], result.output
    assert not (out / truth.log_id).exists() and not list(out.glob(".*"))


def test_one_failing_log_does_not_stop_the_others(small_root, tmp_path):
    _, truth = small_root
    root = tmp_path / "root"
    _copy_log(truth, root)
    broken = root / "val" / "00000000-0000-3000-8000-000000000000"
    broken.mkdir()
    result = run("--root-dir", str(root), "--output-dir", str(tmp_path / "out"), "argoverse2-v4", "--split", "val")
    assert result.exit_code == 1
    assert "1 converted, 0 skipped, 1 failed" in result.output
    assert (tmp_path / "out" / truth.log_id / f"{truth.log_id}.json").exists()


def test_synth_command_writes_a_log(tmp_path):
    result = run("synth", "argoverse2", "--out", str(tmp_path), "--seconds", "0.2", "--camera-fps", "0")
    assert result.exit_code == 0, result.output
    (log_dir,) = list(tmp_path.iterdir())
    assert len(av2.list_sweep_timestamps_ns(UPath(log_dir))) == 2
    assert np.all(np.diff(av2.read_city_SE3_ego(UPath(log_dir))[0]) > 0)
