"""Argoverse 2 Sensor on-disk format: small, pure readers. Knows nothing of NCore.

Layout: ``<root>/<split>/<log_id>/`` with feather tables (read with pyarrow), lidar sweeps under
``sensors/lidar/<timestamp_ns>.feather`` and JPEGs under ``sensors/cameras/<camera>/<timestamp_ns>.jpg``.
Frames follow av2: ``city_SE3_ego`` maps ego points to the city frame, ``ego_SE3_sensor`` maps
sensor points to the ego frame. Quaternions are scalar-first (qw, qx, qy, qz). The readers return
them under the project's ``T_a_b`` names (``T_ego_city``, ``T_sensor_ego``, ``T_object_ego``), so av2's
``x_SE3_y`` names stay in the AV2 readers (this module, :mod:`.argoverse2_annotations`).

Every reader raises :class:`SourceError` naming the file and the cause on bad input.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import PIL.Image
import pyarrow as pa
import pyarrow.feather as feather
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.paths import is_local
from ncore_convert.sources.checks import check_safe_names, jpeg_defect
from ncore_convert.sources.reader import Reader, reading
from ncore_convert.sources.store import ObjectInfo, unreadable
from ncore_convert.transforms.geometry import se3_from_quat_wxyz

SPLITS = ("train", "val", "test")
RING_CAMERAS = (
    "ring_front_center",
    "ring_front_left",
    "ring_front_right",
    "ring_rear_left",
    "ring_rear_right",
    "ring_side_left",
    "ring_side_right",
)
STEREO_CAMERAS = ("stereo_front_left", "stereo_front_right")
CAMERAS = RING_CAMERAS + STEREO_CAMERAS
LIDARS = ("up_lidar", "down_lidar")

POSE_COLUMNS = ("qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
LIDAR_SCHEMA = pa.schema(
    [
        ("x", pa.float16()),
        ("y", pa.float16()),
        ("z", pa.float16()),
        ("intensity", pa.uint8()),
        ("laser_number", pa.uint8()),
        ("offset_ns", pa.int32()),
    ]
)
POSES_SCHEMA = pa.schema([("timestamp_ns", pa.int64())] + [(c, pa.float64()) for c in POSE_COLUMNS])
EXTRINSICS_SCHEMA = pa.schema([("sensor_name", pa.string())] + [(c, pa.float64()) for c in POSE_COLUMNS])
INTRINSICS_SCHEMA = pa.schema(
    [("sensor_name", pa.string())]
    + [(c, pa.float64()) for c in ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "k3")]
    + [("height_px", pa.uint16()), ("width_px", pa.uint16())]
)
ANNOTATIONS_SCHEMA = pa.schema(
    [("timestamp_ns", pa.int64()), ("track_uuid", pa.string()), ("category", pa.string())]
    + [(c, pa.float64()) for c in ("length_m", "width_m", "height_m") + POSE_COLUMNS]
    + [("num_interior_pts", pa.int64())]
)


def read_table(
    path: UPath,
    schema: pa.Schema,
    columns: list[str] | None = None,
    data: bytes | None = None,
    listing: dict[str, ObjectInfo] | None = None,
    reader: Reader | None = None,
) -> pa.Table:
    """Read a feather file and check that it has the columns and types of ``schema``.

    ``data``: the file's bytes, already fetched (:mod:`sources.reader`). Without them, a local file
    is memory-mapped and a remote one (s3://, ...) fetched whole in one request by ``reader``,
    checked against its folder's ``listing`` entry and kept for the log's later readers.
    """
    path = UPath(path)
    wanted = columns or schema.names
    try:
        if data is None and is_local(path):
            table = feather.read_table(path.path, columns=wanted, memory_map=True, use_threads=False)
        else:
            if data is None:
                with reading(reader) as r:
                    data = r.read(path, listing, keep=True)
            source = pa.BufferReader(data)
            table = feather.read_table(source, columns=wanted, use_threads=False)
        table.validate(full=True)  # a damaged body must not reach numpy as garbage offsets
    except (FileNotFoundError, PermissionError) as err:
        raise unreadable(path, err) from None
    except (pa.ArrowException, KeyError, OSError) as err:
        cause = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise SourceError(path, f"not a readable feather table with columns {wanted} ({cause})") from None
    for name in wanted:
        expected = schema.field(name).type
        actual = table.schema.field(name).type
        if actual != expected:
            raise SourceError(path, f"column {name!r} has type {actual}, expected {expected}")
        if table.column(name).null_count:
            raise SourceError(path, f"column {name!r} has {table.column(name).null_count} null value(s)")
    return table


def column(table: pa.Table, name: str) -> np.ndarray:
    return table.column(name).to_numpy()


def _fill_from_chunks(out: np.ndarray, column: pa.ChunkedArray) -> None:
    """Copy a null-free fixed-width column into ``out`` [N] chunk by chunk, converting the dtype
    on the way (no intermediate concatenated array; float16 -> float32 is exact)."""
    row = 0
    for chunk in column.chunks:
        n = len(chunk)
        out[row : row + n] = np.frombuffer(
            chunk.buffers()[1], dtype=chunk.type.to_pandas_dtype(), count=n, offset=chunk.offset * chunk.type.byte_width
        )
        row += n


def poses_from_table(path: UPath, table: pa.Table) -> np.ndarray:
    """SE(3) [N,4,4] from the quaternion and translation columns; SourceError naming the first
    row that is not a pose (non-finite values or a zero quaternion)."""
    quat = np.stack([column(table, c) for c in POSE_COLUMNS[:4]], axis=1)
    t = np.stack([column(table, c) for c in POSE_COLUMNS[4:]], axis=1)
    finite = np.isfinite(quat).all(axis=1) & np.isfinite(t).all(axis=1)
    with np.errstate(over="ignore"):
        norm = np.linalg.norm(np.where(finite[:, None], quat, 0.0), axis=1)
    bad = ~finite | ~np.isfinite(norm) | (norm < 1e-6)
    if bad.any():
        raise SourceError(path, f"row {int(np.argmax(bad))}: not a pose (non-finite values or a zero quaternion)")
    return se3_from_quat_wxyz(quat, t).reshape(-1, 4, 4)


# Dataset layout


def log_dir(root: UPath, split: str | None, log_id: str) -> UPath:
    """A log's folder: ``<root>/<split>/<log_id>`` (AV2 Sensor), or ``<root>/<log_id>`` (TbV: split None)."""
    return root / log_id if split is None else root / split / log_id


def list_log_ids(root: UPath, split: str, reader: Reader | None = None) -> list[str]:
    """Log ids (directory names) under ``<root>/<split>``, sorted (one listing)."""
    split_dir = root / split
    with reading(reader) as r:
        if not r.is_folder(split_dir):
            raise SourceError(split_dir, "split folder not found")
        return r.folder_names(split_dir, "log folder")


def poses_path(log_dir: UPath) -> UPath:
    return log_dir / "city_SE3_egovehicle.feather"


def extrinsics_path(log_dir: UPath) -> UPath:
    return log_dir / "calibration" / "egovehicle_SE3_sensor.feather"


def intrinsics_path(log_dir: UPath) -> UPath:
    return log_dir / "calibration" / "intrinsics.feather"


def sweep_path(log_dir: UPath, timestamp_ns: int) -> UPath:
    return log_dir / "sensors" / "lidar" / f"{timestamp_ns}.feather"


def image_path(log_dir: UPath, camera: str, timestamp_ns: int) -> UPath:
    return log_dir / "sensors" / "cameras" / camera / f"{timestamp_ns}.jpg"


def read_jpeg(
    log_dir: UPath, camera: str, timestamp_ns: int, data: bytes | None = None, reader: Reader | None = None
) -> bytes:
    """The encoded bytes of one image (``data``: already fetched; else read by ``reader``), checked
    to be a JPEG (SourceError naming the file if not)."""
    path = image_path(log_dir, camera, timestamp_ns)
    if data is None:
        with reading(reader) as r:
            data = r.read(path)
    if (defect := jpeg_defect(data)) is not None:
        raise SourceError(path, defect)
    return data


def decode_jpeg(path: UPath, data: bytes, reduction: int, mode: str) -> np.ndarray:
    """One image's bytes decoded at 1/``reduction`` of its size (JPEG DCT scaling: only what that
    size needs is decoded) in PIL ``mode`` ("L": grey, "RGB"), uint8 [h,w] or [h,w,3]; SourceError
    naming ``path`` if it is not a JPEG or does not decode."""
    if (defect := jpeg_defect(data)) is not None:
        raise SourceError(path, defect)
    try:
        with PIL.Image.open(io.BytesIO(data)) as image:
            image.draft(mode, (image.width // reduction, image.height // reduction))
            return np.asarray(image.convert(mode))
    except (OSError, ValueError, PIL.UnidentifiedImageError) as err:
        raise SourceError(path, f"JPEG does not decode ({err})") from None


def _timestamps_from_stems(
    directory: UPath, suffix: str, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> np.ndarray:
    """The timestamps in the file names ``<timestamp_ns><suffix>`` of a folder (int64, sorted; empty
    without the folder). A remote folder is listed once, and its files' sizes and ETags are added
    to ``listing``."""
    stamps = []
    with reading(reader) as r:
        names = r.file_names(directory, listing)
    for name in names:
        if name.endswith(suffix):
            stem = name[: -len(suffix)]
            if not stem.isdigit():
                raise SourceError(directory / name, f"file name is not <timestamp_ns>{suffix}")
            stamps.append(int(stem))
    return np.sort(np.array(stamps, dtype=np.int64))


def list_sweep_timestamps_ns(
    log_dir: UPath, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> np.ndarray:
    """Sweep reference timestamps (ns, int64, sorted) from ``sensors/lidar/*.feather`` (a remote
    folder's sizes and ETags added to ``listing``)."""
    return _timestamps_from_stems(log_dir / "sensors" / "lidar", ".feather", listing, reader)


def list_image_timestamps_ns(
    log_dir: UPath, camera: str, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> np.ndarray:
    """Image timestamps (ns, int64, sorted) of one camera; empty if the camera folder is absent (a
    remote folder's sizes and ETags added to ``listing``)."""
    return _timestamps_from_stems(log_dir / "sensors" / "cameras" / camera, ".jpg", listing, reader)


# Tables


def read_ego_poses(
    log_dir: UPath, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Ego poses from ``city_SE3_egovehicle.feather`` (av2's ``city_SE3_ego``); ``listing``: the
    log folder's (a remote file is checked against it).

    Returns:
        timestamps_ns: int64 [N], strictly increasing.
        T_ego_city: float64 [N,4,4], maps ego-frame points to the city frame.
    """
    path = poses_path(log_dir)
    table = read_table(path, POSES_SCHEMA, listing=listing, reader=reader)
    if table.num_rows < 2:
        raise SourceError(path, f"needs at least 2 poses, has {table.num_rows}")
    timestamps_ns = column(table, "timestamp_ns")
    _check_increasing(path, timestamps_ns)
    return timestamps_ns, poses_from_table(path, table)


def _check_increasing(path: UPath, timestamps_ns: np.ndarray) -> None:
    """SourceError naming the first row whose timestamp repeats or goes back."""
    bad = np.flatnonzero(np.diff(timestamps_ns) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "duplicate" if timestamps_ns[i] == timestamps_ns[i - 1] else "non-monotonic"
        raise SourceError(
            path,
            f"{kind} timestamp_ns at row {i} ({timestamps_ns[i]} after {timestamps_ns[i - 1]});"
            " rows must be strictly increasing",
        )


def read_sensor_extrinsics(
    log_dir: UPath, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> dict[str, np.ndarray]:
    """Static extrinsics by sensor name: ``T_sensor_ego`` (av2's ``ego_SE3_sensor``), float64 [4,4],
    maps sensor-frame points to the ego frame."""
    path = extrinsics_path(log_dir)
    table = read_table(path, EXTRINSICS_SCHEMA, listing=listing, reader=reader)
    names = table.column("sensor_name").to_pylist()
    _check_sensor_names(path, names)
    return dict(zip(names, poses_from_table(path, table), strict=True))


def _check_sensor_names(path: UPath, names: list[str]) -> None:
    """Sensor names are unique, and safe as parts of output file names."""
    check_safe_names(path, names, "sensor_name")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise SourceError(path, f"sensor(s) listed more than once: {', '.join(repeated)}")


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of one camera (pixels), plus the original-lens radial coefficients."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    k1: float
    k2: float
    k3: float
    width_px: int
    height_px: int


def read_intrinsics(
    log_dir: UPath, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> dict[str, CameraIntrinsics]:
    """Camera intrinsics by camera name from ``calibration/intrinsics.feather``."""
    path = intrinsics_path(log_dir)
    rows = read_table(path, INTRINSICS_SCHEMA, listing=listing, reader=reader).to_pylist()
    _check_sensor_names(path, [row["sensor_name"] for row in rows])
    out = {}
    for row in rows:
        name = row.pop("sensor_name")
        intr = CameraIntrinsics(**row)
        values = np.array([intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px, intr.k1, intr.k2, intr.k3])
        if not (
            np.all(np.isfinite(values))
            and intr.fx_px > 0
            and intr.fy_px > 0
            and intr.width_px > 0
            and intr.height_px > 0
        ):
            raise SourceError(path, f"camera {name!r} has a non-finite or non-positive focal length or size")
        out[name] = intr
    return out


@dataclass(frozen=True)
class Sweep:
    """One lidar sweep as stored by AV2: ego frame, motion-compensated to ``timestamp_ns``.

    Attributes:
        timestamp_ns: sweep reference time (file stem), ns.
        xyz_ego_m: points in the ego frame at ``timestamp_ns``, float32 [N,3] (exact cast from
            float16, column-major).
        intensity: uint8 [N].
        laser_number: uint8 [N], 0..63; the two halves are the two VLP-32C units.
        offset_ns: int32 [N], per-point time relative to ``timestamp_ns``; None where the
            dataset has no per-point times (TbV).
    """

    timestamp_ns: int
    xyz_ego_m: np.ndarray
    intensity: np.ndarray
    laser_number: np.ndarray
    offset_ns: np.ndarray | None
    path: UPath | None = None  #: the file it was read from (for errors)

    def __len__(self) -> int:
        return len(self.laser_number)


def read_sweep(
    log_dir: UPath,
    timestamp_ns: int,
    with_offsets: bool = True,
    data: bytes | None = None,
    reader: Reader | None = None,
) -> Sweep:
    """Read one sweep (without ``offset_ns``: a TbV sweep, which has no such column); ``data``: its
    file's bytes, already fetched (else read by ``reader``).

    Raises SourceError on a bad schema or laser_number outside 0..63."""
    path = sweep_path(log_dir, timestamp_ns)
    columns = None if with_offsets else [n for n in LIDAR_SCHEMA.names if n != "offset_ns"]
    table = read_table(path, LIDAR_SCHEMA, columns=columns, data=data, reader=reader)
    # float16 is exact in float32; column-major keeps per-axis math contiguous
    xyz = np.empty((table.num_rows, 3), dtype=np.float32, order="F")
    for k, c in enumerate(("x", "y", "z")):
        _fill_from_chunks(xyz[:, k], table.column(c))
    laser_number = column(table, "laser_number")
    if laser_number.size and laser_number.max() > 63:
        raise SourceError(path, f"laser_number {int(laser_number.max())} outside 0..63")
    offset_ns = column(table, "offset_ns") if with_offsets else None
    if offset_ns is not None and offset_ns.size and offset_ns.min() < 0:
        raise SourceError(path, f"negative offset_ns {int(offset_ns.min())}")
    return Sweep(timestamp_ns, xyz, column(table, "intensity"), laser_number, offset_ns, path)


def read_sweeps(
    log_dir: UPath,
    timestamps_ns: Iterable[int],
    with_offsets: bool = True,
    listing: dict[str, ObjectInfo] | None = None,
    keep: bool = True,
    reader: Reader | None = None,
) -> Iterator[Sweep]:
    """:func:`read_sweep` of each sweep in turn, the files fetched ahead (:meth:`Reader.read_ahead`;
    ``keep``: spooled, as other jobs of the log read the sweeps again)."""
    stamps = [int(t) for t in timestamps_ns]
    with reading(reader) as r:
        fetched = r.read_ahead([sweep_path(log_dir, t) for t in stamps], listing, keep)
        for t, (_, data) in zip(stamps, fetched, strict=True):
            if isinstance(data, SourceError):
                raise data
            yield read_sweep(log_dir, t, with_offsets, data)


def read_images(
    log_dir: UPath,
    camera: str,
    timestamps_ns: Iterable[int],
    listing: dict[str, ObjectInfo] | None = None,
    keep: bool = False,
    reader: Reader | None = None,
) -> Iterator[tuple[UPath, bytes | SourceError]]:
    """Each image's bytes in turn, fetched ahead (:meth:`Reader.read_ahead`; ``keep``: spooled for
    the camera's copy job), or its SourceError."""
    with reading(reader) as r:
        yield from r.read_ahead([image_path(log_dir, camera, int(t)) for t in timestamps_ns], listing, keep)


def count_sweep_points(
    log_dir: UPath,
    timestamps_ns: Iterable[int],
    listing: dict[str, ObjectInfo] | None = None,
    reader: Reader | None = None,
) -> int:
    """Rows of the sweep files (their ``laser_number`` column only is read; remote files are fetched
    ahead, checked against their ``listing`` entries)."""
    paths = [sweep_path(log_dir, int(t)) for t in timestamps_ns]
    if is_local(log_dir):
        return sum(read_table(path, LIDAR_SCHEMA, columns=["laser_number"]).num_rows for path in paths)
    rows = 0
    with reading(reader) as r:
        for path, data in r.read_ahead(paths, listing):
            if isinstance(data, SourceError):
                raise data
            rows += read_table(path, LIDAR_SCHEMA, columns=["laser_number"], data=data).num_rows
    return rows


def read_sweep_offset_range_ns(
    log_dir: UPath, timestamp_ns: int, listing: dict[str, ObjectInfo] | None = None, reader: Reader | None = None
) -> tuple[int, int]:
    """(min, max) of a sweep's ``offset_ns`` column without converting the points (a remote file is
    fetched whole, checked against its ``listing`` entry)."""
    path = sweep_path(log_dir, timestamp_ns)
    table = read_table(path, LIDAR_SCHEMA, columns=["offset_ns"], listing=listing, reader=reader)
    offsets = column(table, "offset_ns")
    if offsets.size == 0:
        return 0, 0
    return int(offsets.min()), int(offsets.max())
