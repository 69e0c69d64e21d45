"""Run Roost's benchmarks: ``python -m bench [module ...]`` (``make bench`` runs all).

Each module listed in :data:`MODULES` measures one area and returns figures; results
are merged into ``bench/results.json``, printed, and summarised in the README's table.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys

from bench.core import RESULTS, Figure, update_readme, write_results

MODULES: tuple[str, ...] = (
    "dev",
    "controlplane",
    "kine",
    "images",
    "mission",
    "leader",
    "cluster",
    "agent",
    "metrics",
    "link",
    "firmware",
    "vehicle",
    "hub",
    "hubcost",
    "hubsigning",
    "records",
    "standby",
    "params",
    "fence",
    "disruption",
    "sync",
    "node",
    "syncpods",
    "kind",
    "partition",
    "dashboard",
    "fleet",
    "fleetapi",
    "sandbox",
    "missionrecords",
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument(
        "modules",
        nargs="*",
        help=f"subset of {', '.join(MODULES)}; also nodearm64 (node's arm64 part alone)",
    )
    parser.add_argument(
        "--readme-only",
        action="store_true",
        help="only rewrite the README table from bench/results.json",
    )
    args = parser.parse_args(argv)
    if args.readme_only:
        update_readme(json.loads(RESULTS.read_text()))
        return 0
    figures: list[Figure] = []
    for name in args.modules or MODULES:
        module = importlib.import_module(f"bench.{name}")
        print(f"bench: running {name} ...", file=sys.stderr, flush=True)
        measured = module.run()
        figures.extend(measured)
        # kept as each module ends: a later module that fails or is stopped loses no
        # figure measured before it
        update_readme(write_results(measured))
    for fig in figures:
        verdict = {True: "meets", False: "MISSES", None: ""}[fig.meets_target()]
        print(f"{fig.name:45} {fig.value:12.3f} {fig.unit:6} target {fig.target:10} {verdict}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
