"""How camera labels are stored (``--camera-labels``; docs/camera-labels.md): depth quantized RAW, the
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

#: How depth labels are stored: RAW, quantized to whole millimetres in uint32 (no range cap; 0 stays
#: 0 = no measurement). The zero pixels compress to almost nothing (Blosc lz4 with bit shuffling,
#: the library's choice). The library quantizes through ``intermediate_dtype``: float32 here (a
#: fifth of float64's time on a full picture; the error of a value at most 0.52 mm instead of 0.5
#: at 250 m). Readers de-quantize through float64 (the field is not stored).
DEPTH_QUANTIZATION = QuantizationParams(
    quantized_dtype=np.dtype("uint32"), scale=0.001, offset=0.0, intermediate_dtype=np.dtype("float32")
)


#: How mask labels are stored: PNG (``IMAGE_ENCODED``), the library decoding them through PIL.
#: ``mask.dynamic`` is a 1-bit PNG (read back as uint8 0/1); ``segmentation.instance`` a grey PNG,
#: 8-bit when the label's indices allow, else 16-bit (read back as uint16: up to 65,535 instances
#: per sequence). zlib level 1: a third of level 6's time.
PNG_COMPRESS_LEVEL = 1
#: What each kind's component metadata says of its storage.
LABEL_STORAGE = {
    "depth": "RAW, uint32 millimetres (NCore quantization scale 0.001: error <= 0.52 mm)",
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
        metres for ``depth`` (0 = none); bool for ``dynamic``; uint16 instance indices for
        ``instance`` (0 = none). The masks are PNG-encoded here."""
        stored = data if self._kind == "depth" else _png(data, self._kind)
        self._writer.store_label(stored, int(timestamp_us), generic_meta_data or {})

    def set_meta(self, generic_meta_data: dict) -> None:
        """Replace the component-level metadata (the generator and its parameters; the storage is
        added here)."""
        self._writer.set_generic_data({}, {**generic_meta_data, "storage": LABEL_STORAGE[self._kind]})
