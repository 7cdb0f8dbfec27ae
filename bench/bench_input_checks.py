"""Benchmark what the bad-input checks cost on the read path. Not a test.

Side by side in one run, interleaved, medians over --repeat rounds:
1. a real AV2 sweep (the sample's first, ~95k points): pyarrow's feather read alone, and the same
   read plus ``Table.validate(full=True)``, as ``sources.argoverse2.read_table`` now does;
2. ``read_sweep`` as the converter calls it (read, schema, validate, columns to numpy);
3. 200 synthetic JPEGs of AV2 size (~0.4 MB): the bytes read alone, and read plus the
   start/end-marker check of ``read_jpeg``.

    python bench/bench_input_checks.py [--work /tmp/ncore-bench] [--repeat 15]
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.feather as feather
from bench_argoverse2 import bench_parser, work_dir
from upath import UPath

from ncore_convert.sources import argoverse2 as av2
from ncore_convert.sources.checks import jpeg_defect
from ncore_convert.sources.store import read_local


def sample_log() -> UPath:
    """The real AV2 sample's log, found as the tests find it."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from conftest import AV2_SAMPLE_LOG, find_av2_sample

    return UPath(find_av2_sample() / "val" / AV2_SAMPLE_LOG)


def jpegs(folder: Path, n: int = 200, size: int = 400_000) -> list[UPath]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        path = folder / f"{i}.jpg"
        if not path.exists():
            path.write_bytes(b"\xff\xd8" + rng.bytes(size) + b"\xff\xd9")
        paths.append(UPath(path))
    return paths


def each(paths: list[UPath], fn) -> None:
    """``fn`` on every path, keeping no result (both variants allocate and free alike)."""
    for path in paths:
        fn(path)


def timed(fn) -> float:
    started = time.perf_counter()
    fn()
    return time.perf_counter() - started


def main() -> None:
    args = bench_parser(__doc__, repeat=15).parse_args()
    log = sample_log()
    stamp = int(av2.list_sweep_timestamps_ns(log)[0])
    sweep = av2.sweep_path(log, stamp).path
    images = jpegs(work_dir(args) / "input-checks-jpegs")
    cases = {
        "feather read": lambda: feather.read_table(sweep, memory_map=True, use_threads=False),
        "feather read + validate(full=True)": lambda: feather.read_table(
            sweep, memory_map=True, use_threads=False
        ).validate(full=True),
        "read_sweep (all checks, to numpy)": lambda: av2.read_sweep(log, stamp),
        "200 JPEGs read": lambda: each(images, read_local),
        "200 JPEGs read + marker check": lambda: each(images, lambda p: jpeg_defect(read_local(p))),
    }
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(args.repeat):  # interleaved: drift and noise hit every case alike
        for name, fn in cases.items():
            times[name].append(timed(fn))
    med = {name: statistics.median(t) for name, t in times.items()}
    print(f"medians of {args.repeat}, interleaved")
    for name, seconds in med.items():
        print(f"  {name:40s} {seconds * 1e3:8.2f} ms")
    validated = med["feather read + validate(full=True)"] / med["feather read"]
    checked = med["200 JPEGs read + marker check"] / med["200 JPEGs read"]
    print(f"validate(full=True) / plain feather read: {validated:.2f}")
    print(f"JPEG marker check / plain read:           {checked:.3f}")


if __name__ == "__main__":
    main()
