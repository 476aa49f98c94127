"""A GP's outputs spread over a few Python threads, BLAS single-threaded inside each.

A batch of queries costs, per output, one kernel block (a small matrix product and an
``exp`` per entry), the variance's products and a sum of squares. NumPy's ``exp`` and sums
run on one core whatever BLAS does, and OpenBLAS's own threads contend on small products;
splitting the independent outputs over as many threads as BLAS has puts every part of the
work on every core. NumPy's products and ufuncs release the GIL (two threads, two outputs:
128 -> 73 ms of products, 63 -> 42 ms of ``exp``); SciPy's triangular wrappers do not (295
-> 298 ms), so the work given to the threads avoids them where it can. Results do not
depend on the split: each output is computed by the same calls.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait

from estimator_service.gp.linalg import blas_threads, single_threaded_blas

__all__ = ["over_outputs"]

_PREFIX = "gp-outputs"
_LOCK = threading.Lock()
_POOL: list[tuple[int, ThreadPoolExecutor]] = []  # (its size, the pool)
os.register_at_fork(after_in_child=_POOL.clear)  # a forked child has none of the pool's threads


def _pool(workers: int) -> ThreadPoolExecutor:
    with _LOCK:
        if not _POOL or _POOL[0][0] < workers:
            if _POOL:
                _POOL[0][1].shutdown(wait=False)
            _POOL[:] = [(workers, ThreadPoolExecutor(workers, thread_name_prefix=_PREFIX))]
        return _POOL[0][1]


def over_outputs(fn: Callable[[int], None], outputs: int) -> None:
    """Call ``fn(p)`` for every ``p`` in ``range(outputs)``: output ``p`` on thread ``p % w``
    of ``w`` threads, ``w`` the BLAS thread count now (so ``threadpool_limits(1)`` around a
    call keeps it on one thread), BLAS on one thread each; in the calling thread when ``w``
    is 1 or the call is already on a worker. Every output has finished when it returns or
    raises the first error."""
    w = min(blas_threads(), outputs)
    if w <= 1 or threading.current_thread().name.startswith(_PREFIX):
        for p in range(outputs):
            fn(p)
        return

    def stride(first: int) -> None:
        for p in range(first, outputs, w):
            fn(p)

    with single_threaded_blas():
        futures = [_pool(w).submit(stride, i) for i in range(w)]
        wait(futures)
    for f in futures:
        f.result()
