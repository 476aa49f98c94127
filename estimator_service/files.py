"""Atomic file writes: a reader sees the old file or the new one, never half of one.

Every file the estimator writes (models, flights, calibration, reports) goes through
:func:`atomic_write`: the bytes go to a temporary file in the destination folder, are
flushed, and the temporary file is renamed over the destination. The result has the mode
an ordinary ``open(path, "w")`` would give (``0o666`` less the process umask), not the
``0o600`` of a bare temporary file. A failed write removes its temporary file; one
killed outright (``SIGKILL``) leaves a ``.gpbf-*.tmp`` file behind, which the next write
into the same folder removes once it is an hour old (:func:`remove_stale_temps`).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

__all__ = [
    "TEMP_PREFIX",
    "atomic_savez",
    "atomic_write",
    "atomic_write_text",
    "current_umask",
    "json_text",
    "npz_oversized",
    "npz_unreadable",
    "remove_stale_temps",
]

TEMP_PREFIX = ".gpbf-"
TEMP_SUFFIX = ".tmp"
STALE_AFTER_S = 3600.0  # no write takes this long: an older temporary file's writer is dead


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    old = os.umask(0o022)  # no /proc: read by setting (briefly) and restoring
    os.umask(old)
    return old


def atomic_write(path: str | os.PathLike[str], write: Callable[[BinaryIO], object]) -> Path:
    """Call ``write(fh)`` on a temporary file beside ``path``, then rename it to ``path``.

    The parent folder is created when missing. On any exception the temporary file is
    removed and the destination is left as it was; an operating-system error (a full disk,
    a folder where the file should go) is raised naming ``path``, never the temporary file.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    folder.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(folder, STALE_AFTER_S)  # left by a writer killed outright
    fd, tmp = tempfile.mkstemp(prefix=TEMP_PREFIX, suffix=TEMP_SUFFIX, dir=folder)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        if e.errno is None:
            raise
        raise type(e)(e.errno, e.strerror, os.fspath(path)) from e
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_savez(path: str | os.PathLike[str], **arrays: np.ndarray) -> Path:
    """``np.savez(path, **arrays)`` written atomically (no pickle on reading back)."""
    return atomic_write(path, lambda fh: np.savez(fh, **arrays))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """``text`` as UTF-8, written atomically."""
    return atomic_write(path, lambda fh: fh.write(text.encode("utf-8")))


def remove_stale_temps(folder: str | os.PathLike[str], older_than_s: float = 0.0) -> int:
    """Remove this module's temporary files in ``folder`` (not recursing) that are older
    than ``older_than_s`` seconds; returns how many were removed."""
    now, removed = time.time(), 0
    for p in Path(folder).glob(f"{TEMP_PREFIX}*{TEMP_SUFFIX}"):
        try:
            if now - p.stat().st_mtime >= older_than_s:
                p.unlink()
                removed += 1
        except FileNotFoundError:
            continue
    return removed


def json_text(obj: object, indent: int | None = None) -> str:
    """``obj`` as standard JSON: a non-finite float (NaN, +-inf: "not measured here") becomes
    ``null`` instead of the bare ``NaN`` that ``json.dumps`` writes and JSON parsers refuse;
    numpy scalars and arrays become numbers and lists."""
    return json.dumps(_finite_or_null(obj), indent=indent, allow_nan=False)


def _finite_or_null(obj: object) -> object:
    if isinstance(obj, dict):
        return {k: _finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_null(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):  # numpy scalars and arrays
        return _finite_or_null(obj.tolist())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


MAX_ARRAY_BYTES = 2**31  # a larger array in a data or model file is refused before it is read


def npz_unreadable(exc: Exception) -> str:
    """Why ``np.load(path, allow_pickle=False)`` raised ``exc``, in a user's terms: a file that
    is neither a zip archive nor a ``.npy`` array makes NumPy suggest an unsafe pickle load,
    which would be wrong advice for a file that is simply not ``.npz``."""
    if isinstance(exc, ValueError) and "pickled" in str(exc):  # not "allow_pickle": an object array
        return "not a NumPy .npz file (neither a zip archive nor a .npy array)"
    return f"unreadable or truncated ({exc})"


def npz_oversized(npz: np.lib.npyio.NpzFile) -> str | None:
    """Why one of ``npz``'s arrays may not be read (None when all may): its header declares
    more than :data:`MAX_ARRAY_BYTES` or more than the member stores. Reads only the headers,
    so a file declaring terabytes costs nothing to refuse."""
    for info in npz.zip.infolist():
        with npz.zip.open(info) as fh:
            version = np.lib.format.read_magic(fh)
            read = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            shape, _, dtype = read(fh)
        declared = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
        if declared > MAX_ARRAY_BYTES or declared > info.file_size:
            name = info.filename.removesuffix(".npy")
            return f"array '{name}' declares {declared} bytes, more than it stores or {MAX_ARRAY_BYTES}"
    return None
