"""Fuzzing the source readers with hypothesis: for any bytes, a reader either returns its result
or raises the project's own SourceError naming the file, never another exception (or a crash).

Inputs are drawn three ways per reader: arbitrary bytes; a valid file cut short, with bytes flipped
or spliced in (what interrupted downloads and bit rot produce); and well-formed containers with
wrong contents (header values, YAML structures, column types). FUZZ_EXAMPLES cases per reader run
in CI (``make test``); set NCORE_CONVERT_FUZZ_EXAMPLES to run more.
"""

from __future__ import annotations

import copy
import io
import os
import tempfile
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources import argoverse2_annotations as av2_annotations
from ncore_convert.sources import opencood as ocd
from ncore_convert.sources.pcd import read_pcd, read_pcd_header

FUZZ_EXAMPLES = int(os.environ.get("NCORE_CONVERT_FUZZ_EXAMPLES", "3000"))
FUZZ = settings(
    max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large]
)


@pytest.fixture(scope="module")
def scratch() -> Path:
    with tempfile.TemporaryDirectory() as folder:
        yield Path(folder)


def damaged(valid: bytes) -> st.SearchStrategy[bytes]:
    """``valid`` cut short, with bytes overwritten, or with bytes spliced in."""
    n = len(valid)
    cut = st.integers(0, n).map(lambda k: valid[:k])
    flip = st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 255)), min_size=1, max_size=8).map(
        lambda edits: _overwrite(valid, edits)
    )
    splice = st.tuples(st.integers(0, n), st.binary(min_size=1, max_size=64)).map(
        lambda e: valid[: e[0]] + e[1] + valid[e[0] :]
    )
    return st.one_of(cut, flip, splice)


def _overwrite(data: bytes, edits: list[tuple[int, int]]) -> bytes:
    out = bytearray(data)
    for at, value in edits:
        out[at] = value
    return bytes(out)


def parses_or_source_error(read, path: Path, data: bytes) -> None:
    path.write_bytes(data)
    try:
        read(UPath(path))
        event("parsed")
    except SourceError as err:
        event("SourceError")
        assert err.path == str(path) and "\n" not in str(err)


# ------------------------------------------------------------------------------------------------
# PCD (OPV2V / V2XSet lidar frames)
# ------------------------------------------------------------------------------------------------

FIELDS = ["x", "y", "z", "rgb"]


def pcd_file(xyz: np.ndarray, data: str) -> bytes:
    header = (
        f"VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {len(xyz)}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(xyz)}\nDATA {data}\n"
    ).encode()
    table = np.column_stack([xyz, np.full(len(xyz), 1.5)]).astype(np.float32)
    if data == "binary":
        return header + table.tobytes()
    body = io.BytesIO()
    np.savetxt(body, table, fmt="%.10g")
    return header + body.getvalue()


VALID_PCD = [pcd_file(np.random.default_rng(1).uniform(-50, 50, (20, 3)), kind) for kind in ("ascii", "binary")]
header_words = st.sampled_from(["FIELDS", "SIZE", "TYPE", "COUNT", "POINTS", "DATA", "WIDTH", "#", "VERSION"])
header_values = st.lists(
    st.one_of(
        st.sampled_from(
            ["x", "y", "z", "rgb", "F", "U", "I", "4", "8", "1", "2", "ascii", "binary", "binary_compressed"]
        ),
        st.integers(-10, 10**12).map(str),
        st.text(alphabet="abcXYZ019-.", max_size=6),
    ),
    max_size=6,
)
header_line = st.tuples(header_words, header_values).map(lambda wv: " ".join([wv[0], *wv[1]]))
structured_pcd = st.tuples(st.lists(header_line, max_size=12), st.binary(max_size=256)).map(
    lambda hb: ("\n".join(hb[0]) + "\n").encode() + hb[1]
)
pcd_inputs = st.one_of(st.binary(max_size=512), damaged(VALID_PCD[0]), damaged(VALID_PCD[1]), structured_pcd)


def read_pcd_fully(path: UPath) -> None:
    read_pcd_header(path)
    read_pcd(path)
    ocd.read_points(path.parent, path.stem)


@FUZZ
@given(pcd_inputs)
def test_pcd_reader_parses_or_raises_source_error(scratch, data):
    parses_or_source_error(read_pcd_fully, scratch / "000001.pcd", data)


# ------------------------------------------------------------------------------------------------
# YAML (OPV2V / V2XSet frame metadata)
# ------------------------------------------------------------------------------------------------

VALID_FRAME = {
    "lidar_pose": [1.0, 2.0, 1.9, 0.1, 90.0, 0.2],
    "true_ego_pos": [1.0, 2.0, 0.0, 0.1, 90.0, 0.2],
    "camera0": {"cords": [1.0, 2.0, 1.0, 0.0, 90.0, 0.0], "intrinsic": [[400, 0, 400], [0, 400, 300], [0, 0, 1]]},
    "vehicles": {"712": {"location": [5, 1, 0], "angle": [0, 45, 0], "center": [0, 0, 0.7], "extent": [2.4, 1.0, 0.7]}},
}
VALID_YAML = yaml.safe_dump(VALID_FRAME).encode()
scalars = st.one_of(
    st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8), st.just("!!python/object:os.system")
)
yaml_values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=7), st.dictionaries(st.text(max_size=6), inner, max_size=5)),
    max_leaves=20,
)


