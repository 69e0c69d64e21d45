"""Results of a run: the paper's Table I per vehicle and task, and planned vs flown paths.

``table.md``: for every task, each vehicle's delay d, wait w, arrival and corrected
transit (``arrival_k - arrival_(k-1) - wait_(k-1) - d_k``), as in the paper's Table I.
``paths.svg``: the planned trajectories dashed and the flown paths solid, one colour per
vehicle, with time marks every 10 s (like the paper's Fig. 3), drawn without a plotting
library so the monitor image stays small.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def table(results: Mapping[str, Mapping[str, Any]]) -> str:
    """Markdown table: one row per task, delay/wait/arrival/transit per vehicle."""
    names = sorted(results)
    rows: dict[int, dict[str, Mapping[str, Any]]] = {}
    for name in names:
        for record in results[name].get("records", []):
            rows.setdefault(int(record["task"]), {})[name] = record
    header = (
        "| task | "
        + " | ".join(
            f"{what} {n}" for what in ("delay", "wait", "arrival", "transit") for n in names
        )
        + " |"
    )
    lines = [header, "|" + "---|" * (1 + 4 * len(names))]
    for task in sorted(rows):
        cells = []
        for what in ("delay_s", "wait_s", "arrival_s", "transit_s"):
            for n in names:
                record = rows[task].get(n)
                cells.append(f"{record[what]:.1f}" if record else "—")
        lines.append(f"| {task - 1}-{task} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def max_transit_error(results: Mapping[str, Mapping[str, Any]]) -> float:
    """Largest |corrected transit - planned transit| over every vehicle and task."""
    errors = [
        abs(r["transit_s"] - r["planned_transit_s"])
        for result in results.values()
        for r in result.get("records", [])
    ]
    return max(errors, default=float("nan"))


def svg(results: Mapping[str, Mapping[str, Any]], size: int = 640) -> str:
    """Planned (dashed) and flown (solid) paths seen from above, north up."""
    points: list[Sequence[float]] = []
    for result in results.values():
        points += [p[1:3] for p in result.get("plan", [])] + [
            p[1:3] for p in result.get("path", [])
        ]
    if not points:
        return '<svg xmlns="http://www.w3.org/2000/svg"/>'
    norths, easts = [p[0] for p in points], [p[1] for p in points]
    span = max(max(norths) - min(norths), max(easts) - min(easts), 1.0)
    margin = 40

    def xy(north: float, east: float) -> str:
        x = margin + (east - min(easts)) / span * (size - 2 * margin)
        y = size - margin - (north - min(norths)) / span * (size - 2 * margin)
        return f"{x:.1f},{y:.1f}"

    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{size}" height="{size}" '
        f'font-family="sans-serif" font-size="11"><rect width="100%" height="100%" fill="white"/>'
    ]
    for index, name in enumerate(sorted(results)):
        colour = COLOURS[index % len(COLOURS)]
        plan = results[name].get("plan", [])
        path = results[name].get("path", [])
        if plan:
            parts.append(
                f'<polyline points="{" ".join(xy(p[1], p[2]) for p in plan)}" fill="none" '
                f'stroke="{colour}" stroke-dasharray="6 4" stroke-width="1.5"/>'
            )
        if path:
            parts.append(
                f'<polyline points="{" ".join(xy(p[1], p[2]) for p in path)}" fill="none" '
                f'stroke="{colour}" stroke-width="2"/>'
            )
            for p in path:
                if abs(p[0] % 10.0) < 0.26 or abs(p[0] % 10.0 - 10.0) < 0.26:
                    x, y = xy(p[1], p[2]).split(",")
                    parts.append(f'<circle cx="{x}" cy="{y}" r="3" fill="{colour}"/>')
                    parts.append(f'<text x="{x}" y="{y}" dx="5" dy="-5">{p[0]:.0f}s</text>')
        parts.append(
            f'<text x="{margin}" y="{20 + 14 * index}" fill="{colour}">{name}: plan dashed, '
            "flown solid</text>"
        )
    parts.append("</svg>")
    return "\n".join(parts)


def write_results(results: Mapping[str, Mapping[str, Any]], output: Path) -> None:
    """``table.md``, ``results.json`` and ``paths.svg`` into ``output``."""
    output.mkdir(parents=True, exist_ok=True)
    (output / "table.md").write_text(table(results))
    (output / "results.json").write_text(json.dumps(results, indent=1))
    (output / "paths.svg").write_text(svg(results))
