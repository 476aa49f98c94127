"""Reports that keep their hand-written notes: a generated ``report.md`` is rewritten from
the run's data, and whatever follows :data:`NOTES_MARKER` in the report already there (the
reading of the tables, failed claims with their measured causes) is carried over unchanged."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from estimator_service.files import atomic_write_text

__all__ = ["NOTES_MARKER", "write_keeping_notes"]

NOTES_MARKER = "<!-- Written by hand below this line: kept when the report is regenerated. -->"


def _hand_written(path: Path) -> str:
    """The part of the report at ``path`` from :data:`NOTES_MARKER` on (marker included);
    empty when the file or the marker is missing."""
    if not path.exists():
        return ""
    text = path.read_text(encoding="utf-8")
    at = text.find(NOTES_MARKER)
    return "" if at < 0 else text[at:]


def write_keeping_notes(path: Path, lines: Sequence[str]) -> None:
    """Write the generated ``lines`` to ``path`` atomically, followed by the hand-written
    notes of the report already there (from :data:`NOTES_MARKER` on)."""
    generated = "\n".join(lines).rstrip("\n") + "\n"
    notes = _hand_written(path)
    atomic_write_text(path, generated + ("\n" + notes if notes else ""))
