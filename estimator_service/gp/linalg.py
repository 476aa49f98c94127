"""Dense linear algebra for GPs: Cholesky with adaptive jitter and fast triangular solves."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.linalg import blas
from threadpoolctl import ThreadpoolController

__all__ = [
    "NotPositiveDefiniteError",
    "blas_threads",
    "chol_inverse",
    "chol_solve",
    "inverse_factor",
    "robust_cholesky",
    "single_threaded_blas",
    "tri_solve",
]

#: largest 1-norm condition estimate of a Cholesky factor ``L`` whose explicit inverse replaces
#: the triangular solve: ``L^-1 k`` is then accurate to about ``cond * eps`` = 2e-8 relative.
MAX_INVERSE_COND = 1e8

_BLAS = ThreadpoolController()


@contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Context: BLAS on one thread. For many small solves, as in a sparse GP, the second BLAS
    thread only spins against the main thread (measured: docs/measurements.md#one-blas-thread).

    Safe from several threads at once: the first to enter sets one thread, the last to
    leave restores what was there (nested limits from different threads would otherwise
    restore each other's settings in the wrong order)."""
    with _SINGLE_LOCK:
        if not _SINGLE:
            _SINGLE.append(_BLAS.limit(limits=1, user_api="blas"))
        _SINGLE.append(None)
    try:
        yield
    finally:
        with _SINGLE_LOCK:
            _SINGLE.pop()
            if len(_SINGLE) == 1:
                _SINGLE.pop().restore_original_limits()


_SINGLE_LOCK = threading.Lock()
_SINGLE: list = []  # [the limiter, one None per thread inside]


def blas_threads() -> int:
    """BLAS threads in use now (the largest over the loaded BLAS libraries; 1 if none)."""
    return max((c.num_threads for c in _BLAS.select(user_api="blas").lib_controllers), default=1)


FloatArray = NDArray[np.float64]


class NotPositiveDefiniteError(np.linalg.LinAlgError):
    """The matrix stayed indefinite even with the largest jitter."""


def robust_cholesky(k: FloatArray, max_tries: int = 8) -> tuple[FloatArray, float]:
    """Lower Cholesky factor of symmetric ``k (n, n)``, adding jitter only if needed.

    Jitter starts at ``1e-10`` of the mean diagonal and grows tenfold per failure.

    Returns
    -------
    L: (n, n)
        Lower triangular with ``L L^T = k + jitter I``.
    jitter
        The jitter that was added (0.0 when none was needed).
    """
    try:
        return np.linalg.cholesky(k), 0.0
    except np.linalg.LinAlgError:
        pass
    scale = float(np.mean(np.diag(k)))
    if not np.isfinite(scale) or scale <= 0:
        raise NotPositiveDefiniteError("kernel matrix has a non-positive or non-finite diagonal")
    eye = np.eye(k.shape[0])
    jitter = 1e-10 * scale
    for _ in range(max_tries):
        try:
            return np.linalg.cholesky(k + jitter * eye), jitter
        except np.linalg.LinAlgError:
            jitter *= 10.0
    raise NotPositiveDefiniteError(f"matrix not positive definite even with jitter {jitter:.3g}")


def tri_solve(l_fortran: FloatArray, b: FloatArray, overwrite_b: bool = False) -> FloatArray:
    """Solve ``L X = B`` for lower-triangular ``L (n, n)`` and ``B (n, M)``.

    One right-hand side goes to BLAS ``trsv``, more to LAPACK ``trtrs`` (measured faster
    here than calling ``trsm`` through its wrapper for skinny ``B``).

    ``L`` should be Fortran-ordered (a posterior stores it so) and ``B`` is best passed
    Fortran-ordered too, e.g. the transpose of a C-ordered ``(M, n)`` array: then no copy
    is made and with ``overwrite_b`` the solve happens in place.
    """
    if b.shape[1] == 1:  # one query (the EKF): trsv streams L once, about twice as fast
        return blas.dtrsv(l_fortran, b[:, 0], lower=1, overwrite_x=int(overwrite_b))[:, None]
    return sla.solve_triangular(l_fortran, b, lower=True, check_finite=False, overwrite_b=overwrite_b)


def inverse_factor(l_fortran: FloatArray, max_cond: float = MAX_INVERSE_COND) -> FloatArray | None:
    """``L^-1`` of a lower-triangular ``L (n, n)`` (LAPACK ``trtri``), lower and Fortran-ordered,
    or None when ``L``'s condition estimate (``trcon``, O(n^2)) exceeds ``max_cond``: then the
    product ``L^-1 B`` would lose more than ``max_cond * eps`` relative accuracy against the
    solve and the caller keeps solving."""
    rcond, info = sla.lapack.dtrcon(l_fortran, norm="1", uplo="L", diag="N")
    if info != 0 or not rcond * max_cond >= 1.0:
        return None
    inv, info = sla.lapack.dtrtri(l_fortran, lower=1)
    if info != 0 or not np.all(np.isfinite(inv)):
        return None
    return np.asfortranarray(np.tril(inv))


def chol_solve(l: FloatArray, b: FloatArray) -> FloatArray:
    """Solve ``(L L^T) X = B`` given the lower Cholesky factor ``L``."""
    return sla.cho_solve((l, True), b, check_finite=False)


def chol_inverse(l: FloatArray) -> FloatArray:
    """``(L L^T)^-1 (n, n)`` from the lower Cholesky factor ``L`` (LAPACK ``potri``).

    Needed whole only for marginal-likelihood gradients; ``potri`` costs ``2n^3/3`` flops
    against ``2n^3`` for solving with the identity (bench_training: 14.3 vs 19.9 ms at ``n = 900``).
    """
    inv, info = sla.lapack.dpotri(l, lower=1)
    if info != 0:
        raise NotPositiveDefiniteError(f"potri failed with info {info}")
    return np.tril(inv) + np.tril(inv, -1).T  # potri fills the lower triangle only
