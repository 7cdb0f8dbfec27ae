"""Depth labels' bytes under the library's codec and under others, on the same labels (issue 52 item 4).

The library stores a RAW label through ``store_label`` with a fixed compressor (Blosc lz4, level 5,
bit shuffle), and applies NCore's quantization only to RAW labels (an ``IMAGE_ENCODED`` label is
decoded by PIL and never de-quantized). This converts the 15 s synthetic AV2 log with
``--camera-labels depth`` (or reads ``--sequence``), reads every ``--every``-th depth label back
through ``SequenceLoaderV4``, quantizes it again as the writer did (uint16 steps of 4 mm) and
encodes the same arrays with each codec, against the camera stores' bytes per frame.

    python bench/bench_depth_codecs.py [--sequence DIR] [--every 10]
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np
from bench_argoverse2 import bench_parser, work_dir
from bench_camera_labels import _bytes
from bench_speed import ours, speed_log, timed
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from numcodecs import Blosc
from PIL import Image
from upath import UPath

from ncore_convert.writer.labels import DEPTH_QUANTIZATION


def _png16(counts: np.ndarray) -> int:
    buffer = io.BytesIO()
    Image.fromarray(counts).save(buffer, format="png", compress_level=9)
    return len(buffer.getvalue())


#: name -> bytes of one quantized label (uint16 [H,W]); the first is the library's own choice.
CODECS = {
    "Blosc lz4 5 bitshuffle (the library's)": lambda q: len(Blosc("lz4", 5, Blosc.BITSHUFFLE).encode(q)),
    "Blosc zstd 5 bitshuffle": lambda q: len(Blosc("zstd", 5, Blosc.BITSHUFFLE).encode(q)),
    "Blosc zstd 9 bitshuffle": lambda q: len(Blosc("zstd", 9, Blosc.BITSHUFFLE).encode(q)),
    "PNG 16-bit, zlib 9": _png16,
}


def main() -> None:
    parser = bench_parser(__doc__, repeat=1)
    parser.add_argument("--sequence", help="a converted sequence with depth labels (default: the 15 s log)")
    parser.add_argument("--every", type=int, default=10, help="read every n-th depth label")
    args = parser.parse_args()
    if args.sequence:
        sequence = Path(args.sequence)
    else:
        work = work_dir(args)
        root, log_id = speed_log(work)
        seconds = timed([*ours(root, work / "codecs", False), "--camera-labels", "depth"], work / "codecs")
        print(f"  converted the 15 s log with depth labels in {seconds:.1f} s", flush=True)
        sequence = work / "codecs" / log_id
    manifests = sorted(sequence.glob("*.json"))
    if not manifests:
        sys.exit(f"{sequence}: no sequence manifest (*.json)")
    loader = SequenceLoaderV4(SequenceComponentGroupsReader([UPath(manifests[0])]))
    q = DEPTH_QUANTIZATION
    frames = sum(len(loader.get_camera_sensor(cam).frames_timestamps_us) for cam in loader.camera_ids)
    image_bytes_per_frame = sum(_bytes(sequence, f"ncore4-{cam}.zarr") for cam in loader.camera_ids) / frames
    stored = _bytes(sequence, "ncore4-depth.z@")
    totals, labels, labelled = dict.fromkeys(CODECS, 0), 0, 0
    depth_ids = [name for name in loader.camera_labels_ids if name.startswith("depth.z@")]
    all_labels = sum(len(loader.get_camera_labels(name).label_timestamps_us) for name in depth_ids)
    for name in depth_ids:
        stream = loader.get_camera_labels(name)
        for t_us in stream.label_timestamps_us[:: args.every]:
            depth_m = stream.get_label(int(t_us)).get_data()
            counts = np.round((depth_m.astype(q.intermediate_dtype) - q.offset) / q.scale).astype(q.quantized_dtype)
            for codec, encode in CODECS.items():
                totals[codec] += encode(counts)
            labels += 1
            labelled += int(np.count_nonzero(counts))
    print(f"{sequence.name}: {labels} of {all_labels} depth labels, {labelled / labels:,.0f} labelled pixels each;")
    per_label_stored = stored / all_labels
    print(f"  camera stores {image_bytes_per_frame / 1e3:.1f} kB a frame;", end=" ")
    print(f"depth stores {per_label_stored / 1e3:.1f} kB a label")
    for codec, total in totals.items():
        per_label = total / labels
        ratio = per_label / image_bytes_per_frame
        print(
            f"  {codec:<40} {per_label / 1e3:7.1f} kB a label  {8 * total / labelled:5.2f} bits a labelled pixel"
            f"  {ratio:.3f} of the camera stores (issue 52: <= 0.30)"
        )


if __name__ == "__main__":
    main()
