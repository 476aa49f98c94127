"""A GP's outputs spread over a few Python threads, BLAS single-threaded inside each.

A batch of queries costs, per output, one kernel block (a small matrix product and an
``exp`` per entry), one triangular product or solve and a sum of squares. NumPy's ``exp``
and sums run on one core whatever BLAS does, and OpenBLAS's own threads contend on small
triangular solves; splitting the independent outputs over as many threads as BLAS has
(NumPy and SciPy's BLAS wrappers release the GIL) puts every part of the work on every
core. Results do not depend on the split: each output is computed by the same calls.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from estimator_service.gp.linalg import blas_threads, single_threaded_blas

__all__ = ["output_workers", "over_outputs"]

_LOCK = threading.Lock()
_POOL: list[ThreadPoolExecutor] = []
os.register_at_fork(after_in_child=_POOL.clear)  # a forked child has none of the pool's threads


def output_workers() -> int:
    """Threads used for the outputs: BLAS's thread count now (so ``threadpool_limits(1)``
    around a call keeps it on one thread)."""
    return blas_threads()


def _pool(workers: int) -> ThreadPoolExecutor:
    with _LOCK:
        if not _POOL or _POOL[0]._max_workers < workers:
            _POOL[:] = [ThreadPoolExecutor(workers, thread_name_prefix=_PREFIX)]
        return _POOL[0]


_PREFIX = "gp-outputs"


def over_outputs(fn: Callable[[int], None], outputs: int) -> None:
    """Call ``fn(p)`` for every ``p`` in ``range(outputs)``: output ``p`` on thread
    ``p % w`` of ``w =`` :func:`output_workers` threads, BLAS on one thread each (in the
    calling thread when ``w`` is 1 or the call is already on a worker); exceptions
    propagate."""
    w = min(output_workers(), outputs)
    if w <= 1 or threading.current_thread().name.startswith(_PREFIX):
        for p in range(outputs):
            fn(p)
        return

    def stride(first: int) -> None:
        for p in range(first, outputs, w):
            fn(p)

    with single_threaded_blas():
        for f in [_pool(w).submit(stride, i) for i in range(w)]:
            f.result()
