"""HD maps travel with the sequence: exact round trip through the nvidia-ncore reader, placement
against world_global on the real sample, --no-maps, and bad map files."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from conftest import AV2_SAMPLE_LOG, open_sequence
from ncore.data.v4 import PosesComponent
from upath import UPath

from ncore_convert.contract import MAP_GROUND_HEIGHT, MAP_META, MAP_VECTOR_JSON
from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
from ncore_convert.errors import SourceError
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import argoverse2_map as av2_map


def stored_map(loader) -> tuple[bytes, np.ndarray, dict]:
    poses = loader._reader.open_component_readers(PosesComponent.Reader)["default"]
    vector = poses.get_generic_data(MAP_VECTOR_JSON).tobytes()
    return vector, poses.get_generic_data(MAP_GROUND_HEIGHT), poses.generic_meta_data[MAP_META]


def ground_height_at(raster: np.ndarray, sim2: dict, xy_city_m: np.ndarray) -> np.ndarray:
    """The AV2 raster lookup (test's own statement of it): p_img = s (R xy + t), truncated to cells."""
    R = np.asarray(sim2["R"]).reshape(2, 2)
    p_img = sim2["s"] * (xy_city_m @ R.T + np.asarray(sim2["t"]))
    col, row = p_img.astype(np.int64).T
    inside = (row >= 0) & (row < raster.shape[0]) & (col >= 0) & (col < raster.shape[1])
    out = np.full(len(xy_city_m), np.nan)
    out[inside] = raster[row[inside], col[inside]]
    return out


def test_real_map_round_trips_exactly(real_log, av2_sample_root):
    source = av2_map.read_log_map(UPath(av2_sample_root / "val" / AV2_SAMPLE_LOG))
    vector, raster, meta = stored_map(real_log.loader)
    assert vector == source.vector_map_json and json.loads(vector) == json.loads(source.vector_map_json)
    assert raster.dtype == np.float16 and raster.shape == (785, 880)
    assert raster.tobytes() == source.ground_height_m.tobytes()  # bit for bit, NaNs included
    assert np.isnan(raster).mean() > 0.3
    assert meta["img_Sim2_city"] == source.img_Sim2_city and meta["city"] == "PIT"
    assert meta["frame"].startswith("world_global") and real_log.summary.maps == 1


def test_real_map_sits_under_the_converted_trajectory(real_log, av2_sample_root):
    """Ground height at the ego positions from the converted world_global poses is a near-constant
    distance below the ego origin, as it is with the source poses."""
    _, raster, meta = stored_map(real_log.loader)
    poses = real_log.reader.open_component_readers(PosesComponent.Reader)["default"]
    T_rig_world, _ = poses.get_dynamic_pose("rig", "world")
    T_world_global = poses.get_static_pose("world", "world_global")
    ego_global = (T_world_global @ T_rig_world.astype(np.float64))[:, :3, 3]
    height = ego_global[:, 2] - ground_height_at(raster, meta["img_Sim2_city"], ego_global[:, :2])
    _, T_ego_city = av2.read_ego_poses(UPath(av2_sample_root / "val" / AV2_SAMPLE_LOG))
    source = av2_map.read_log_map(UPath(av2_sample_root / "val" / AV2_SAMPLE_LOG))
    xyz = T_ego_city[:, :3, 3]
    source_height = xyz[:, 2] - ground_height_at(source.ground_height_m, source.img_Sim2_city, xyz[:, :2])
    assert np.isfinite(height).mean() > 0.95
    assert np.nanstd(height) <= 0.05, np.nanstd(height)
    assert abs(np.nanmedian(height) - np.nanmedian(source_height)) <= 0.005
    assert 0.2 < np.nanmedian(height) < 0.45  # a rear-axle origin above the road


def test_no_maps_option_leaves_the_map_out(av2_sample_root, tmp_path):
    seq = tmp_path / AV2_SAMPLE_LOG
    summary = convert_log(UPath(av2_sample_root), UPath(seq), AV2_SAMPLE_LOG, Argoverse2Options("val", maps=False))
    poses = open_sequence(seq, AV2_SAMPLE_LOG)._reader.open_component_readers(PosesComponent.Reader)["default"]
    assert (
        summary.maps == 0 and not poses.has_generic_data(MAP_GROUND_HEIGHT) and MAP_META not in poses.generic_meta_data
    )


@pytest.mark.parametrize(
    "damage, cause",
    [
        (lambda d: (d / "extra___img_Sim2_city.json").write_text("{}"), "expected exactly one *___img_Sim2_city.json"),
        (lambda d: next(d.glob("*.npy")).write_bytes(b"\x93NUMPY garbage"), "not a .npy array"),
        (
            lambda d: next(d.glob("log_map_archive_*")).write_text('{"lane_segments": {}}'),
            "a vector map needs the keys",
        ),
    ],
)
def test_bad_map_files_are_named_in_the_error(av2_sample_root, tmp_path, damage, cause):
    log_dir = tmp_path / AV2_SAMPLE_LOG
    shutil.copytree(av2_sample_root / "val" / AV2_SAMPLE_LOG / "map", log_dir / "map")
    for path in (log_dir / "map").iterdir():
        path.chmod(0o644)
    damage(log_dir / "map")
    with pytest.raises(SourceError, match="map") as err:
        av2_map.read_log_map(UPath(log_dir))
    assert cause in str(err.value)


def test_synthetic_map_files_match_the_real_format(av2_sample_root, tmp_path):
    from ncore_convert.synth.argoverse2 import SynthConfig, write_log

    truth = write_log(UPath(tmp_path), SynthConfig(seconds=0.3, seed=3, camera_fps=0, tbv=True))
    synth, real = (
        av2_map.read_log_map(truth.log_dir),
        av2_map.read_log_map(UPath(av2_sample_root / "val" / AV2_SAMPLE_LOG)),
    )
    synth_vector, real_vector = json.loads(synth.vector_map_json), json.loads(real.vector_map_json)
    assert list(synth_vector) == list(real_vector)
    for kind in real_vector:
        assert list(next(iter(synth_vector[kind].values()))) == list(next(iter(real_vector[kind].values()))), kind
    assert (
        synth.ground_height_m.dtype == real.ground_height_m.dtype
        and synth.img_Sim2_city.keys() == real.img_Sim2_city.keys()
    )
    for name, real_name in zip(synth.file_names, real.file_names, strict=True):
        assert (
            name.replace(truth.log_id, "ID").split("____")[0]
            == real_name.replace(AV2_SAMPLE_LOG, "ID").split("____")[0]
        )
