"""The test suite's time per file, from a JUnit XML report (``pytest --junitxml FILE``), slowest
first, with the tests per file and the total; given two reports, side by side (before, after).

    .venv/bin/python -m pytest -q -n auto --dist loadfile --junitxml /tmp/suite.xml
    python bench/suite_table.py /tmp/before.xml [/tmp/after.xml]

Seconds are each test's setup + call + teardown, summed per file (what the workers spent on it).
"""

from __future__ import annotations

import argparse
import collections
import xml.etree.ElementTree as ET


def per_file(report: str) -> tuple[collections.Counter, collections.Counter]:
    seconds, tests = collections.Counter(), collections.Counter()
    for case in ET.parse(report).iter("testcase"):
        name = (case.get("classname") or "?").split(".")[-1]
        seconds[name] += float(case.get("time") or 0.0)
        tests[name] += 1
    return seconds, tests


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("reports", nargs="+", help="one or two JUnit XML reports")
    args = parser.parse_args()
    tables = [per_file(r) for r in args.reports[:2]]
    names = sorted(set().union(*(s for s, _ in tables)), key=lambda n: -tables[-1][0][n])
    print(f"{'file':34s}" + "".join(f"{'tests':>7s}{'s':>9s}" for _ in tables))
    for name in names:
        print(f"{name:34s}" + "".join(f"{t[name]:7d}{s[name]:9.1f}" for s, t in tables))
    print(f"{'total':34s}" + "".join(f"{sum(t.values()):7d}{sum(s.values()):9.1f}" for s, t in tables))


if __name__ == "__main__":
    main()
