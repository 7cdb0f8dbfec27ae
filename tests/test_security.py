"""Names from the data never become paths outside the output folder, and YAML is loaded safely."""

from __future__ import annotations

import shutil

import pyarrow as pa
import pyarrow.feather as feather
import pytest
from click.testing import CliRunner
from upath import UPath

from ncore_convert.cli import cli
from ncore_convert.errors import SourceError
from ncore_convert.run.runner import convert_one
from ncore_convert.sources import opencood as ocd
from ncore_convert.sources.noise_config import read_noise_config
from ncore_convert.synth.argoverse2 import SynthConfig, write_log

UNSAFE = ["..", "../escape", "a/b", ".hidden", "name with space", "x" * 129, "-leading-dash"]


def run(*args):
    return CliRunner().invoke(cli, ["--no-progress", *args], catch_exceptions=False)


@pytest.fixture(scope="module")
def tbv_log(tmp_path_factory):
    root = tmp_path_factory.mktemp("tbv-security")
    truth = write_log(UPath(root / "tbv"), SynthConfig(seconds=0.5, seed=12, camera_fps=0, tbv=True))
    return root / "tbv", truth.log_id


def test_unsafe_folder_names_in_a_split_are_refused_before_anything_is_written(tmp_path):
    for dataset, split in (("argoverse2-v4", ["--split", "val"]), ("opv2v-v4", ["--split", "test"])):
        folder = tmp_path / dataset / split[1]
        (folder / "name with space").mkdir(parents=True)
        out = tmp_path / f"out-{dataset}"
        result = run("--root-dir", str(tmp_path / dataset), "--output-dir", str(out), dataset, *split)
        assert result.exit_code == 2, result.output
        assert f"{folder}: " in result.output and "'name with space' is not a safe name" in result.output
        assert not out.exists()


def test_a_log_id_outside_the_split_is_not_found(tmp_path, tbv_log):
    root, log_id = tbv_log
    out = tmp_path / "out"
    result = run("--root-dir", str(root), "--output-dir", str(out), "tbv-v4", "--log-id", f"../tbv/{log_id}")
    assert result.exit_code == 2 and "not found" in result.output
    assert not out.exists()


def test_a_sensor_name_that_would_escape_fails_the_log_naming_the_calibration(tmp_path, tbv_log):
    """TbV takes its camera names from calibration/intrinsics.feather: they become store file names."""
    base, log_id = tbv_log
    root = tmp_path / "root"
    shutil.copytree(base / log_id, root / log_id)
    intrinsics = root / log_id / "calibration" / "intrinsics.feather"
    table = feather.read_table(intrinsics)
    names = table["sensor_name"].to_pylist()
    names[1] = "../../escaped"
    feather.write_feather(table.set_column(0, "sensor_name", pa.array(names)), intrinsics)
    out = tmp_path / "out"
    result = run("--root-dir", str(root), "--output-dir", str(out), "tbv-v4")
    assert result.exit_code == 1
    assert f"{intrinsics}: sensor_name '../../escaped' is not a safe name" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "root"]  # nothing escaped
    assert [p.name for p in out.iterdir()] == ["conversion-report.json"]


@pytest.mark.parametrize("log_id", UNSAFE)
def test_the_runner_refuses_unsafe_log_ids(tmp_path, log_id):
    out = tmp_path / "deep" / "out"
    out.mkdir(parents=True)
    called = []
    result = convert_one(UPath(out), log_id, lambda *args: called.append(args), show_progress=False)
    assert not result.ok and "is not a safe output folder name" in result.error and not called
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == ["deep", "deep/out"]


YAML_ATTACKS = [
    "a: !!python/object/apply:os.system ['touch {marker}']\n",
    "a: !!python/object/new:subprocess.Popen [['touch', '{marker}']]\n",
    "a: !!python/name:os.system\n",
]


@pytest.mark.parametrize("text", YAML_ATTACKS)
def test_yaml_tags_construct_no_objects(tmp_path, text):
    """Frame YAMLs and noise configs: Python tags are refused with a SourceError; nothing runs."""
    marker = tmp_path / "marker"
    frame = tmp_path / "000001.yaml"
    frame.write_text(text.format(marker=marker))
    with pytest.raises(SourceError, match="000001.yaml: not valid YAML"):
        ocd.read_agent_frame(UPath(tmp_path), "000001")
    config = tmp_path / "noise.yaml"
    config.write_text("wild_setting:\n  " + text.format(marker=marker))
    with pytest.raises(SourceError, match="noise.yaml: not valid YAML"):
        read_noise_config(UPath(config))
    assert not marker.exists()
