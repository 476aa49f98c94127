"""The gap sweep's table and its section in a reproduction's report (no experiment code, so
the report can read a sweep without importing the sweep)."""

from __future__ import annotations

import json
from pathlib import Path

from estimator_service.provenance import provenance_line

__all__ = ["FILTERS", "KINDS", "SWEEP_FOLDER", "describe", "report_lines"]

KINDS = ("param", "gp", "egp")
FILTERS = ("ekf", "ukf")
#: where a reproduction's report finds a sweep: ``gpbf gap-sweep --out <reproduce out>/gap_sweep``
SWEEP_FOLDER = "gap_sweep"


def describe(result: dict) -> list[str]:
    """The sweep as a markdown table."""
    cols = [f"{f}/{k}" for f in FILTERS for k in KINDS if k != "param"]
    lines = [
        "## Improvement over Param against the reality gap (Table 7 measure, %)",
        "",
        *([provenance_line(result["provenance"]), ""] if "provenance" in result else []),
        "| strength | " + " | ".join(c.upper() for c in cols) + " |",
        "| ---: | " + " | ".join("---:" for _ in cols) + " |",
    ]
    for strength, row in result["improvement_pct"].items():
        lines.append(f"| {strength} | " + " | ".join(f"{row[c]:.0f}" for c in cols) + " |")
    return lines


def report_lines(out: Path) -> list[str]:
    """The report section of the sweep in ``out/gap_sweep`` (none when it has not run)."""
    path = out / SWEEP_FOLDER / "gap_sweep.json"
    if not path.exists():
        return []
    result = json.loads(path.read_text())
    s = result["settings"]
    head = 4 if "provenance" in result else 2  # the heading (and the provenance line)
    return [
        *describe(result)[:head],
        f"Beyond the paper (`gpbf gap-sweep`, seed {s['seed']}, the sizes above): one scripted flight "
        "per reality strength in the lab's drafts (0: the textbook world the parametric model "
        "describes, 1: the lab, 2: twice its unmodelled physics), the same cross-validation, and "
        "the Table 7 measure of the GP and EGP filters against Param.",
        "",
        f"![gap sweep]({SWEEP_FOLDER}/gap_sweep.png)",
        "",
        *describe(result)[head:],
        "",
    ]
