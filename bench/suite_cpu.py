"""Where the test suite's CPU goes, every process counted (the pytest workers, the CLI processes the
tests start, their fork servers and pool workers, Ray, moto): a summary of a py-spy recording.

The suite keeps both cores busy (97 % of the CPU on 2026-12-07), so only less work makes it faster;
the JUnit per-file table (``suite_table.py``) shows each file's wall time, not what its processes
cost. Record the whole run with py-spy (``pip install py-spy``; not a dependency of the project):

    py-spy record --subprocesses --nonblocking --rate 50 --format raw -o /tmp/suite.spy -- \\
        .venv/bin/python -m pytest -q -n auto --dist loadfile --no-loadscope-reorder
    python bench/suite_cpu.py /tmp/suite.spy

Prints CPU seconds (samples / rate) by process kind, by activity (importing, the generator, the
converters, validation, hypothesis, the tests' own code) and by test file.
"""

from __future__ import annotations

import argparse
import collections
import re

#: activity of a stack: the first rule whose text appears in it (order matters: an import inside
#: a conversion is an import)
ACTIVITIES = (
    ("import", ("importlib._bootstrap",)),
    ("generator (synth/)", ("ncore_convert/synth/",)),
    ("hypothesis", ("hypothesis/",)),
    ("validation (validate/)", ("validate_sequence", "validate_tree", "lidar_checks_job", "check_coregistration")),
    ("conversion (converters/, writer/)", ("ncore_convert/converters/", "ncore_convert/writer/")),
    ("views, preview", ("ncore_convert/views/", "ncore_convert/preview")),
    ("test code", ("tests/", "test_")),
)


def process_kind(stack: str) -> str:
    procs = [f for f in stack.split(";") if f.startswith("process ")]
    command = procs[-1] if procs else ""
    for kind, mark in (
        ("fork server and pool workers", "forkserver"),
        ("CLI processes", "ncore-convert"),
        ("moto", "moto"),
        ("Ray", "ray"),
        ("pytest workers", "-u -c import sys"),  # xdist (its command holds a ";": cut there)
    ):
        if mark in command:
            return kind
    return "other"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", help="py-spy --format raw output")
    parser.add_argument("--rate", type=float, default=50.0, help="the recording's samples per second")
    args = parser.parse_args()
    kinds, activities, files = collections.Counter(), collections.Counter(), collections.Counter()
    with open(args.recording, errors="replace") as lines:
        for line in lines:
            stack, _, count = line.rstrip("\n").rpartition(" ")
            if not count.isdigit():
                continue
            n = int(count)
            kinds[process_kind(stack)] += n
            activity = next((name for name, marks in ACTIVITIES if any(m in stack for m in marks)), "other")
            activities[activity] += n
            test_file = re.search(r"\((?:tests/)?(test_[a-z_0-9]+)\.py:", stack)
            files[test_file.group(1) if test_file else "(no test frame: CLI processes, workers)"] += n
    total = sum(kinds.values())
    for title, table in (("process", kinds), ("activity", activities), ("test file", files)):
        print(f"{title:44s} {'CPU s':>8s} {'share':>6s}")
        for name, n in table.most_common(25):
            print(f"  {name:42s} {n / args.rate:8.1f} {n / total:6.1%}")
    print(f"{'total':44s} {total / args.rate:8.1f}")


if __name__ == "__main__":
    main()
