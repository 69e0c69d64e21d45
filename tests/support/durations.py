"""The slowest tests of a whole ``make test``, across its pytest runs.

Each tier runs in a pytest of its own (each prints its own 25 slowest); every run also
writes a JUnit report, and ``python -m tests.support.durations REPORT...`` prints the 25
slowest test calls of all of them together, so the tier a slow test belongs in is
visible in one list.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from xml.etree import ElementTree


def slowest(reports: list[Path], count: int = 25) -> list[tuple[float, str]]:
    """``(seconds, node id)`` of the ``count`` slowest test cases in ``reports``."""
    cases: list[tuple[float, str]] = []
    for report in reports:
        for case in ElementTree.parse(report).iter("testcase"):
            name = f"{case.get('classname', '')}::{case.get('name', '')}"
            cases.append((float(case.get("time", "0")), name))
    return sorted(cases, reverse=True)[:count]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("reports", nargs="+", type=Path, help="JUnit XML reports")
    parser.add_argument("--count", type=int, default=25)
    args = parser.parse_args(argv)
    reports = [path for path in args.reports if path.is_file()]
    total = sum(
        float(case.get("time", "0"))
        for report in reports
        for case in ElementTree.parse(report).iter("testcase")
    )
    print(f"slowest {args.count} tests of {len(reports)} runs ({total:.0f} s of test time):")
    for seconds, name in slowest(reports, args.count):
        print(f"{seconds:9.2f}s  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
