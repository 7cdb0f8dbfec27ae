"""The command line: conventions, help, usage errors, bad input, output layout and profiles."""

from __future__ import annotations

import json

import numpy as np
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
        "--root-dir",
        str(root),
        "--output-dir",
        str(tmp_path),
        "--lidar-id",
        "up_lidar",
        "argoverse2-v4",
        "--split",
        "val",
        "--store-type",
        store_type,
        "--profile",
        profile,
    )
    assert result.exit_code == 0, result.output
    names = {p.name for p in (tmp_path / truth.log_id).iterdir()}
    for suffix in expected:
        assert truth.log_id + suffix in names
    loader = open_sequence(tmp_path / truth.log_id, truth.log_id)
    assert loader.lidar_ids == ["up_lidar"] and loader.camera_ids == []
    assert len(list(loader.get_cuboid_track_observations())) == truth.n_cuboids


def test_no_sequence_meta_writes_no_json(small_root, tmp_path):
    root, truth = small_root
    result = run(
        "--root-dir",
        str(root),
        "--output-dir",
        str(tmp_path),
        "--no-lidars",
        "argoverse2-v4",
        "--split",
        "val",
        "--no-sequence-meta",
    )
    assert result.exit_code == 0, result.output
    assert not (tmp_path / truth.log_id / f"{truth.log_id}.json").exists()


