"""Squared-exponential ARD kernel (paper eq. 4), batched over independent outputs.

Hyperparameters of one output live in log space as ``theta = [log ell_1..d, log sf, log sn]``:
``k(x, x') = sf^2 exp(-1/2 sum_i (x_i - x'_i)^2 / ell_i^2)`` and observation noise
variance ``sn^2``. (The paper writes ``W = diag(1/ell^2)``.)
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["se_kernel", "split_theta", "sq_dist"]

FloatArray = NDArray[np.float64]


def split_theta(theta: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``(ell, sf2, sn2)`` from log hyperparameters ``theta (..., d + 2)``."""
    ell = np.exp(theta[..., :-2])
    return ell, np.exp(2.0 * theta[..., -2]), np.exp(2.0 * theta[..., -1])


def sq_dist(a: FloatArray, b: FloatArray) -> FloatArray:
    """Squared distances ``(..., M, n)`` between rows of ``a (..., M, d)`` and ``b (..., n, d)``.

    Uses ``|a|^2 + |b|^2 - 2 a b^T`` (one matrix multiply), clipped at zero.
    """
    aa = np.sum(a * a, axis=-1)[..., :, None]
    bb = np.sum(b * b, axis=-1)[..., None, :]
    d2 = aa + bb - 2.0 * (a @ np.swapaxes(b, -1, -2))
    return np.maximum(d2, 0.0, out=d2)


def se_kernel(a: FloatArray, b: FloatArray, ell: FloatArray, sf2: FloatArray | float) -> FloatArray:
    """Kernel matrix ``(..., M, n)``.

    Parameters
    ----------
    a: (M, d) or (P, M, d)
    b: (n, d) or (P, n, d)
    ell: (d,) or (P, d)
        Length scales.
    sf2: scalar or (P,)
        Signal variances.
    """
    ell = np.asarray(ell)
    k = sq_dist(a / ell[..., None, :], b / ell[..., None, :])
    k *= -0.5
    np.exp(k, out=k)
    k *= np.asarray(sf2)[..., None, None]
    return k


def cross_kernel_mean_jac(
    xs: FloatArray, centres: FloatArray, theta: FloatArray, weights: FloatArray, return_jac: bool
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Kernel block, weighted-sum mean and its Jacobian for ``P`` outputs at once.

    Parameters
    ----------
    xs: (M, d)
        Standardised queries.
    centres: (n, d) or (P, n, d)
        Training inputs (shared) or pseudo-inputs (per output).
    theta: (P, d + 2)
    weights: (P, n)
        ``alpha`` (exact GP) or ``beta`` (sparse GP).

    Returns
    -------
    ks: (P, M, n)
        ``k(x*, centres)`` per output.
    mean: (M, P)
        ``ks @ weights`` (paper eq. 2).
    jac: (M, P, d) or None
        ``d mean / d x*`` (paper eq. 20-22): ``-W (x* mean - (ks * weights) @ centres)``.
    """
    ell, sf2, _ = split_theta(theta)
    ks = se_kernel(xs[None], centres if centres.ndim == 3 else centres[None], ell, sf2)
    mean = np.einsum("pmn,pn->mp", ks, weights)
    jac = None
    if return_jac:
        kw = ks * weights[:, None, :]
        jac = (kw @ centres - xs[None] * mean.T[:, :, None]) / (ell * ell)[:, None, :]
        jac = jac.transpose(1, 0, 2)
    return ks, mean, jac
