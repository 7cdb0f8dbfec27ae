"""TbV: per-point firing times reconstructed without offset_ns, checked against the real truth."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
from click.testing import CliRunner
from ncore.data.v4 import LidarSensorComponent
from conftest import AV2_SAMPLE_LOG, find_av2_sample, open_sequence
from upath import UPath

from ncore_convert.cli import cli
from ncore_convert.sources import argoverse2 as av2


def make_tbv_like(av2_log_dir, tbv_root) -> str:
    """A TbV-like copy of an AV2 log: flat layout, no offset_ns, no stereo rows, no annotations.
    Returns the log id; the true offsets stay in the AV2 original."""
    log_dir = tbv_root / AV2_SAMPLE_LOG
    shutil.copytree(av2_log_dir, log_dir, ignore=shutil.ignore_patterns("annotations.feather", "stereo_*"))
    for path in (log_dir / "sensors" / "lidar").glob("*.feather"):
        table = feather.read_table(path)
        feather.write_feather(table.drop_columns(["offset_ns"]), path, compression="uncompressed")
    for name in ("egovehicle_SE3_sensor.feather", "intrinsics.feather"):
        path = log_dir / "calibration" / name
        table = feather.read_table(path)
        keep = [not str(n).startswith("stereo_") for n in table.column("sensor_name").to_pylist()]
        feather.write_feather(table.filter(pa.array(keep)), path, compression="uncompressed")
    return AV2_SAMPLE_LOG


@pytest.fixture(scope="module")
def real_tbv(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tbv-real")
    av2_log_dir = find_av2_sample() / "val" / AV2_SAMPLE_LOG
    log_id = make_tbv_like(av2_log_dir, tmp / "root")
    out = tmp / "out"
    result = CliRunner().invoke(
        cli, ["--no-progress", "--root-dir", str(tmp / "root"), "--output-dir", str(out), "tbv-v4"],
        catch_exceptions=False,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    return av2_log_dir, out / log_id, open_sequence(out / log_id, log_id)


def test_tbv_like_copy_has_no_offsets(real_tbv, tmp_path):
    av2_log_dir, _, _ = real_tbv
    make_tbv_like(av2_log_dir, tmp_path)
    sweep = next((tmp_path / AV2_SAMPLE_LOG / "sensors" / "lidar").glob("*.feather"))
    assert "offset_ns" not in feather.read_table(sweep).column_names


def test_reconstructed_times_match_the_true_offsets(real_tbv):
    av2_log_dir, _, loader = real_tbv
    errors_ms = []
    for unit, low_half in (("up_lidar", True), ("down_lidar", False)):
        lidar = loader.get_lidar_sensor(unit)
        for frame, ts in enumerate(av2.list_sweep_timestamps_ns(UPath(av2_log_dir))):
            sweep = av2.read_sweep(UPath(av2_log_dir), int(ts))
            rows = np.flatnonzero((sweep.laser_number < 32) == low_half)  # the true unit of each row
            true_us = (int(ts) + sweep.offset_ns[rows].astype(np.int64)) / 1e3
            stored_us = lidar.get_frame_ray_bundle_timestamp_us(frame)
            assert len(stored_us) == len(rows), unit  # every return kept, in row order, under the right unit
            errors_ms.append((stored_us.astype(np.float64) - true_us) / 1e3)
    errors = np.abs(np.concatenate(errors_ms))
    assert np.median(errors) <= 0.06 and np.percentile(errors, 95) <= 0.3, (np.median(errors), np.percentile(errors, 95))


def test_timing_method_and_residuals_are_in_the_lidar_metadata(real_tbv):
    _, _, loader = real_tbv
    readers = loader._reader.open_component_readers(LidarSensorComponent.Reader)
    for unit in ("up_lidar", "down_lidar"):
        assert readers[unit].generic_meta_data["av2_unit_decision"]["laser_number_lt_32"] == "up_lidar"
        timing = readers[unit].generic_meta_data["point_timing"]
        assert timing["method"] == "reconstructed" and timing["trigger_phases"] == 14
        assert 0 <= timing["first_firing_ms"] < 10 and timing["knot_residual_ms"] < 0.1
        json.dumps(timing)


def test_the_lidar_model_fits_the_reconstructed_rays(real_tbv):
    from ncore_convert.evaluate import evaluate_lidar_model

    _, _, loader = real_tbv
    for unit in ("up_lidar", "down_lidar"):
        report = evaluate_lidar_model(loader, unit, far_range_m=20.0)
        assert report.far_mean_deg <= 0.015, (unit, report.far_mean_deg)
