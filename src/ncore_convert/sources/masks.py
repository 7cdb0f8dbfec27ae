"""User-supplied camera masks (``--ego-masks DIR``): ``<DIR>/<camera_id>.png``, binary, the camera's
size, non-zero = ego. Read and checked here; every problem is one line naming the file."""

from __future__ import annotations

import io

import numpy as np
import PIL.Image
from upath import UPath

from ncore_convert.errors import UsageError
from ncore_convert.sources.reader import Reader, reading

#: Image modes a binary mask may have: 1-bit, or 8-bit grey with at most one non-zero value.
MASK_MODES = ("1", "L")


def read_mask_folder(
    folder: UPath, camera_sizes: dict[str, tuple[int, int]], reader: Reader | None = None
) -> dict[str, bytes]:
    """The PNG bytes of every ``<camera_id>.png`` in ``folder`` (one listing, one read per file,
    through ``reader``), checked against the cameras.

    Args:
        camera_sizes: camera id -> (width, height) of the cameras being converted.

    Returns:
        camera id -> the file's bytes (stored as given, so the mask round-trips bit-exactly).

    Raises UsageError (file: cause) for a PNG that names no camera, does not decode, is not binary
    or not the camera's size.
    """
    folder = UPath(folder)
    out = {}
    with reading(reader) as r:
        listing: dict = {}
        names = sorted(name for name in r.file_names(folder, listing) if name.endswith(".png"))
        files = [(folder / name, r.read(folder / name, listing)) for name in names]
    for path, data in files:
        camera = path.name[: -len(".png")]
        if camera not in camera_sizes:
            raise UsageError(f"{path}: no camera {camera!r} in this log (cameras: {', '.join(sorted(camera_sizes))})")
        try:
            with PIL.Image.open(io.BytesIO(data), formats=["PNG"]) as image:
                mode, size, pixels = image.mode, image.size, np.asarray(image)
        except (OSError, ValueError, PIL.UnidentifiedImageError) as err:
            raise UsageError(f"{path}: not a readable PNG ({err})") from None
        if mode not in MASK_MODES or len(np.unique(pixels[pixels != 0])) > 1:
            raise UsageError(
                f"{path}: not a binary mask (mode {mode}; expected 1-bit or 8-bit with one non-zero value)"
            )
        if size != camera_sizes[camera]:
            raise UsageError(
                f"{path}: {size[0]}x{size[1]} px, but {camera} is {camera_sizes[camera][0]}x{camera_sizes[camera][1]}"
            )
        out[camera] = data
    return out
