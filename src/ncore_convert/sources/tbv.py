"""Argoverse 2 TbV (Trust, but Verify) on-disk layout; knows nothing of NCore.

TbV logs sit directly under the dataset root (``<root>/<log_id>``, log ids like
``VvgE5LfOzIahbS266MFW7tP2al00LhQn__Autumn_2020``) and use the Argoverse 2 Sensor file formats
(read with :mod:`ncore_convert.sources.argoverse2`), except:
- sweeps have no ``offset_ns`` column (``read_sweep(..., with_offsets=False)``);
- the cameras are the 7 ring cameras, the six other than ring_front_center at half resolution
  (read from ``calibration/intrinsics.feather``, never assumed);
- there is no ``annotations.feather``.
"""

from __future__ import annotations

from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.reader import Reader, reading


def list_log_ids(root: UPath, reader: Reader | None = None) -> list[str]:
    """Log ids (directory names) directly under the TbV root, sorted (one listing)."""
    with reading(reader) as r:
        if not r.is_folder(root):
            raise SourceError(root, "TbV root folder not found")
        return r.folder_names(root, "log folder")
