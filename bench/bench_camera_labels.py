"""Camera labels (``--camera-labels``) on the 15 s synthetic AV2 log: what they cost and weigh.

Whole commands (``--no-validate``, so the figures are the conversion's own), with and without the
labels (``--kinds``, default all three), interleaved, medians of ``--repeat``; the difference per
camera frame; the labels' own seconds per kind from the conversion report; and, from the last
labelled output, each kind's stores' bytes against the camera stores'.

    python bench/bench_camera_labels.py --repeat 3 [--kinds depth,dynamic,instance]
"""

from __future__ import annotations

import statistics
import sys
from pathlib import Path

from bench_argoverse2 import bench_parser, work_dir
from bench_speed import ours, speed_log, timed
from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4
from upath import UPath

from ncore_convert.contract import CAMERA_LABEL_QUALIFIED


def _bytes(folder: Path, part: str) -> int:
    """Bytes of the stores of ``folder`` whose names contain ``part``."""
    return sum(p.stat().st_size for p in folder.rglob("*.zarr.itar") if part in p.name)


def main() -> None:
    parser = bench_parser(__doc__, repeat=3)
    parser.add_argument("--kinds", default="depth,dynamic,instance", help="--camera-labels value to measure")
    args = parser.parse_args()
    work = work_dir(args)
    root, log_id = speed_log(work)
    with_labels = f"--camera-labels {args.kinds}"
    rows: dict[str, list[float]] = {"without labels": [], with_labels: []}
    for round_ in range(args.repeat):
        plain = timed(ours(root, work / "labels-plain", False), work / "labels-plain")
        labelled = timed([*ours(root, work / "labels", False), "--camera-labels", args.kinds], work / "labels")
        rows["without labels"].append(plain)
        rows[with_labels].append(labelled)
        print(f"  round {round_ + 1}: without {plain:.2f} s, with labels {labelled:.2f} s", flush=True)
    med = {label: statistics.median(seconds) for label, seconds in rows.items()}
    sequence = work / "labels" / log_id
    loader = SequenceLoaderV4(SequenceComponentGroupsReader([UPath(sequence / f"{log_id}.json")]))
    frames = sum(len(loader.get_camera_sensor(cam).frames_timestamps_us) for cam in loader.camera_ids)
    labels = sum(len(loader.get_camera_labels(label).label_timestamps_us) for label in loader.camera_labels_ids)
    image_bytes = sum(_bytes(sequence, f"ncore4-{cam}.zarr") for cam in loader.camera_ids)
    extra_s = med[with_labels] - med["without labels"]
    print(f"15 s AV2 log, whole commands (--no-validate), medians of {args.repeat}:")
    for label, seconds in med.items():
        print(f"  {label:<40} {seconds:7.2f} s")
    print(f"  with / without = {med[with_labels] / med['without labels']:.2f} (issue 41: <= 2)")
    print(f"  {labels} labels for {frames} camera frames: {1e3 * extra_s / max(frames, 1):.1f} ms more per frame")
    total = 0
    for kind in args.kinds.split(","):
        kind_bytes = _bytes(sequence, f"ncore4-{CAMERA_LABEL_QUALIFIED[kind]}@")
        total += kind_bytes
        print(f"  bytes {kind}: {kind_bytes / 1e6:.1f} MB ({kind_bytes / max(image_bytes, 1):.3f} of the images)")
    print(
        f"  bytes: labels {total / 1e6:.1f} MB, images {image_bytes / 1e6:.1f} MB"
        f" (labels / images = {total / max(image_bytes, 1):.2f}; issue 41: <= 0.25)"
    )


if __name__ == "__main__":
    sys.exit(main())
