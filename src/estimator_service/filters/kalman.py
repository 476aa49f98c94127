"""GP-EKF (paper Table 2) and GP-UKF (paper Table 3)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from estimator_service.filters.common import (
    GaussianBelief,
    StepInfo,
    Wrapping,
    finite,
    implausible,
    make_pd,
    nis_from_cholesky,
)
from estimator_service.models.base import ObservationModel, PredictionModel

__all__ = ["EKF", "UKF", "sigma_weights"]

FloatArray = NDArray[np.float64]


def _valid_index(valid: NDArray[np.bool_] | None, m: int) -> NDArray[np.intp]:
    if valid is None:
        return np.arange(m)
    return np.flatnonzero(valid)


def _kalman_update(
    prior: GaussianBelief, r: FloatArray, s: FloatArray, pxz: FloatArray,
    wrap: Wrapping, joseph_h: FloatArray | None = None, r_noise: FloatArray | None = None,
) -> tuple[GaussianBelief, StepInfo]:  # fmt: skip
    """Kalman update from innovation ``r``, its covariance ``s`` and cross-covariance ``pxz``.

    Skips the update (flagging divergence) when ``s`` is not positive definite or the
    result is not finite; never returns NaN.
    """
    try:
        ls = np.linalg.cholesky(0.5 * (s + s.T))
    except np.linalg.LinAlgError:
        return prior, StepInfo(math.nan, len(r), True)
    k = sla.cho_solve((ls, True), pxz.T, check_finite=False).T  # Pxz S^-1
    mean = wrap.state_value(prior.mean + k @ r)
    if joseph_h is not None:  # EKF: (I - KH) P (I - KH)^T + K R K^T
        a = np.eye(len(mean)) - k @ joseph_h
        cov = a @ prior.cov @ a.T + (k * r_noise) @ k.T
    else:  # UKF: P - K S K^T
        cov = prior.cov - k @ s @ k.T
    nis = nis_from_cholesky(ls, r)
    if not finite(mean, cov):
        return prior, StepInfo(nis, len(r), True)
    cov, _ = make_pd(cov)
    return GaussianBelief(mean, cov), StepInfo(nis, len(r), implausible(nis, len(r)))


class _GaussianFilter:
    """What the EKF and UKF share: angle handling and the predict-then-update step."""

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None

    @property
    def _wrap(self) -> Wrapping:
        return self.wrapping or Wrapping.none(self.prediction.state_dim, self.observation.obs_dim)

    def predict(self, belief: GaussianBelief, u: FloatArray) -> GaussianBelief:
        raise NotImplementedError

    def update(
        self, prior: GaussianBelief, z: FloatArray, valid: NDArray[np.bool_] | None = None
    ) -> tuple[GaussianBelief, StepInfo]:
        raise NotImplementedError

    def step(
        self, belief: GaussianBelief, u: FloatArray, z: FloatArray | None = None,
        valid: NDArray[np.bool_] | None = None,
    ) -> tuple[GaussianBelief, StepInfo]:  # fmt: skip
        """Predict with control ``u (k,)``, then update with the valid entries of ``z (m,)``."""
        prior = self.predict(belief, u)
        if z is None:
            return prior, StepInfo()
        return self.update(prior, z, valid)


@dataclass(frozen=True)
class EKF(_GaussianFilter):
    """GP-EKF: linearise the models' means at the current estimate (paper Table 2).

    ``G = I + d(mean change)/dx`` and ``H = d(mean obs)/dx`` come from the models'
    Jacobians (paper eq. 20-22 for GPs); ``Q`` and ``R`` are the models' variances at the
    mean. The covariance update uses the Joseph form, which equals Table 2's
    ``(I - K H) Sigma`` for the optimal gain and stays symmetric positive definite.
    """

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None = None
    name: str = "EKF"

    def predict(self, belief: GaussianBelief, u: FloatArray) -> GaussianBelief:
        """Steps 2-5 of Table 2."""
        out = self.prediction.predict(belief.mean[None], u, jac=True)
        g = np.eye(belief.mean.size) + out.jac[0]
        cov = g @ belief.cov @ g.T + np.diag(out.var[0])
        return GaussianBelief(self._wrap.state_value(belief.mean + out.mean[0]), 0.5 * (cov + cov.T))

    def update(
        self, prior: GaussianBelief, z: FloatArray, valid: NDArray[np.bool_] | None = None
    ) -> tuple[GaussianBelief, StepInfo]:
        """Steps 6-11 of Table 2, with exactly the observation entries marked ``valid``."""
        idx = _valid_index(valid, self.observation.obs_dim)
        if idx.size == 0:
            return prior, StepInfo()
        obs = self.observation.observe(prior.mean[None], jac=True)
        h, r_noise = obs.jac[0, idx], obs.var[0, idx]
        r = self._wrap.obs_diff(np.asarray(z, dtype=np.float64)[idx] - obs.mean[0, idx], idx)
        s = h @ prior.cov @ h.T + np.diag(r_noise)
        return _kalman_update(prior, r, s, prior.cov @ h.T, self._wrap, h, r_noise)


def sigma_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[FloatArray, FloatArray, float]:
    """Unscented-transform weights: mean weights ``(2n+1,)``, covariance weights, ``gamma``."""
    lam = alpha * alpha * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + (1.0 - alpha * alpha + beta)
    return wm, wc, math.sqrt(n + lam)


@dataclass(frozen=True)
class UKF(_GaussianFilter):
    """GP-UKF: unscented transform through the models' means (paper Table 3).

    All ``2n + 1`` sigma points go through a model in one batched call. ``Q`` and ``R`` are
    the models' variances at the mean (the paper's choice, ``noise="mean"``) or the
    plain average over the sigma points (``noise="sigma"``).
    """

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None = None
    alpha: float = 1e-3
    beta: float = 2.0
    kappa: float = 0.0
    noise: str = "mean"
    name: str = "UKF"
    _w: tuple[FloatArray, FloatArray, float] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.noise not in ("mean", "sigma"):
            raise ValueError(f"noise must be 'mean' or 'sigma', got {self.noise!r}")
        object.__setattr__(
            self, "_w", sigma_weights(self.prediction.state_dim, self.alpha, self.beta, self.kappa)
        )

    def sigma_points(self, belief: GaussianBelief) -> FloatArray:
        """``(2n + 1, n)``: the mean, then ``mean +- gamma`` times the Cholesky columns."""
        _, l = make_pd(belief.cov)
        d = self._w[2] * l.T
        return np.concatenate([belief.mean[None], belief.mean + d, belief.mean - d])

    def predict(self, belief: GaussianBelief, u: FloatArray) -> GaussianBelief:
        """Steps 2-6 of Table 3."""
        wm, wc, _ = self._w
        x = self.sigma_points(belief)
        out = self.prediction.predict(x, u, var=self.noise == "sigma")
        xk = x + out.mean
        q = out.var.mean(axis=0) if self.noise == "sigma" else self.prediction.predict(x[:1], u).var[0]
        mean = self._wrap.mean(xk, wm, self._wrap.state)
        dev = self._wrap.state_diff(xk - mean)
        cov = (dev * wc[:, None]).T @ dev + np.diag(q)
        return GaussianBelief(mean, 0.5 * (cov + cov.T))

    def update(
        self, prior: GaussianBelief, z: FloatArray, valid: NDArray[np.bool_] | None = None
    ) -> tuple[GaussianBelief, StepInfo]:
        """Steps 7-15 of Table 3, with exactly the observation entries marked ``valid``."""
        idx = _valid_index(valid, self.observation.obs_dim)
        if idx.size == 0:
            return prior, StepInfo()
        wm, wc, _ = self._w
        x = self.sigma_points(prior)
        out = self.observation.observe(x, var=self.noise == "sigma")
        zs = out.mean[:, idx]
        r_noise = (
            out.var[:, idx].mean(axis=0)
            if self.noise == "sigma"
            else self.observation.observe(x[:1]).var[0, idx]
        )
        zhat = self._wrap.mean(zs, wm, self._wrap.obs[idx])
        dz = self._wrap.obs_diff(zs - zhat, idx)
        dx = self._wrap.state_diff(x - prior.mean)
        s = (dz * wc[:, None]).T @ dz + np.diag(r_noise)
        pxz = (dx * wc[:, None]).T @ dz
        r = self._wrap.obs_diff(np.asarray(z, dtype=np.float64)[idx] - zhat, idx)
        return _kalman_update(prior, r, s, pxz, self._wrap)
