"""The shape of a benchmark figure and how figures are written.

Every benchmark module in this package exposes ``run() -> list[Figure]``. The runner
(``python -m bench``) collects the figures of all modules into ``bench/results.json``
so they can be compared over time by name. Figures are measurements, never test
assertions: a figure that misses its target is reported, not failed.
"""

from __future__ import annotations

import json
import platform
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).with_name("results.json")
README = Path(__file__).resolve().parents[1] / "README.md"
TABLE_START = "<!-- bench-table -->"
TABLE_END = "<!-- /bench-table -->"


@dataclass(frozen=True)
class Figure:
    """One measured figure."""

    name: str
    value: float
    unit: str
    target: str
    command: str
    note: str = ""

    def meets_target(self) -> bool | None:
        """True/False when the target is a simple bound such as "<= 5", else None."""
        for op in ("<=", ">=", "=="):
            if self.target.startswith(op):
                bound = float(self.target[len(op) :].split()[0])
                return {
                    "<=": self.value <= bound,
                    ">=": self.value >= bound,
                    "==": self.value == bound,
                }[op]
        return None


def write_results(figures: list[Figure], path: Path = RESULTS) -> dict[str, Any]:
    """Merge ``figures`` into the results file (other modules' figures are kept)."""
    existing: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    by_name = {f["name"]: f for f in existing.get("figures", [])}
    for fig in figures:
        by_name[fig.name] = {**asdict(fig), "meets_target": fig.meets_target()}
    doc = {
        "machine": f"{platform.machine()} {platform.system()}, python {platform.python_version()}",
        "updated": datetime.now(UTC).replace(microsecond=0).isoformat(),
        "figures": sorted(by_name.values(), key=lambda f: f["name"]),
    }
    path.write_text(json.dumps(doc, indent=2) + "\n")
    return doc


def _fmt(value: float) -> str:
    return f"{value:.3g}" if abs(value) < 1000 else f"{value:.0f}"


def markdown_table(doc: dict[str, Any]) -> str:
    """The results file as a Markdown table (what the README shows)."""
    verdicts = {True: "✅ meets", False: "❌ misses", None: "—"}
    rows = [
        "| figure | value | target | | note |",
        "|---|---|---|---|---|",
    ]
    for fig in doc["figures"]:
        note = " ".join(str(fig.get("note", "")).split())
        rows.append(
            f"| `{fig['name']}` | {_fmt(fig['value'])} {fig['unit']} | {fig['target']} "
            f"| {verdicts[fig['meets_target']]} | {note} |"
        )
    rows.append("")
    rows.append(f"Measured on {doc['machine']}; updated {doc['updated']}.")
    return "\n".join(rows)


def update_readme(doc: dict[str, Any], readme: Path = README) -> None:
    """Replace the README's table between the bench-table markers with ``doc``'s figures."""
    text = readme.read_text()
    if TABLE_START not in text:
        return
    head, rest = text.split(TABLE_START, 1)
    tail = rest.split(TABLE_END, 1)[1] if TABLE_END in rest else ""
    readme.write_text(f"{head}{TABLE_START}\n{markdown_table(doc)}\n{TABLE_END}{tail}")
