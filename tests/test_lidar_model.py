"""The empirical structured lidar model: against the simulated VLP-32C truth and on the real sample."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import synth_and_convert
from ncore.data.v4 import LidarSensorComponent
from ncore.impl.data.types import RowOffsetStructuredSpinningLidarModelParameters

from ncore_convert.cli import cli
from ncore_convert.converters.argoverse2 import Argoverse2Options
from ncore_convert.evaluate import evaluate_lidar_model
from ncore_convert.synth.argoverse2 import UNIT_SPIN, SynthConfig
from ncore_convert.transforms.lidar import vlp32c

UNITS = ("up_lidar", "down_lidar")


def _params(converted, unit) -> RowOffsetStructuredSpinningLidarModelParameters:
    params = converted.loader.get_lidar_sensor(unit).model_parameters
    assert isinstance(params, RowOffsetStructuredSpinningLidarModelParameters)
    return params


def _centred_deg(offsets_deg: np.ndarray) -> np.ndarray:
    """Row offsets up to the constant that can move between columns and rows."""
    return offsets_deg - offsets_deg.mean()


@pytest.mark.parametrize("unit", UNITS)
def test_model_recovers_the_simulated_beams_and_spin(synth_log, unit):
    params = _params(synth_log, unit)
    truth_order = np.argsort(-vlp32c.BEAM_ELEVATION_DEG)
    elevation_deg = np.degrees(params.row_elevations_rad.astype(np.float64))
    assert np.max(np.abs(elevation_deg - vlp32c.BEAM_ELEVATION_DEG[truth_order])) <= 0.01
    offsets_deg = np.degrees(params.row_azimuth_offsets_rad.astype(np.float64))
    truth_offsets_deg = vlp32c.BEAM_AZIMUTH_OFFSET_DEG[truth_order]
    assert np.max(np.abs(_centred_deg(offsets_deg) - _centred_deg(truth_offsets_deg))) <= 0.02
    spin, _ = UNIT_SPIN[unit]
    assert params.spinning_direction == ("ccw" if spin > 0 else "cw")
    assert params.spinning_frequency_hz == pytest.approx(vlp32c.SPIN_RATE_HZ, rel=1e-3)


@pytest.mark.parametrize("unit", UNITS)
def test_model_elements_reproduce_the_simulated_rays(synth_log, unit):
    report = evaluate_lidar_model(synth_log.loader, unit, far_range_m=20.0)
    assert report.far_points > 10_000
    assert report.far_mean_deg <= 0.008
    sensor = synth_log.loader.get_lidar_sensor(unit)
    params = _params(synth_log, unit)
    for i in range(sensor.frames_count):
        elements = sensor.get_frame_ray_bundle_model_element(i)
        assert elements.dtype == np.uint16 and elements.shape == (len(sensor.get_frame_ray_bundle_direction(i)), 2)
        assert elements[:, 0].max() < params.n_rows and elements[:, 1].max() < params.n_columns


def test_a_single_sweep_log_gets_a_model(tmp_path):
    converted = synth_and_convert(
        tmp_path, SynthConfig(seconds=0.1, seed=4, camera_fps=0), Argoverse2Options(split="val", camera_ids=())
    )
    assert converted.summary.frames == 1
    for unit in UNITS:
        assert evaluate_lidar_model(converted.loader, unit).far_mean_deg <= 0.008


@pytest.mark.parametrize("unit", UNITS)
def test_real_sample_model_accuracy(real_log, unit):
    report = evaluate_lidar_model(real_log.loader, unit, far_range_m=20.0)
    sensor = real_log.loader.get_lidar_sensor(unit)
    assert report.points == sum(len(sensor.get_frame_ray_bundle_direction(i)) for i in range(sensor.frames_count))
    assert report.far_mean_deg <= 0.009
    assert max(r["far_mean_deg"] for r in report.rows if r["far_points"]) <= 0.02
    assert abs(report.azimuth_bias_deg) <= 0.003 and abs(report.elevation_bias_deg) <= 0.003


def test_evaluate_command_prints_tables_and_json(synth_log):
    meta = synth_log.seq_dir / f"{synth_log.truth.log_id}.json"
    result = CliRunner().invoke(cli, ["evaluate-lidar-model", str(meta), "--lidar-id", "up_lidar"])
    assert result.exit_code == 0, result.output
    assert result.output.startswith("up_lidar: ") and "far range (> 20 m" in result.output
    assert "row  elevation°" in result.output and "frame  timestamp_us" in result.output
    result = CliRunner().invoke(cli, ["evaluate-lidar-model", str(meta), "--json", "--far-range-m", "30"])
    reports = json.loads(result.output)
    assert sorted(r["lidar_id"] for r in reports) == sorted(UNITS)
    assert all(r["far_range_m"] == 30 and len(r["rows"]) == 32 for r in reports)
    result = CliRunner().invoke(cli, ["evaluate-lidar-model", str(meta), "--lidar-id", "side_lidar"])
    assert result.exit_code == 2 and "side_lidar" in result.output


def test_evaluate_command_fails_clearly_without_a_model(tmp_path):
    converted = synth_and_convert(
        tmp_path,
        SynthConfig(seconds=0.1, seed=4, camera_fps=0),
        Argoverse2Options(split="val", camera_ids=(), lidar_model_source="none"),
    )
    meta = converted.seq_dir / f"{converted.truth.log_id}.json"
    result = CliRunner().invoke(cli, ["evaluate-lidar-model", str(meta)])
    assert result.exit_code == 1 and "no row-offset structured lidar model" in result.output


def test_column_time_remap_unwraps_and_recovers_phase_and_rate():
    from ncore_convert.transforms.lidar.model import column_time_remap

    rng = np.random.default_rng(3)
    n, rate = 28_928, 28_928 * 10.02  # columns per second of a slightly fast spin
    t = np.sort(rng.uniform(0.0026, 0.1028, 50_000))
    true = 28_900.0 + rate * (t - t.min())  # starts just before the end of the grid, so it wraps
    columns = np.rint(true + rng.normal(0, 2, len(t))) % n
    remap = column_time_remap(columns, t, n, 10.0)
    assert remap["first_time_s"] == t.min()
    assert remap["column_at_first_time"] == pytest.approx(28_900.0, abs=0.5)
    assert remap["columns_per_second"] == pytest.approx(rate, rel=1e-4)
    assert remap["residual_p99_columns"] < 8


@pytest.mark.parametrize("unit", UNITS)
def test_every_frame_records_its_column_time_alignment(synth_log, unit):
    sensor = synth_log.loader.get_lidar_sensor(unit)
    n_columns = _params(synth_log, unit).n_columns
    for i in range(sensor.frames_count):
        remap = sensor.get_frame_generic_meta_data(i)["model_column_time_remap"]
        assert remap["columns_per_second"] == pytest.approx(n_columns * vlp32c.SPIN_RATE_HZ, rel=2e-3)
        assert remap["residual_p99_columns"] < 4  # a uniform simulated spin: only firing-stagger and µs rounding


@pytest.mark.parametrize("unit", UNITS)
def test_laser_number_to_row_map_is_stored_and_sorts_by_elevation(synth_log, unit):
    meta = synth_log.reader.open_component_readers(LidarSensorComponent.Reader)[unit].generic_meta_data
    laser_to_row = {int(k): v for k, v in meta["lidar_model"]["laser_number_to_row"].items()}
    low = meta["av2_unit_decision"]["laser_number_lt_32"] == unit
    assert sorted(laser_to_row) == list(range(0, 32) if low else range(32, 64))
    assert sorted(laser_to_row.values()) == list(range(32))
    by_row = sorted(laser_to_row, key=laser_to_row.get)
    assert np.all(np.diff(vlp32c.BEAM_ELEVATION_DEG[np.array(by_row) % 32]) < 0)
