"""The one compilation setting of the simulator's numba kernels.

:func:`kernel` compiles with ``error_model="numpy"`` (a division by zero gives inf or nan,
as the array code did, instead of raising) and caches the machine code, so only the first
process on a machine compiles (seconds). Numba checks only the defining file of a cached
function, yet the kernels inline each other and the coefficient layout of
:mod:`gpbf_env.coeffs`; the cache therefore lives in a folder named after a hash of every
kernel source file (:data:`KERNEL_SOURCES`), so an edit to any of them, or another git
checkout, compiles afresh instead of running stale code. Where no folder is writable
the kernels compile in every process, uncached.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from numba import njit
from numba.core import config

__all__ = ["CACHE_DIR", "KERNEL_SOURCES", "kernel"]

F = TypeVar("F", bound=Callable[..., Any])
_HERE = Path(__file__).resolve().parent
#: the modules whose source enters compiled kernels (their own or inlined)
KERNEL_SOURCES = ("coeffs.py", "dynamics.py", "jit.py", "lab_dynamics.py", "mocap_kernel.py", "outline.py")
_PREFIX = "numba-"


def _digest() -> str:
    h = hashlib.sha256()
    for name in KERNEL_SOURCES:
        h.update((_HERE / name).read_bytes())
    return h.hexdigest()[:16]


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(folder, os.W_OK)


def _cache_dir(home: Path, shared: Path, name: str) -> Path | None:
    """``home/name`` (the package's own ``__pycache__``; its stale ``numba-*`` siblings are
    removed, since only this install writes there), else ``shared/name`` in the temporary
    folder, which other installs of other versions share (nothing is removed there: each
    would delete the other's cache and recompile in every process), else None (no caching)."""
    own = home / name
    if _writable(own):
        for old in home.glob(_PREFIX + "*"):
            if old != own:
                shutil.rmtree(old, ignore_errors=True)  # another process may hold it: best effort
        return own
    fallback = shared / name
    return fallback if _writable(fallback) else None


CACHE_DIR = _cache_dir(
    _HERE / "__pycache__",
    Path(tempfile.gettempdir()) / f"gpbf-{getattr(os, 'getuid', lambda: 0)()}",
    _PREFIX + _digest(),
)


def kernel(func: F) -> F:
    """``func`` compiled by numba (nopython, numpy error model), cached in :data:`CACHE_DIR`."""
    if CACHE_DIR is None:
        return njit(cache=False, error_model="numpy")(func)
    saved = config.CACHE_DIR
    config.CACHE_DIR = str(CACHE_DIR)  # read once, when the dispatcher picks its cache locator
    try:
        return njit(cache=True, error_model="numpy")(func)
    finally:
        config.CACHE_DIR = saved
