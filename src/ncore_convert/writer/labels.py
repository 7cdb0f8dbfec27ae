"""How camera labels are stored (``--camera-labels``; docs/camera-labels.md): depth quantized RAW (uint16, 4 mm), the
masks as PNG; each label kind's NCore descriptor, and the stream that writes a camera's labels of one
kind. Part of the writer: :class:`~ncore_convert.writer.SequenceWriter` opens the streams.
"""

from __future__ import annotations

import io

import numpy as np
import PIL.Image
from ncore.data.v4 import CameraLabelsComponent
from ncore.impl.data.types import (
    CameraLabelDescriptor,
    LabelEncoding,
    LabelSchema,
    LabelSource,
    LabelType,
    QuantizationParams,
)

#: How depth labels are stored: RAW, quantized by the library to uint16 steps of 4 mm (``value =
#: stored * 0.004``: error <= 2 mm from the steps, 2.014 mm with the float32 values' own rounding;
#: range 262.14 m; the VLP-32C reaches 200 m and CARLA's lidars 120 m;
#: 0 stays 0 = no measurement). A depth beyond the range is not stored (0) and is counted in the
#: label's metadata (``DEPTH_BEYOND_RANGE``). The zero pixels compress to almost nothing (Blosc lz4
#: with bit shuffling, the library's choice); two bytes per labelled pixel instead of uint32
#: millimetres' four. The library quantizes through ``intermediate_dtype``: float32 here (a fifth of
#: float64's time on a full picture, and the same largest error). Readers de-quantize through float64.
DEPTH_STEP_M = 0.004
DEPTH_QUANTIZATION = QuantizationParams(
    quantized_dtype=np.dtype("uint16"), scale=DEPTH_STEP_M, offset=0.0, intermediate_dtype=np.dtype("float32")
)
MAX_DEPTH_M = np.iinfo(np.uint16).max * DEPTH_STEP_M  #: the deepest depth stored, m (262.14)
DEPTH_BEYOND_RANGE = "depth_beyond_range"  #: per-label metadata: pixels whose depth was beyond ``MAX_DEPTH_M``


#: How mask labels are stored: PNG (``IMAGE_ENCODED``), the library decoding them through PIL.
#: ``mask.dynamic`` is a 1-bit PNG (read back as uint8 0/1); ``segmentation.instance`` a grey PNG,
#: 8-bit when the label's indices allow, else 16-bit (read back as uint16: up to 65,535 instances
#: per sequence). zlib level 1: a third of level 6's time.
PNG_COMPRESS_LEVEL = 1
#: What each kind's component metadata says of its storage.
LABEL_STORAGE = {
    "depth": f"RAW, uint16 steps of 4 mm (NCore quantization scale {DEPTH_STEP_M:g}: error <= 2 mm); depths beyond"
    f" {MAX_DEPTH_M:.2f} m are not stored (0) and counted per label in {DEPTH_BEYOND_RANGE}",
    "dynamic": "PNG (IMAGE_ENCODED), 1-bit: read back as uint8 0/1",
    "instance": "PNG (IMAGE_ENCODED), grey, 8-bit where every index is below 256, else 16-bit: read back as uint16",
}
_PNG_LABELS = {
    "dynamic": (LabelType.MASK_DYNAMIC, np.dtype("uint8")),
    "instance": (LabelType.SEGMENTATION_INSTANCE, np.dtype("uint16")),
}


def label_descriptor(kind: str, camera_id: str, source: str) -> CameraLabelDescriptor:
    """The NCore descriptor of one ``contract.CAMERA_LABEL_KINDS`` label of ``camera_id``."""
    if kind == "depth":
        label_type = LabelType.DEPTH_Z_M
        schema = LabelSchema(dtype=np.dtype("float32"), encoding=LabelEncoding.RAW, quantization=DEPTH_QUANTIZATION)
    elif kind in _PNG_LABELS:
        label_type, dtype = _PNG_LABELS[kind]
        schema = LabelSchema(dtype=dtype, encoding=LabelEncoding.IMAGE_ENCODED, encoded_format="png")
    else:
        raise ValueError(f"unknown camera label kind {kind!r}")
    return CameraLabelDescriptor(
        camera_id=camera_id, label_type=label_type, label_schema=schema, label_source=LabelSource[source]
    )


def _png(data: np.ndarray, kind: str) -> bytes:
    """A mask label as PNG bytes: 1-bit for ``dynamic`` (``data`` bool or 0/1); for ``instance``
    (``data`` uint16) 8-bit grey when every index is below 256, else 16-bit (both read back as the
    same uint16 values; 8 bits take two thirds of the time)."""
    if kind == "dynamic":
        image = PIL.Image.fromarray(data.astype(bool))
    else:
        image = PIL.Image.fromarray(data.astype(np.uint8 if int(data.max(initial=0)) < 256 else np.uint16))
    out = io.BytesIO()
    image.save(out, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return out.getvalue()


class CameraLabelStream:
    """The labels of one kind for one camera, one per camera frame."""

    def __init__(self, writer: CameraLabelsComponent.Writer, kind: str) -> None:
        self._writer = writer
        self._kind = kind

    def store_label(self, data: np.ndarray, timestamp_us: int, generic_meta_data: dict | None = None) -> None:
        """Store the label of the camera frame ending at ``timestamp_us``, [height,width]: float32
        metres for ``depth`` (0 = none; beyond ``MAX_DEPTH_M``: not stored, counted in the label's
        ``DEPTH_BEYOND_RANGE``); bool for ``dynamic``; uint16 instance indices for ``instance``
        (0 = none). The masks are PNG-encoded here."""
        meta = dict(generic_meta_data or {})
        if self._kind == "depth":
            beyond = data > MAX_DEPTH_M
            if beyond.any():
                data = np.where(beyond, np.float32(0.0), data)
                meta[DEPTH_BEYOND_RANGE] = int(beyond.sum())
            stored = data
        else:
            stored = _png(data, self._kind)
        self._writer.store_label(stored, int(timestamp_us), meta)

    def set_meta(self, generic_meta_data: dict) -> None:
        """Replace the component-level metadata (the generator and its parameters; the storage is
        added here)."""
        self._writer.set_generic_data({}, {**generic_meta_data, "storage": LABEL_STORAGE[self._kind]})
