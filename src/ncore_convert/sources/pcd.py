"""Point Cloud Data (PCD v0.7) files as written by Open3D (OPV2V, V2XSet); no open3d dependency.

Reads ``DATA ascii`` and ``DATA binary`` files whose fields are scalars (COUNT 1), into one float32
column per field, vectorised (no per-line Python), and writes the ASCII layout OPV2V's files have
(:func:`write_pcd`). ``DATA binary_compressed`` is refused with a
clear error. Open3D stores a colour as a packed float ``rgb`` field (bytes b, g, r, 0); OPV2V puts
the lidar intensity in the red channel, so :func:`intensity_from_rgb` recovers it as R / 255.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.csv as pa_csv
from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.reader import Reader, reading

_TYPES = {
    ("F", 4): np.float32,
    ("F", 8): np.float64,
    ("U", 1): np.uint8,
    ("U", 2): np.uint16,
    ("U", 4): np.uint32,
    ("I", 1): np.int8,
    ("I", 2): np.int16,
    ("I", 4): np.int32,
}
HEADER_BYTES = 65536  #: a PCD header (at most 65 lines) fits in this


@dataclass(frozen=True)
class PcdHeader:
    fields: tuple[str, ...]
    dtypes: tuple[np.dtype, ...]
    points: int
    data: str  #: "ascii" or "binary"


def _parse_header(path: UPath, lines: list[bytes]) -> PcdHeader:
    entries: dict[str, list[str]] = {}
    for line in lines:
        words = line.decode("ascii", errors="replace").split()
        if words and not words[0].startswith("#"):
            entries[words[0].upper()] = words[1:]
    missing = [k for k in ("FIELDS", "SIZE", "TYPE", "POINTS", "DATA") if k not in entries]
    if missing:
        raise SourceError(path, f"PCD header lacks {', '.join(missing)}")
    fields, sizes, types = entries["FIELDS"], entries["SIZE"], entries["TYPE"]
    counts = entries.get("COUNT", ["1"] * len(fields))
    if not len(fields) == len(sizes) == len(types) == len(counts):
        raise SourceError(path, "PCD header FIELDS, SIZE, TYPE and COUNT differ in length")
    if len(set(fields)) < len(fields):
        raise SourceError(path, f"PCD header names a field twice ({' '.join(fields)})")
    if any(c != "1" for c in counts):
        raise SourceError(path, f"PCD fields with COUNT other than 1 are not supported ({counts})")
    try:
        dtypes = tuple(np.dtype(_TYPES[(t.upper(), int(s))]) for t, s in zip(types, sizes, strict=True))
        points = int(entries["POINTS"][0])
    except (KeyError, ValueError, IndexError):
        raise SourceError(path, f"unsupported PCD field types {list(zip(types, sizes, strict=True))}") from None
    data = entries["DATA"][0].lower() if entries["DATA"] else ""
    if data not in ("ascii", "binary"):
        raise SourceError(path, f"PCD DATA {data or '(none)'} is not supported (ascii and binary are)")
    return PcdHeader(tuple(fields), dtypes, points, data)


def _header_lines(path: UPath, raw: bytes) -> tuple[list[bytes], int]:
    """The header lines of a PCD file's bytes (through DATA) and the offset of its body."""
    lines, offset = [], 0
    while True:
        end = raw.find(b"\n", offset)
        if end < 0:
            raise SourceError(path, "PCD header has no DATA line")
        line = raw[offset:end]
        lines.append(line)
        offset = end + 1
        if line.strip().upper().startswith(b"DATA"):
            return lines, offset
        if len(lines) > 64:
            raise SourceError(path, "PCD header has no DATA line in its first 64 lines")


def read_pcd_header(path: UPath, reader: Reader | None = None) -> PcdHeader:
    """Only the header of a PCD file (its first 64 KiB are read: one ranged GET remotely, through
    ``reader``): fields, types and point count."""
    with reading(reader) as r:
        head = r.read(UPath(path), max_bytes=HEADER_BYTES)
    return _parse_header(path, _header_lines(path, head)[0])


def read_pcd(path: UPath) -> dict[str, np.ndarray]:
    """Read a PCD file: {field name: column [N]} in file order, each in its stored type (ascii:
    float fields as float32 parsed from text, integer fields as their type).

    Raises SourceError naming the file on a bad header, a short body or unsupported encodings.
    """
    return read_pcd_with_header(path)[1]


