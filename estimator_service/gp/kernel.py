"""Squared-exponential ARD kernel (paper eq. 4), batched over independent outputs.

Hyperparameters of one output live in log space as ``theta = [log ell_1..d, log sf, log sn]``:
``k(x, x') = sf^2 exp(-1/2 sum_i (x_i - x'_i)^2 / ell_i^2)`` and observation noise
variance ``sn^2``. (The paper writes ``W = diag(1/ell^2)``.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.fastexp import exp_capped

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
    exp_capped(k)
    k *= np.asarray(sf2)[..., None, None]
    return k


@dataclass(frozen=True, eq=False)
class CrossKernel:
    """Precomputed pieces for ``k(x*, centres)``, the GP mean and its Jacobian (P outputs).

    The squared-exponential exponent ``log sf^2 - |a - b|^2 / 2`` (``a = x*/ell``,
    ``b = centre/ell``) is one matrix product of augmented rows ``[a, -|a|^2/2, 1]`` and
    ``[b, 1, log sf^2 - |b|^2/2]``, followed by one in-place ``exp``.

    Attributes
    ----------
    ell: (P, d)
    log_sf2: (P,)
    b_aug_t: (P, d + 2, n)
    weights: (P, n, 1)
        ``alpha`` (exact GP) or ``beta`` (sparse GP).
    weighted_centres: (P, n, d)
        ``weights * centres``, for the Jacobian.
    """

    ell: FloatArray
    log_sf2: FloatArray
    b_aug_t: FloatArray
    weights: FloatArray
    weighted_centres: FloatArray

    @classmethod
    def build(cls, centres: FloatArray, theta: FloatArray, weights: FloatArray) -> CrossKernel:
        """From centres ``(n, d)`` or ``(P, n, d)``, ``theta (P, d+2)``, ``weights (P, n)``."""
        ell, sf2, _ = split_theta(theta)
        c = np.broadcast_to(centres, (theta.shape[0], *centres.shape[-2:]))
        b = c / ell[:, None, :]
        ones = np.ones((*b.shape[:2], 1))
        top = (np.log(sf2)[:, None] - 0.5 * np.sum(b * b, axis=-1))[..., None]
        b_aug_t = np.ascontiguousarray(np.concatenate([b, ones, top], axis=-1).transpose(0, 2, 1))
        return cls(ell, np.log(sf2), b_aug_t, weights[:, :, None].copy(), weights[:, :, None] * c)

    def block(self, xs: FloatArray) -> FloatArray:
        """Kernel block ``ks (P, M, n)`` at standardised queries ``xs (M, d)``."""
        a = xs[None] / self.ell[:, None, :]
        ones = np.ones((*a.shape[:2], 1))
        a_aug = np.concatenate([a, -0.5 * np.sum(a * a, axis=-1)[..., None], ones], axis=-1)
        return exp_capped(a_aug @ self.b_aug_t, self.log_sf2)  # capped: distance >= 0

    def block_one(self, xs: FloatArray, p: int) -> FloatArray:
        """Output ``p``'s kernel block ``(M, n)`` at standardised queries ``xs (M, d)``."""
        a = xs / self.ell[p]
        a_aug = np.concatenate([a, -0.5 * np.sum(a * a, axis=1)[:, None], np.ones((a.shape[0], 1))], axis=1)
        return exp_capped(a_aug @ self.b_aug_t[p], float(self.log_sf2[p]))  # distance >= 0

    def jacobian(self, ks: FloatArray, xs: FloatArray, mean: FloatArray) -> FloatArray:
        """``d mean / d x* (M, P, d)`` (eq. 20-22) from the block ``ks (P, M, n)``, the
        queries ``xs (M, d)`` and the mean ``(M, P)``: ``-W (x* mean - ks @ (weights *
        centres))``."""
        jac = (ks @ self.weighted_centres - xs[None] * mean.T[:, :, None]) / (self.ell**2)[:, None, :]
        return jac.transpose(1, 0, 2)

    def __call__(self, xs: FloatArray, return_jac: bool) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """Kernel block, mean and Jacobian at standardised queries ``xs (M, d)``.

        Returns
        -------
        ks: (P, M, n)
        mean: (M, P)
            ``ks @ weights`` (paper eq. 2).
        jac: (M, P, d) or None
            See :meth:`jacobian`.
        """
        ks = self.block(xs)
        mean = (ks @ self.weights)[:, :, 0].T  # (M, P)
        return ks, mean, self.jacobian(ks, xs, mean) if return_jac else None
