"""``validate``: converted sequences pass; sequences corrupted on purpose, through the low-level zarr
API, fail the check that names the fault."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import zarr
from conftest import synth_and_convert
from ncore.impl.data.stores import consolidate_compressed_metadata
from upath import UPath

from ncore_convert.converters.argoverse2 import Argoverse2Options
from ncore_convert.converters.opencood import OpenCoodOptions, convert_scenario
from ncore_convert.synth.argoverse2 import SynthConfig
from ncore_convert.synth.opencood import SynthConfig as OpenCoodConfig
from ncore_convert.synth.opencood import write_dataset
from ncore_convert.validate import find_sequences, validate_sequence


@pytest.fixture(scope="module")
def directory_log(tmp_path_factory):
    """A 0.6 s synthetic AV2 log (6 sweeps per lidar, no images) in one directory store."""
    options = Argoverse2Options(split="val", store_type="directory", profile="default", camera_ids=())
    return synth_and_convert(
        tmp_path_factory.mktemp("validate"), SynthConfig(seconds=0.6, seed=4, camera_fps=0), options
    )


def failed(report) -> dict[str, str]:
    return {c.name: c.detail for c in report.checks if not c.ok}


def corrupt(directory_log, tmp_path: Path, edit) -> dict[str, str]:
    """Copy the sequence, apply ``edit(group)`` to its zarr store, re-consolidate, validate; the failures."""
    seq_dir = tmp_path / directory_log.seq_dir.name
    shutil.copytree(directory_log.seq_dir, seq_dir)
    (store_path,) = seq_dir.glob("*.ncore4.zarr")
    store = zarr.DirectoryStore(str(store_path))
    edit(zarr.open_group(store, mode="r+"))
    consolidate_compressed_metadata(store)
    (meta,) = seq_dir.glob("*.json")
    return failed(validate_sequence(UPath(meta)))


def frame_keys(group, lidar: str) -> list[str]:
    return sorted(group[f"lidars/{lidar}/frames"].group_keys(), key=int)


def test_the_uncorrupted_copy_passes(directory_log, tmp_path):
    assert corrupt(directory_log, tmp_path, lambda g: None) == {}


def test_a_flipped_extrinsic_empties_the_cuboids(directory_log, tmp_path):
    def flip(group):
        attrs = dict(group["poses/default/static_poses"].attrs)
        pose = np.array(attrs["('up_lidar', 'rig')"]["pose"])
        pose[:3, :3] = pose[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # upside down
        attrs["('up_lidar', 'rig')"]["pose"] = pose.tolist()
        group["poses/default/static_poses"].attrs.put(attrs)

    failures = corrupt(directory_log, tmp_path, flip)
    assert list(failures) == ["lidar up_lidar: cuboids hold points"], failures


def test_a_shifted_timestamp_leaves_points_outside_their_frame(directory_log, tmp_path):
    def shift(group):
        key = frame_keys(group, "down_lidar")[2]
        t = group[f"lidars/down_lidar/frames/{key}/ray_bundle/timestamp_us"]
        t[:] = t[:] + np.uint64(30_000)

    failures = corrupt(directory_log, tmp_path, shift)
    assert "lidar down_lidar: point times within frames" in failures, failures
    assert all(name.startswith("lidar down_lidar") for name in failures)


def test_a_dropped_frame_breaks_the_frame_spacing(directory_log, tmp_path):
    def drop(group):
        frames = group["lidars/up_lidar/frames"]
        key = frame_keys(group, "up_lidar")[3]
        del frames[key]  # the frame's data and its entry in the frame list
        frames.attrs["frames_timestamps_us"] = [r for r in frames.attrs["frames_timestamps_us"] if r[1] != int(key)]

    failures = corrupt(directory_log, tmp_path, drop)
    assert list(failures) == ["lidar up_lidar: frame spacing"], failures
    assert "a dropped or shifted frame" in failures["lidar up_lidar: frame spacing"]


def test_a_listed_frame_without_data_is_unreadable(directory_log, tmp_path):
    def drop_data(group):
        del group["lidars/down_lidar/frames"][frame_keys(group, "down_lidar")[1]]

    failures = corrupt(directory_log, tmp_path, drop_data)
    assert list(failures) == ["lidar down_lidar: frames readable"], failures


def test_a_non_unit_direction_is_caught(directory_log, tmp_path):
    def stretch(group):
        key = frame_keys(group, "up_lidar")[1]
        d = group[f"lidars/up_lidar/frames/{key}/ray_bundle/direction"]
        values = d[:]
        values[7] *= 1.01
        d[:] = values

    failures = corrupt(directory_log, tmp_path, stretch)
    assert list(failures) == ["lidar up_lidar: unit directions"], failures


def test_validate_passes_on_the_synthetic_and_real_conversions(synth_log, real_log):
    for converted in (synth_log, real_log):
        (meta,) = converted.seq_dir.glob("*.json")
        report = validate_sequence(UPath(meta))
        assert report.ok, failed(report)
        names = [c.name for c in report.checks]
        assert "world_global in the pose graph" in names
        assert any(n.endswith("cuboids hold points") for n in names)


@pytest.mark.parametrize("layout", ["agents", "scenario"])
def test_validate_passes_on_opv2v_and_v2xset_conversions(tmp_path, layout):
    config = OpenCoodConfig(dataset="v2xset", frames=4, seed=6, cavs=2, infrastructure=True, lidar_columns=90)
    (truth,) = write_dataset(UPath(tmp_path / "src"), config)
    out = tmp_path / "out" / truth.scenario
    convert_scenario(UPath(tmp_path / "src"), UPath(out), truth.scenario,
                     OpenCoodOptions(dataset="v2xset", split=config.split, layout=layout))  # fmt: skip
    sequences = find_sequences(UPath(tmp_path / "out"))
    assert len(sequences) == (len(truth.agents) if layout == "agents" else 1)
    for meta in sequences:
        report = validate_sequence(meta)
        assert report.ok, failed(report)
        assert json.loads(json.dumps(report.to_dict()))["ok"] is True


def test_the_validate_command_prints_failures_writes_json_and_exits_non_zero(directory_log, tmp_path):
    from click.testing import CliRunner

    from ncore_convert.cli import cli

    good = CliRunner().invoke(cli, ["validate", str(directory_log.seq_dir), "--json", str(tmp_path / "good.json")])
    assert good.exit_code == 0 and "1 sequence(s) passed, 0 failed" in good.output
    assert json.loads((tmp_path / "good.json").read_text())[0]["ok"] is True
    bad_dir = tmp_path / "bad"
    corrupt(directory_log, bad_dir, lambda g: g[f"lidars/up_lidar/frames/{frame_keys(g, 'up_lidar')[0]}"
                                              "/ray_bundle/direction"].__setitem__((0, 0), 3.0))  # fmt: skip
    bad = CliRunner().invoke(cli, ["validate", str(bad_dir), "--json", str(tmp_path / "bad.json")])
    assert bad.exit_code == 1 and "FAIL" in bad.output and "lidar up_lidar: unit directions" in bad.output
    report = json.loads((tmp_path / "bad.json").read_text())[0]
    assert report["ok"] is False and any(c["name"] == "lidar up_lidar: unit directions" and not c["ok"]
                                         for c in report["checks"])  # fmt: skip
