"""Cheap checks of what was read: names safe to become output folders, and whether an encoded image
is complete.

Images are stored byte-identical, so the converter never decodes them; the checks catch the damage
that interrupted downloads cause (a file cut short, or not an image at all) from the first and last
bytes only.
"""

from __future__ import annotations

from ncore_convert.contract import SAFE_NAME
from ncore_convert.errors import SourceError


def check_safe_names(path: object, names: list[str], what: str) -> None:
    """SourceError naming ``path`` if a name could escape, or hide in, the output folder."""
    bad = [name for name in names if not SAFE_NAME.match(name)]
    if bad:
        raise SourceError(path, f"{what} {bad[0]!r} is not a safe name (letters, digits, '_', '-', '.'; 128 at most)")


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"  #: the IEND chunk's type and CRC, the last 8 bytes of a PNG
_JPEG_SOI = b"\xff\xd8"
_JPEG_EOI = b"\xff\xd9"
_TAIL_BYTES = 1024  #: encoders may pad after the end marker; a marker this close to the end counts


def jpeg_defect(data: bytes) -> str | None:
    """Why ``data`` is not a complete JPEG (missing start or end-of-image marker), or None."""
    if not data.startswith(_JPEG_SOI):
        return "not a JPEG file (missing SOI marker)"
    if data.rfind(_JPEG_EOI, max(2, len(data) - _TAIL_BYTES)) < 0:
        return "truncated JPEG (no EOI marker at the end)"
    return None


def png_defect(data: bytes) -> str | None:
    """Why ``data`` is not a complete PNG (missing signature or IEND chunk), or None."""
    if not data.startswith(PNG_SIGNATURE):
        return "not a PNG file (missing signature)"
    if data.rfind(_PNG_IEND, len(PNG_SIGNATURE), len(data)) < max(len(PNG_SIGNATURE), len(data) - _TAIL_BYTES):
        return "truncated PNG (no IEND chunk at the end)"
    return None
