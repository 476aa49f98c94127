"""The model store: the one module that writes and reads a model folder as a whole.

A model folder holds ``system.json`` (the :class:`~estimator_service.system.System` the
models describe), the model files (``parametric.npz``, ``prediction_<kind>.npz``,
``observation_<kind>_cam<k>.npz`` per sensor, see :mod:`estimator_service.factory`),
optionally ``calibration.json``, and ``manifest.json``, written last, which lists every
file with its size and SHA-256.

A folder is replaced as a whole, never left mixed: :func:`writing` hands out a staging
folder beside the destination; when the block ends without an error the manifest is
written and the staging folder is swapped in (the old folder is moved aside and then
deleted); on an error the staging folder is deleted and the old folder is untouched. A
process killed mid-write leaves a ``.<name>.staging-*`` folder, which a later
:func:`writing` of the same destination removes once it is an hour old (a younger one may
belong to a training still running). :func:`check_folder` (used by
everything that loads models to serve or track) refuses a folder without a manifest or
whose files differ from it; its hash is the ``model_version`` the service reports.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from estimator_service.files import STALE_AFTER_S, atomic_write_text, current_umask
from estimator_service.models.calibration import CALIBRATION_FILE
from estimator_service.system import DescriptionError, System

__all__ = [
    "MANIFEST_FILE",
    "SYSTEM_FILE",
    "ModelStoreError",
    "check_folder",
    "model_version",
    "read_system",
    "seal",
    "writing",
]

MANIFEST_FILE = "manifest.json"
SYSTEM_FILE = "system.json"
STORE_FORMAT = "gpbf-models"
STORE_VERSION = 1


class ModelStoreError(ValueError):
    """A model folder is missing, incomplete or inconsistent."""


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def seal(folder: str | os.PathLike[str], system: System) -> dict[str, Any]:
    """Write ``system.json`` and then the manifest of every file in ``folder``.

    :func:`writing` calls it; call it yourself only for a folder you assembled by hand.
    """
    folder = Path(folder)
    atomic_write_text(folder / SYSTEM_FILE, system.to_json())
    files = {
        p.name: {"bytes": p.stat().st_size, "sha256": _sha256(p)}
        for p in sorted(folder.iterdir())
        if p.is_file() and p.name != MANIFEST_FILE and not p.name.startswith(".")
    }
    manifest = {"format": STORE_FORMAT, "version": STORE_VERSION, "files": files}
    atomic_write_text(folder / MANIFEST_FILE, json.dumps(manifest, indent=1))
    return manifest


@contextmanager
def writing(out_dir: str | os.PathLike[str], system: System) -> Iterator[Path]:
    """Stage a new model folder for ``out_dir``; swapped in whole when the block succeeds."""
    out = Path(out_dir).absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.exists() and not out.is_dir():
        raise ModelStoreError(f"model folder {os.fspath(out_dir)!r} exists and is not a folder")
    for stale in out.parent.glob(f".{out.name}.staging-*"):  # a training killed outright
        if time.time() - stale.stat().st_mtime >= STALE_AFTER_S:  # a younger one may be running
            shutil.rmtree(stale, ignore_errors=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    try:
        yield stage
        seal(stage, system)
        _swap(stage, out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


def _swap(stage: Path, out: Path) -> None:
    """Put ``stage`` at ``out``; an existing ``out`` is moved aside first, then removed."""
    os.chmod(stage, 0o777 & ~current_umask())
    old = None
    if out.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
        os.replace(out, old / out.name)
    os.replace(stage, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def read_system(folder: str | os.PathLike[str]) -> System:
    """The system description of a model folder."""
    path = Path(folder) / SYSTEM_FILE
    if not path.exists():
        raise ModelStoreError(
            f"model folder {os.fspath(folder)!r} has no {SYSTEM_FILE}: train it with 'gpbf train'"
        )
    try:
        return System.from_json(path.read_text(encoding="utf-8"), f"{path}")
    except DescriptionError as exc:
        raise ModelStoreError(str(exc)) from None


def check_folder(folder: str | os.PathLike[str], *, hashes: bool = False) -> dict[str, Any]:
    """The folder's manifest, after checking that every listed file is there with its size
    (and, with ``hashes``, its SHA-256) and that no model file and no noise calibration is
    unlisted."""
    folder = Path(folder)
    where = f"model folder {os.fspath(folder)!r}"
    if not folder.is_dir():
        raise ModelStoreError(f"{where} does not exist")
    path = folder / MANIFEST_FILE
    if not path.exists():
        raise ModelStoreError(
            f"{where} has no {MANIFEST_FILE} (incomplete or from an older gpbf): retrain it"
        )
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
        files = manifest["files"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ModelStoreError(f"{where}: unreadable {MANIFEST_FILE} ({exc})") from None
    if manifest.get("format") != STORE_FORMAT or manifest.get("version") != STORE_VERSION:
        raise ModelStoreError(
            f"{where}: {MANIFEST_FILE} is not a version-{STORE_VERSION} {STORE_FORMAT} manifest"
        )
    for name, info in files.items():
        p = folder / name
        if not p.is_file() or p.stat().st_size != info["bytes"] or (hashes and _sha256(p) != info["sha256"]):
            raise ModelStoreError(f"{where}: {name} is missing or differs from the manifest: retrain it")
    extra = sorted(p.name for p in folder.glob("*.npz") if p.name not in files)
    if (folder / CALIBRATION_FILE).exists() and CALIBRATION_FILE not in files:
        extra.append(CALIBRATION_FILE)  # noise scales added after sealing would change the models
    if extra:
        raise ModelStoreError(f"{where}: files not in the manifest {extra} (a mixed folder): retrain it")
    return manifest


def model_version(folder: str | os.PathLike[str]) -> str:
    """A short hash of the folder's manifest: equal for the same models, different after any
    retrain (what the service reports as ``model_version``); every file's hash is checked."""
    check_folder(folder, hashes=True)
    return hashlib.sha256((Path(folder) / MANIFEST_FILE).read_bytes()).hexdigest()[:16]