def read_pcd_with_header(
    path: UPath, data: bytes | None = None, reader: Reader | None = None
) -> tuple[PcdHeader, dict[str, np.ndarray]]:
    """:func:`read_pcd` and the file's header; ``data``: the file's bytes, already fetched (else
    read by ``reader``)."""
    raw = data
    if raw is None:
        with reading(reader) as r:
            raw = r.read(UPath(path))
    lines, offset = _header_lines(path, raw)
    header = _parse_header(path, lines)
    body = raw[offset:]
    if header.data == "binary":
        record = np.dtype([(f"f{i}", dt) for i, dt in enumerate(header.dtypes)])
        if len(body) < header.points * record.itemsize:
            raise SourceError(path, f"PCD body holds {len(body) // record.itemsize} of {header.points} points")
        table = np.frombuffer(body, dtype=record, count=header.points)
        return header, {name: table[f"f{i}"].copy() for i, name in enumerate(header.fields)}
    return header, _parse_ascii(path, header, body)


def _parse_ascii(path: UPath, header: PcdHeader, body: bytes) -> dict[str, np.ndarray]:
    """The ASCII body with Arrow's multi-threaded CSV reader, each field parsed straight into its
    type (correctly rounded, so the %.10g text Open3D writes gives back the exact float32)."""
    if not body.strip():
        if header.points:
            raise SourceError(path, f"PCD body is empty, the header says {header.points} points")
        return {name: np.zeros(0, dtype=dt) for name, dt in zip(header.fields, header.dtypes, strict=True)}
    first = body[: body.find(b"\n")].rstrip(b"\r")
    extra = max(0, len(first.split(b" ")) - len(header.fields))  # trailing separators give empty columns
    names = list(header.fields) + [f"_pad{i}" for i in range(extra)]
    try:
        table = pa_csv.read_csv(
            pa.py_buffer(body),
            read_options=pa_csv.ReadOptions(column_names=names, block_size=1 << 22),
            parse_options=pa_csv.ParseOptions(delimiter=" ", ignore_empty_lines=True),
            convert_options=pa_csv.ConvertOptions(
                column_types={n: pa.from_numpy_dtype(dt) for n, dt in zip(header.fields, header.dtypes, strict=True)},
                include_columns=list(header.fields),
            ),
        )
    except (pa.ArrowInvalid, pa.ArrowTypeError) as err:
        raise SourceError(
            path, f"PCD body is not {len(header.fields)} numbers per line ({str(err).splitlines()[0]})"
        ) from None
    if table.num_rows != header.points:
        raise SourceError(path, f"PCD body holds {table.num_rows} points, the header says {header.points}")
    return {name: table.column(name).to_numpy() for name in header.fields}


def red_from_rgb(rgb: np.ndarray) -> np.ndarray:
    """The red channel (uint8 [N]) of Open3D's packed float ``rgb`` (bytes b, g, r, 0)."""
    bits = np.ascontiguousarray(rgb, dtype=np.float32).view(np.uint32)
    return ((bits >> 16) & 0xFF).astype(np.uint8)


def intensity_from_rgb(rgb: np.ndarray) -> np.ndarray:
    """Intensity in [0, 1] from Open3D's packed float ``rgb`` (red channel / 255), float32 [N]."""
    return red_from_rgb(rgb).astype(np.float32) / np.float32(255.0)


#: The header of an OPV2V lidar file (Open3D's PCD: x, y, z and the packed colour, or a float intensity).
PCD_HEADER = (
    "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z {fourth}\nSIZE 4 4 4 4\nTYPE F F F F\n"
    "COUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
)


def rgb_from_red(red_u8: np.ndarray) -> np.ndarray:
    """Open3D's packed float ``rgb`` (bytes b, g, r, 0) with ``red_u8`` [N] in red, float32 [N]."""
    return (red_u8.astype(np.uint32) << 16).view(np.float32)


def write_pcd(path: UPath, xyz: np.ndarray, intensity: np.ndarray, fourth: str = "rgb", binary: bool = False) -> None:
    """A PCD as OpenCDA / Open3D write lidar frames: float32 x y z [N,3] and a fourth float32 field,
    ``rgb`` (the packed colour with ``intensity`` as uint8 [N] in red, as OPV2V stores it) or
    ``intensity`` (float [N] as given), in ``DATA ascii`` (every float32 with enough digits to be
    read back exactly) or ``DATA binary`` (little-endian records)."""
    if fourth not in ("rgb", "intensity"):
        raise ValueError(f"unknown PCD field {fourth!r}")
    last = rgb_from_red(intensity) if fourth == "rgb" else np.asarray(intensity, dtype=np.float32)
    table = np.column_stack([np.asarray(xyz, dtype=np.float32), last])
    header = PCD_HEADER.format(n=len(xyz), fourth=fourth, data="binary" if binary else "ascii").encode()
    if binary:
        UPath(path).write_bytes(header + table.astype("<f4").tobytes())
        return
    # one format over all the values: as np.savetxt(fmt="%.10g") writes them, at twice its speed
    body = ("%.10g %.10g %.10g %.10g\n" * len(table)) % tuple(table.astype(np.float64).ravel().tolist())
    UPath(path).write_bytes(header + body.encode())