@pytest.mark.parametrize(
    "args,message",
    [
        (["argoverse2-v4", "--split", "val"], "--root-dir is required"),
        (["--root-dir", "/nonexistent", "--output-dir", "x", "argoverse2-v4", "--split", "val"], "folder not found"),
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
            "split folder not found",
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


def _truncate_sweep(log_dir, timestamp_ns):
    sweep = av2.sweep_path(UPath(log_dir), timestamp_ns)
    data = open(sweep.path, "rb").read()
    open(sweep.path, "wb").write(data[: len(data) // 2])
    return sweep.path


def test_a_failure_is_one_line_and_its_traceback_needs_verbose(small_root, tmp_path):
    """Bad input prints one FAIL line naming the file and the cause; --verbose adds the traceback."""
    _, truth = small_root
    bad = _truncate_sweep(_copy_log(truth, tmp_path / "root"), truth.sweeps[1].timestamp_ns)
    for verbose in ([], ["--verbose"]):
        args = ["--root-dir", str(tmp_path / "root"), "--output-dir", str(tmp_path / "out"), *verbose]
        result = run(*args, "argoverse2-v4", "--split", "val")
        assert result.exit_code == 1
        fail = [line for line in result.output.splitlines() if line.startswith("FAIL")]
        assert fail == [f"FAIL  {truth.log_id}: {bad}: not a readable feather table" + fail[0].split("table", 1)[1]]
        assert ("Traceback (most recent call last)" in result.output) == bool(verbose), result.output
        assert not list((tmp_path / "out").glob(f"*{truth.log_id}*"))


def test_three_good_logs_and_one_damaged_give_three_sequences_and_one_failure(tmp_path):
    root = tmp_path / "root"
    logs = [write_log(UPath(root / "val"), SynthConfig(seconds=0.3, seed=s, camera_fps=0)) for s in (21, 22, 23, 24)]
    damaged = logs[2]
    bad = _truncate_sweep(damaged.log_dir.path, damaged.sweeps[0].timestamp_ns)
    out = tmp_path / "out"
    result = run("--root-dir", str(root), "--output-dir", str(out), "--workers", "2", "argoverse2-v4", "--split", "val")
    assert result.exit_code == 1
    assert "3 converted, 0 skipped, 1 failed" in result.output
    report = json.loads((out / "conversion-report.json").read_text())["logs"]
    assert report[damaged.log_id]["status"] == "failed" and report[damaged.log_id]["error"]["file"] == str(bad)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["conversion-report.json"] + [t.log_id for t in logs if t is not damaged]
    )
    for truth in logs:
        if truth is not damaged:
            assert report[truth.log_id]["status"] == "ok" and report[truth.log_id]["validation"]["ok"]
            loader = open_sequence(out / truth.log_id, truth.log_id)
            assert loader.get_lidar_sensor("up_lidar").frames_count == len(truth.sweeps)
            assert len(list(loader.get_cuboid_track_observations())) == truth.n_cuboids


def test_synth_command_writes_a_log(tmp_path):
    result = run("synth", "argoverse2", "--out", str(tmp_path), "--seconds", "0.2", "--camera-fps", "0")
    assert result.exit_code == 0, result.output
    assert [p.name for p in tmp_path.iterdir()] == ["val"]  # --out is the dataset root, the split below it
    (log_dir,) = list((tmp_path / "val").iterdir())
    assert len(av2.list_sweep_timestamps_ns(UPath(log_dir))) == 2
    assert np.all(np.diff(av2.read_ego_poses(UPath(log_dir))[0]) > 0)


def test_an_output_folder_that_cannot_be_made_is_a_usage_error(small_root, tmp_path):
    """A file where the output folder should be, or in its path: exit 2, one error line naming
    ``--output-dir``, why, and the fix (before issue 73: exit 1, "File exists; run stopped")."""
    root, _ = small_root
    (tmp_path / "a-file").write_text("a file where the output folder should be")
    for out in (tmp_path / "a-file", tmp_path / "a-file" / "out"):
        result = run("--root-dir", str(root), "--output-dir", str(out), "argoverse2-v4", "--split", "val")
        assert result.exit_code == 2 and "Traceback" not in result.output
        assert result.output.strip().splitlines()[-1] == (
            f"Error: --output-dir {out}: the output folder cannot be made (a file is in the way);"
            " give a folder you can write"
        )


def test_group_options_after_the_dataset_command_have_their_effect(small_root, tmp_path):
    """Group options given after the dataset command (``--no-validate``, ``--workers``, even the
    roots, ``--opt=value`` too) are taken as if given before it: the same run, never "No such
    option" with an unrelated suggestion."""
    root, truth = small_root
    before = ["--root-dir", str(root), "--output-dir", str(tmp_path / "a"), "--no-validate", "--workers", "1"]
    after = ["--root-dir", str(root), f"--output-dir={tmp_path / 'b'}", "--no-validate", "--workers", "1"]
    for result in (run(*before, "argoverse2-v4", "--split", "val"), run("argoverse2-v4", "--split", "val", *after)):
        assert result.exit_code == 0, result.output
        assert f"ok    {truth.log_id}" in result.output and "validated" not in result.output, result.output
    assert sorted(p.name for p in (tmp_path / "a" / truth.log_id).iterdir()) == sorted(
        p.name for p in (tmp_path / "b" / truth.log_id).iterdir()
    )


def test_help_says_where_the_group_options_go():
    """The dataset commands' usage lines and help name the group options; the top-level help says
    they come first."""
    top = CliRunner().invoke(cli, ["--help"], prog_name="ncore-convert").output
    assert "group options: they come before the dataset command" in " ".join(top.split())
    for command in ("argoverse2-v4", "tbv-v4", "opv2v-v4", "v2xset-v4"):
        text = " ".join(CliRunner().invoke(cli, [command, "--help"], prog_name="ncore-convert").output.split())
        assert f"Usage: ncore-convert --root-dir R --output-dir O [GROUP OPTIONS] {command} [OPTIONS]" in text
        assert all(option in text for option in ("--root-dir", "--output-dir", "--workers")), command


@pytest.mark.parametrize(
    "case",
    ["split folder as root", "opv2v tree to argoverse2-v4", "av2 tree to opv2v-v4", "unknown log", "output is /proc"],
)
def test_a_newcomers_mistake_is_a_usage_error_that_names_the_fix(small_root, tmp_path, case):
    """Each mistake exits 2 with an error line that says what to give instead, and leaves no
    output folder: the split folder given as the root (its parent), the real OPV2V agent's tree
    given to ``argoverse2-v4`` and an AV2 tree to ``opv2v-v4`` (the command to use), an unknown
    ``--log-id`` (the ids there), an output folder that cannot be made (which option, and why)."""
    from conftest import find_opv2v_sample

    root, truth = small_root
    out = tmp_path / "out"
    args, fix = {
        "split folder as root": (
            [str(root / "val"), str(out), "argoverse2-v4", "--split", "val"],
            f"it is the split folder itself: give its parent, --root-dir {root}",
        ),
        "opv2v tree to argoverse2-v4": (
            [str(find_opv2v_sample()), str(out), "argoverse2-v4", "--split", "val"],
            "is an OPV2V/V2XSet root: convert it with opv2v-v4 or v2xset-v4",
        ),
        "av2 tree to opv2v-v4": (
            [str(root), str(out), "opv2v-v4", "--split", "test"],
            "is an Argoverse 2 Sensor root: convert it with argoverse2-v4",
        ),
        "unknown log": (
            [str(root), str(out), "argoverse2-v4", "--split", "val", "--log-id", "nope"],
            f"log(s) not found under {root / 'val'}: nope; there: {truth.log_id}",
        ),
        "output is /proc": (
            [str(root), "/proc/self", "argoverse2-v4", "--split", "val"],
            "--output-dir /proc/self: the output folder cannot be made (No such file or directory)",
        ),
    }[case]
    result = run("--root-dir", args[0], "--output-dir", *args[1:])
    assert result.exit_code == 2, result.output
    error = " ".join(result.output.split("Error: ", 1)[1].split())
    assert fix in error, error
    assert not out.exists()
