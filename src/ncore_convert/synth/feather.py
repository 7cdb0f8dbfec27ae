"""Feather files as Argoverse 2's own are written (pandas metadata included), for the synthetic logs."""

from __future__ import annotations

import json

import pyarrow as pa
import pyarrow.feather as feather
from upath import UPath


def _pandas_metadata(schema: pa.Schema) -> bytes:
    columns = [
        {
            "name": f.name,
            "field_name": f.name,
            "pandas_type": _pandas_type(f.type),
            "numpy_type": "object" if f.type == pa.string() else f.type.to_pandas_dtype().__name__,
            "metadata": None,
        }
        for f in schema
    ]
    meta = {
        "index_columns": [],
        "column_indexes": [],
        "columns": columns,
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "1.3.4",
    }
    return json.dumps(meta).encode()


def _pandas_type(t: pa.DataType) -> str:
    return "unicode" if t == pa.string() else t.to_pandas_dtype().__name__


def write_feather_table(path: UPath, schema: pa.Schema, columns: dict[str, object]) -> None:
    """Write a feather V2 file the way AV2 did (pyarrow, lz4, 64k-row batches, pandas metadata)."""
    schema = schema.with_metadata({b"pandas": _pandas_metadata(schema)})
    table = pa.table(
        {name: pa.array(columns[name], type=schema.field(name).type) for name in schema.names}, schema=schema
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        feather.write_feather(table, f, compression="lz4", chunksize=65536)
