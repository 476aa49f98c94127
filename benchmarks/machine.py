"""This machine's own limits, measured by each benchmark in its own run.

* :func:`dgemm_gflops` - float64 matrix-multiply rate (2000 x 2000, best of ``repeats``),
  the bound of flop-heavy work (batched GP prediction, particle filters);
* :func:`read_gbs` - read bandwidth (sum of a 256 MB float64 array, best of ``repeats``),
  the bound of work that streams factors once (one-query GP prediction, EKF steps).

A figure's limit is its flop count over the dgemm rate or its bytes over the bandwidth;
benchmarks print the ratio of their time to it (1 = at the machine's limit).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

__all__ = ["best_time", "dgemm_gflops", "limits", "read_gbs", "triangular_bytes"]


def best_time(fn: Callable[[], object], repeats: int) -> float:
    """Best wall time (s) of ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def dgemm_gflops(repeats: int = 3) -> float:
    """Float64 GEMM GFLOP/s of this machine (all BLAS threads)."""
    a = np.random.default_rng(0).normal(size=(2000, 2000))
    return 2 * 2000**3 / best_time(lambda: a @ a, repeats) / 1e9


def read_gbs(repeats: int = 3, megabytes: int = 256) -> float:
    """Read bandwidth GB/s: a float64 array larger than the caches, summed."""
    a = np.ones(megabytes * 2**20 // 8)
    return a.nbytes / best_time(lambda: np.add.reduce(a), repeats) / 1e9


def triangular_bytes(n: int, factors: int) -> int:
    """Bytes of ``factors`` lower-triangular ``n x n`` float64 factors (the half that is read)."""
    return factors * n * (n + 1) // 2 * 8


def limits(repeats: int = 3) -> dict[str, float]:
    """Both limits as the JSON keys every benchmark prints."""
    return {"dgemm_gflops": round(dgemm_gflops(repeats), 1), "read_gbs": round(read_gbs(repeats), 2)}