@st.composite
def mutated_frames(draw) -> bytes:
    """A valid frame with keys dropped, or values replaced by arbitrary YAML values."""
    frame = copy.deepcopy(VALID_FRAME)  # what VALID_YAML loads to, without parsing it each draw
    for key in draw(st.lists(st.sampled_from(list(frame)), max_size=3)):
        frame.pop(key, None)
    for key in draw(st.lists(st.sampled_from(list(VALID_FRAME) + ["camera1", "vehicles"]), max_size=3)):
        frame[key] = draw(yaml_values)
    vehicle = frame.get("vehicles")
    if isinstance(vehicle, dict) and "712" in vehicle and draw(st.booleans()):
        vehicle["712"][draw(st.sampled_from(["location", "angle", "center", "extent"]))] = draw(yaml_values)
    return yaml.dump(frame, Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper)).encode()  # libyaml if built


yaml_text = st.text(alphabet=st.sampled_from(list("abc019:-[]{},&*!|>'\"#%@ \n\t.")), max_size=200).map(str.encode)
yaml_inputs = st.one_of(st.binary(max_size=256), yaml_text, damaged(VALID_YAML), mutated_frames())


@FUZZ
@given(yaml_inputs)
def test_yaml_reader_parses_or_raises_source_error(scratch, data):
    parses_or_source_error(lambda path: ocd.read_agent_frame(path.parent, path.stem), scratch / "000001.yaml", data)


# ------------------------------------------------------------------------------------------------
# Feather (Argoverse 2 tables and sweeps)
# ------------------------------------------------------------------------------------------------


def feather_bytes(table: pa.Table, compression: str = "lz4") -> bytes:
    sink = io.BytesIO()
    feather.write_feather(table, sink, compression=compression)
    return sink.getvalue()


def _sweep_table(n: int = 40) -> pa.Table:
    rng = np.random.default_rng(2)
    columns = {
        "x": rng.normal(size=n).astype(np.float16),
        "y": rng.normal(size=n).astype(np.float16),
        "z": rng.normal(size=n).astype(np.float16),
        "intensity": rng.integers(0, 255, n).astype(np.uint8),
        "laser_number": rng.integers(0, 64, n).astype(np.uint8),
        "offset_ns": rng.integers(0, 10**8, n).astype(np.int32),
    }
    return pa.table({k: pa.array(v, type=av2.LIDAR_SCHEMA.field(k).type) for k, v in columns.items()})


def _pose_table(n: int = 6) -> pa.Table:
    columns = {"timestamp_ns": np.arange(n, dtype=np.int64) * 10**7, "qw": np.ones(n)}
    columns.update({c: np.zeros(n) for c in ("qx", "qy", "qz", "tx_m", "ty_m", "tz_m")})
    return pa.table({k: pa.array(v, type=av2.POSES_SCHEMA.field(k).type) for k, v in columns.items()})


def _annotation_table(n: int = 3) -> pa.Table:
    columns = {
        "timestamp_ns": np.zeros(n, np.int64),
        "track_uuid": [f"t{i}" for i in range(n)],
        "category": ["BUS"] * n,
    }
    columns.update({c: np.full(n, 2.0) for c in ("length_m", "width_m", "height_m", "qw")})
    columns.update({c: np.zeros(n) for c in ("qx", "qy", "qz", "tx_m", "ty_m", "tz_m")})
    columns["num_interior_pts"] = np.arange(n, dtype=np.int64)
    return pa.table({k: pa.array(v, type=av2.ANNOTATIONS_SCHEMA.field(k).type) for k, v in columns.items()})


TABLES = [_sweep_table(), _pose_table(), _annotation_table()]
VALID_FEATHER = [feather_bytes(t, c) for t in TABLES for c in ("lz4", "uncompressed")]
arrow_types = st.sampled_from(
    [pa.float16(), pa.float32(), pa.float64(), pa.int32(), pa.int64(), pa.uint8(), pa.string(), pa.bool_()]
)


@st.composite
def retyped_tables(draw) -> bytes:
    """A sweep, pose or annotation table with columns cast, dropped, nulled or of another length."""
    table = draw(st.sampled_from(TABLES))
    for name in draw(st.lists(st.sampled_from(table.column_names), max_size=3, unique=True)):
        action = draw(st.sampled_from(["cast", "drop", "null"]))
        i = table.schema.get_field_index(name)
        if action == "drop":
            table = table.remove_column(i)
        elif action == "null":
            table = table.set_column(i, name, pa.nulls(table.num_rows, table.schema.field(name).type))
        else:
            kind = draw(arrow_types)
            values = pa.array(["a"] * table.num_rows) if kind == pa.string() else pa.array(np.ones(table.num_rows))
            table = table.set_column(i, name, values.cast(kind) if kind != pa.string() else values)
    return feather_bytes(table, draw(st.sampled_from(["lz4", "zstd", "uncompressed"])))


feather_inputs = st.one_of(st.binary(max_size=512), *(damaged(v) for v in VALID_FEATHER), retyped_tables())


AV2_READERS = {
    "sweep": lambda log, stamp: av2.read_sweep(log, stamp),
    "TbV sweep": lambda log, stamp: av2.read_sweep(log, stamp, with_offsets=False),
    "poses": lambda log, stamp: av2.read_ego_poses(log),
    "annotations": lambda log, stamp: av2_annotations.read_annotations(log),
}


@FUZZ
@given(feather_inputs)
def test_feather_reader_parses_or_raises_source_error(scratch, data):
    """The same bytes as a sweep, a TbV sweep, a pose table and an annotation table."""
    log, stamp = scratch / "log", 315966265259836000
    files = [av2.sweep_path(UPath(log), stamp).path, log / "city_SE3_egovehicle.feather", log / "annotations.feather"]
    for path in map(Path, files):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    for name, read in AV2_READERS.items():
        try:
            read(UPath(log), stamp)
            event(f"parsed as {name}")
        except SourceError as err:
            event("SourceError")
            assert err.path in map(str, files) and "\n" not in str(err)
