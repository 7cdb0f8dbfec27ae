"""The synthetic AV2 log is format-compatible with the real dataset and simulates the VLP-32C as specified."""

from __future__ import annotations

import numpy as np
import PIL.Image
import pyarrow.feather as feather
import pyarrow.ipc as ipc
import pytest
from conftest import AV2_SAMPLE_LOG

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.synth import ego
from ncore_convert.transforms.lidar import vlp32c

TABLES = [
    "city_SE3_egovehicle.feather",
    "annotations.feather",
    "calibration/egovehicle_SE3_sensor.feather",
    "calibration/intrinsics.feather",
]


def test_feather_schemas_match_the_real_dataset(synth_log, av2_sample_root):
    real = av2_sample_root / "val" / AV2_SAMPLE_LOG
    synth = synth_log.truth.log_dir
    for name in TABLES:
        real_schema = feather.read_table(real / name).schema.remove_metadata()
        assert feather.read_table(synth / name).schema.remove_metadata() == real_schema, name
    real_sweep = sorted((real / "sensors" / "lidar").glob("*.feather"))[0]
    synth_sweep = av2.sweep_path(synth, synth_log.truth.sweeps[0].timestamp_ns)
    with ipc.open_file(real_sweep) as r, synth_sweep.open("rb") as f, ipc.open_file(f) as s:
        assert s.schema.remove_metadata() == r.schema.remove_metadata()
        assert b"pandas" in s.schema.metadata
        assert s.get_batch(0).num_rows == r.get_batch(0).num_rows == 65536  # pyarrow feather chunking


def test_calibration_has_all_sensors_and_real_resolutions(synth_log, av2_sample_root):
    real = av2.read_intrinsics(av2_sample_root / "val" / AV2_SAMPLE_LOG)
    synth = av2.read_intrinsics(synth_log.truth.log_dir)
    assert list(synth) == list(real) == list(av2.CAMERAS)
    for cam in av2.CAMERAS:
        assert (synth[cam].width_px, synth[cam].height_px) == (real[cam].width_px, real[cam].height_px)
    extrinsics = av2.read_sensor_extrinsics(synth_log.truth.log_dir)
    assert list(extrinsics) == list(av2.CAMERAS) + list(av2.LIDARS)
    assert extrinsics["down_lidar"][2, 2] < -0.99 < 0.99 < extrinsics["up_lidar"][2, 2]  # mounted upside down


def test_jpegs_have_realistic_size_and_are_valid(synth_log):
    sizes = [p.stat().st_size for p in synth_log.truth.image_paths]
    assert 150_000 < np.median(sizes) < 800_000
    first = synth_log.truth.image_paths[0].read_bytes()
    assert first[:2] == b"\xff\xd8" and first[-2:] == b"\xff\xd9"


def test_a_pose_at_every_sensor_timestamp(synth_log):
    pose_ns, _ = av2.read_ego_poses(synth_log.truth.log_dir)
    sensor_ns = [s.timestamp_ns for s in synth_log.truth.sweeps] + [int(p.stem) for p in synth_log.truth.image_paths]
    assert np.isin(sensor_ns, pose_ns).all()
    last_point_ns = max(s.timestamp_ns + int(s.offset_ns.max()) for s in synth_log.truth.sweeps)
    assert pose_ns[0] < synth_log.truth.sweeps[0].timestamp_ns and pose_ns[-1] > last_point_ns


def test_lidar_firing_pattern_is_vlp32c(synth_log):
    sweep = synth_log.truth.sweeps[0]
    for unit_index in (0, 1):
        mine = sweep.unit == unit_index
        times = np.unique(sweep.time_ns[mine])
        steps = np.diff(times)
        # within a cycle pairs are 2.304 µs apart; the cycle is 55.296 µs
        assert np.isin(steps % vlp32c.FIRING_PAIR_SPACING_NS, [0]).mean() > 0.9
        assert ((times - times[0]) % vlp32c.FIRING_CYCLE_NS % vlp32c.FIRING_PAIR_SPACING_NS == 0).all()
        _, counts = np.unique(sweep.time_ns[mine], return_counts=True)
        assert counts.max() == 2  # paired firings
        assert 0.9e8 < np.ptp(sweep.time_ns[mine]) <= 1e8 + vlp32c.FIRING_CYCLE_NS  # one revolution


def test_units_spin_opposite_ways_in_their_own_frames(synth_log):
    sweep = synth_log.truth.sweeps[0]
    rates = []
    for unit_index in (0, 1):
        mine = sweep.unit == unit_index
        d = sweep.direction_sensor[mine]
        azimuth = np.unwrap(
            np.arctan2(d[:, 1], d[:, 0]) - np.radians(vlp32c.BEAM_AZIMUTH_OFFSET_DEG[sweep.laser_number[mine] % 32])
        )
        rates.append(np.polyfit(sweep.time_ns[mine] * 1e-9 - sweep.timestamp_ns * 1e-9, azimuth, 1)[0])
    assert rates[0] < 0 < rates[1]  # up clockwise, down counter-clockwise about their own +z
    np.testing.assert_allclose(np.abs(rates), 2 * np.pi * 10, rtol=1e-3)


def test_elevations_follow_the_beam_table(synth_log):
    sweep = synth_log.truth.sweeps[0]
    beams = sweep.laser_number % 32
    elevation = np.degrees(np.arcsin(sweep.direction_sensor[:, 2]))
    np.testing.assert_allclose(elevation, vlp32c.BEAM_ELEVATION_DEG[beams], atol=1e-9)


@pytest.mark.parametrize("size", [(1550, 2048), (4096, 3000)])
def test_picture_pixels_read_through_arrow_equal_pillows_own(size):
    """``synth.ego.pixels`` (the generator's fast path from Pillow to numpy) gives Pillow's own
    pixels, both where the rows are one block (read through Arrow) and where they are not (AV2's
    size, and one over Pillow's block size)."""
    width, height = size
    values = np.random.default_rng(0).uniform(-1, 1, (height // 9, width // 9)).astype(np.float32)
    image = PIL.Image.fromarray(values, mode="F").resize((width, height), PIL.Image.BILINEAR)
    got = ego.pixels(image)
    assert got.dtype == np.float32 and got.shape == (height, width)
    np.testing.assert_array_equal(got, np.asarray(image))
