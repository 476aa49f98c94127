"""Resumable experiments: a run records its settings in its output folder and keeps what it
finished (model folders, JSON scores), so running the same command again continues it."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from estimator_service.files import atomic_write_text
from estimator_service.store import MANIFEST_FILE

__all__ = ["SETTINGS_FILE", "fold_scores_path", "kept", "resume_check", "trained"]

SETTINGS_FILE = "settings.json"


def resume_check(out: Path, settings: dict) -> None:
    """Record an experiment's ``settings`` in ``out/settings.json``; a folder that holds a run
    with other settings is refused, naming them (its models would be mixed into this run's
    tables), and so is one with models but no record (a run older than the record)."""
    path = out / SETTINGS_FILE
    mine = json.loads(json.dumps(settings))  # tuples as lists, as read back
    if not path.exists() and any(out.glob("models_*")):
        raise ValueError(f"out: {out} holds models from a run that recorded no settings; use a new folder")
    if path.exists():
        theirs = json.loads(path.read_text())
        if theirs != mine:
            diff = sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))
            msg = f"out: {out} holds a run with other settings ({', '.join(diff)}); use a new folder"
            raise ValueError(msg)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(mine, indent=2))


def trained(folder: Path) -> bool:
    """Whether ``folder`` holds complete models (``train_models`` writes the manifest last)."""
    return (folder / MANIFEST_FILE).exists()


def kept(path: Path, compute: Callable[[], dict]) -> dict:
    """``compute()``, kept as JSON at ``path`` (written atomically): a resumed run reads it
    back instead of computing again."""
    if path.exists():
        return json.loads(path.read_text())
    res = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(res))
    return res


def fold_scores_path(folder: Path) -> Path:
    """Where a fold's scores are kept: ``fold_scores/<folder name>.json`` beside the models."""
    return folder.parent / "fold_scores" / f"{folder.name}.json"
