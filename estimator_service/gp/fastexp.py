"""The kernel blocks' exponential, vectorised: ``exp(min(a, cap))`` in place, within 1 ulp.

NumPy's float64 ``exp`` is vectorised only on CPUs with AVX-512; elsewhere (AVX2) it calls
the scalar libm routine, 5-9 ns per element, a large part of a batched GP prediction
(docs/measurements.md#vectorised-exp). :mod:`estimator_service.gp.fastexp_kernel` holds a
compiled loop the compiler vectorises (how, and how accurate: its docstring); this module
decides which blocks it gets.

numba compiles that loop once per machine (about 2 s, cached beside the module or in
numba's user cache where that folder is read-only); a process loads it (about 0.7 s with
numba's import) at its first block of :data:`VECTORISE_MIN` elements or more. Smaller
blocks (an EKF's few queries), arrays that are not C-contiguous float64, and installs
without numba (the estimator alone; ``pip install 'gpbf[fast]'`` adds it) use NumPy's
``minimum`` and ``exp``: the same values within 1 ulp. The loop releases the GIL, so
threads over outputs run it side by side.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

__all__ = ["VECTORISE_MIN", "exp_capped", "vectorised"]

FloatArray = NDArray[np.float64]
#: blocks below this many elements use NumPy's exp: at 5 ns an element they cost at most
#: 0.1 ms, while loading the compiled loop costs about 0.7 s once per process
VECTORISE_MIN = 16_384
_UNLOADED = object()
_loaded: object = _UNLOADED  # the compiled loop, None where numba is missing
_lock = threading.Lock()


def _compiled() -> Callable[[FloatArray, FloatArray], None] | None:
    """The compiled loop (loaded on the first call), or None without numba."""
    global _loaded
    if _loaded is _UNLOADED:
        with _lock:
            if _loaded is _UNLOADED:
                try:
                    from estimator_service.gp.fastexp_kernel import exp_capped_rows
                except ImportError:
                    exp_capped_rows = None
                _loaded = exp_capped_rows
    return _loaded  # type: ignore[return-value]


def vectorised() -> bool:
    """Whether large blocks get the compiled loop (numba is installed); loads it."""
    return _compiled() is not None


def exp_capped(a: FloatArray, cap: float | FloatArray = np.inf) -> FloatArray:
    """``a`` set to ``exp(min(a, cap))`` in place and returned, within 1 ulp of NumPy's
    ``exp``.

    Parameters
    ----------
    a: (P, ...)
        float64; C-contiguous blocks of :data:`VECTORISE_MIN` elements or more go through
        the compiled loop, the rest through NumPy.
    cap: scalar or (P,)
        One cap, or one per leading index of ``a`` (e.g. per GP output).
    """
    caps = np.asarray(cap, dtype=np.float64)
    if caps.ndim > 1 or (caps.ndim == 1 and (a.ndim == 0 or caps.size != a.shape[0])):
        raise ValueError(
            f"cap must be a scalar or one per leading index of a {a.shape}, got shape {caps.shape}"
        )
    fast = a.size >= VECTORISE_MIN  # a 0-d array is one element: NumPy's
    loop = _compiled() if fast and a.dtype == np.float64 and a.flags.c_contiguous else None
    if loop is None:
        np.minimum(a, caps if caps.ndim == 0 else caps.reshape(-1, *(1,) * (a.ndim - 1)), out=a)
        return np.exp(a, out=a)
    rows = a.reshape(caps.size, -1) if caps.ndim else a.reshape(1, -1)
    loop(rows, np.ascontiguousarray(np.broadcast_to(caps, rows.shape[:1])))
    return a
