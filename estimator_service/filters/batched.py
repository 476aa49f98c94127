"""The EKF's Kalman update for many beliefs at once (the service's batched steps).

One set of stacked LAPACK calls replaces a Python loop of small ones: for ``B`` blimps
that observed the same entries, the innovation covariances, gains, NIS values and Joseph
updates are computed as ``(B, ...)`` arrays. A batch whose numbers fail (an innovation
covariance or a posterior that is not positive definite) is redone row by row with the
single-belief rule, which skips or repairs exactly the rows that need it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtrc

from estimator_service.filters.common import DIVERGENCE_P, GaussianBelief, StepInfo, Wrapping

__all__ = ["implausible_many", "joseph", "joseph_update_many"]

FloatArray = NDArray[np.float64]
Single = Callable[[int], tuple[GaussianBelief, StepInfo]]


def implausible_many(nis: FloatArray, dof: int) -> NDArray[np.bool_]:
    """:func:`~estimator_service.filters.common.implausible` for an array of NIS values."""
    if dof <= 0:
        return np.zeros(nis.shape, bool)
    with np.errstate(invalid="ignore"):
        return ~np.isfinite(nis) | (chdtrc(dof, nis) < DIVERGENCE_P)


def joseph(cov: FloatArray, k: FloatArray, h: FloatArray, r_noise: FloatArray) -> FloatArray:
    """The Joseph-form posterior covariance ``(I - K H) P (I - K H)^T + K R K^T``,
    symmetrised, for one belief or a batch: ``cov (..., n, n)``, gain ``k (..., n, q)``,
    Jacobian ``h (..., q, n)``, observation noise variances ``r_noise (..., q)`` (``R``
    diagonal). Equal to ``(I - K H) P`` for the optimal gain, and positive semi-definite for
    any gain."""
    a = np.eye(cov.shape[-1]) - k @ h
    post = a @ cov @ np.swapaxes(a, -1, -2) + (k * r_noise[..., None, :]) @ np.swapaxes(k, -1, -2)
    return 0.5 * (post + np.swapaxes(post, -1, -2))


def joseph_update_many(
    mean: FloatArray, cov: FloatArray, r: FloatArray, h: FloatArray, r_noise: FloatArray,
    wrap: Wrapping, single: Single,
) -> list[tuple[GaussianBelief, StepInfo]]:  # fmt: skip
    """EKF updates of ``B`` Gaussians that observed the same ``q`` entries.

    Parameters
    ----------
    mean, cov
        The priors: ``mean (B, n)``, ``cov (B, n, n)``.
    r
        Innovations ``(B, q)``, already angle-wrapped.
    h
        Observation Jacobians ``(B, q, n)``.
    r_noise
        Observation noise variances ``(B, q)``.
    wrap
        The state's angle wrapping.
    single
        ``single(b)``: the single-belief update of row ``b``; used for every row when the
        batched factorisations fail, so a bad row never spoils the others.

    Returns
    -------
    One ``(posterior, StepInfo)`` per row, as the single-belief update gives it.
    """
    b, q = r.shape
    pht = cov @ h.transpose(0, 2, 1)  # (B, n, q)
    s = h @ pht
    s[:, *np.diag_indices(q)] += r_noise
    s = 0.5 * (s + s.transpose(0, 2, 1))
    try:
        np.linalg.cholesky(s)  # positive definite, as the single rule requires
        solved = np.linalg.solve(s, np.concatenate([pht.transpose(0, 2, 1), r[:, :, None]], axis=2))
    except np.linalg.LinAlgError:
        return [single(i) for i in range(b)]
    k = solved[:, :, :-1].transpose(0, 2, 1)  # (B, n, q): P H^T S^-1
    nis = np.einsum("bq,bq->b", r, solved[:, :, -1])
    post_mean = wrap.state_value(mean + np.einsum("bnq,bq->bn", k, r))
    post = joseph(cov, k, h, r_noise)
    ok = np.isfinite(post_mean).all(axis=1) & np.isfinite(post).all(axis=(1, 2)) & np.isfinite(nis)
    try:
        if not ok.all():
            raise np.linalg.LinAlgError
        np.linalg.cholesky(post)
    except np.linalg.LinAlgError:
        return [single(i) for i in range(b)]
    flags = implausible_many(nis, q)
    return [
        (GaussianBelief(m, c), StepInfo(float(v), q, bool(f)))
        for m, c, v, f in zip(post_mean, post, nis, flags, strict=True)
    ]
