"""GP-PF (paper Table 1): particles sampled from their own predictive Gaussians."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from estimator_service.filters.common import (
    GaussianBelief,
    ParticleBelief,
    StepInfo,
    Wrapping,
    finite,
    implausible,
    make_pd,
    nis_from_cholesky,
    normalise_log_weights,
    weighted_mean,
)
from estimator_service.filters.policy import step_one
from estimator_service.models.base import ObservationModel, PredictionModel, observe_columns
from estimator_service.reprs import short_repr

__all__ = ["PF", "systematic_resample"]

FloatArray = NDArray[np.float64]


def systematic_resample(weights: FloatArray, rng: np.random.Generator) -> NDArray[np.intp]:
    """Low-variance resampling: ``M`` indices from one uniform draw (Thrun et al. 2005)."""
    m = weights.size
    positions = (rng.random() + np.arange(m)) / m
    cum = np.cumsum(weights)
    cum[-1] = 1.0
    return np.searchsorted(cum, positions, side="right")


@dataclass(frozen=True)
class PF:
    """GP-PF with log-weights and effective-sample-size-triggered systematic resampling.

    Attributes
    ----------
    n_particles
        ``M`` (paper: up to thousands; default 2,000).
    resample_below
        Resample when ``ESS < resample_below * M`` (1.0 resamples every step, as Table 1).
    roughen
        Regularised resampling: after resampling, move particles by ``N(0, (roughen h)^2 C)``
        with ``h`` Silverman's bandwidth, so the cloud does not collapse onto a few
        particles (0 = Table 1 as written).
    roughen_cov
        ``C`` for the roughening: ``"posterior"``, the weighted particle covariance after the
        update, or ``"kalman"``, the Kalman-updated covariance of the predicted cloud
        (``P - Pxz S^-1 Pxz^T`` from the particles' predicted observations). When a sharp
        likelihood leaves one particle with almost all the weight, the weighted covariance
        is nearly zero and the cloud collapses onto that particle; the Kalman covariance
        keeps the spread a Gaussian filter would have.
    """

    __repr__ = short_repr

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None = None
    n_particles: int = 2000
    resample_below: float = 0.5
    roughen: float = 0.0
    roughen_cov: Literal["posterior", "kalman"] = "posterior"
    name: str = "PF"

    def __post_init__(self) -> None:
        if self.roughen_cov not in ("posterior", "kalman"):
            raise ValueError(f"roughen_cov must be 'posterior' or 'kalman', got {self.roughen_cov!r}")

    @property
    def _wrap(self) -> Wrapping:
        return self.wrapping or Wrapping.none(self.prediction.state_dim, self.observation.obs_dim)

    def initial(self, belief: GaussianBelief, rng: np.random.Generator | None = None) -> ParticleBelief:
        """Particles drawn from a Gaussian belief."""
        return ParticleBelief.from_gaussian(belief, self.n_particles, _need_rng(rng, "initial"))

    def gaussian(self, belief: ParticleBelief) -> GaussianBelief:
        """Weighted mean (circular for angles) and covariance of the particles."""
        w = belief.weights
        mean, dev = self._deviations(belief)
        return GaussianBelief(mean, make_pd((dev * w[:, None]).T @ dev)[0])

    def _deviations(self, belief: ParticleBelief) -> tuple[FloatArray, FloatArray]:
        """Weighted (circular) mean ``(n,)`` and the particles' deviations from it ``(M, n)``."""
        mean = self._wrap.circular_mean(belief.particles, belief.weights)
        return mean, self._wrap.state_diff(belief.particles - mean)

    def predict(
        self, belief: ParticleBelief, u: FloatArray, rng: np.random.Generator | None = None
    ) -> ParticleBelief:
        """Step 4: ``x_m ~ x_m + N(GP_mu([x_m, u]), GP_Sigma([x_m, u]))``, all particles at once
        (``rng`` required)."""
        rng = _need_rng(rng, "predict")
        out = self.prediction.predict(belief.particles, u)
        noise = rng.standard_normal(belief.particles.shape) * np.sqrt(out.var)
        return ParticleBelief(self._wrap.state_value(belief.particles + out.mean + noise), belief.log_weights)

    def update(
        self, prior: ParticleBelief, z: FloatArray, valid: NDArray[np.bool_] | None = None,
        rng: np.random.Generator | None = None,
    ) -> tuple[ParticleBelief, StepInfo]:  # fmt: skip
        """Steps 5-11: weight by the observation likelihood, resample when ESS is low
        (``rng`` required)."""
        rng = _need_rng(rng, "update")
        idx = np.arange(self.observation.obs_dim) if valid is None else np.flatnonzero(valid)
        if idx.size == 0:
            return prior, StepInfo(ess=prior.ess)
        out = observe_columns(self.observation, prior.particles, idx)  # only the sensors that read
        zs, var = out.mean, out.var
        zi = np.asarray(z, dtype=np.float64)[idx]
        r = self._wrap.obs_diff(zi - zs, idx)
        loglik = -0.5 * np.sum(r * r / var + np.log(2 * math.pi * var), axis=1)
        nis, dz, ls = self._innovation(prior.weights, zs, var, zi, idx)
        logw = prior.log_weights + loglik
        if not np.any(np.isfinite(logw)) or not finite(prior.particles):
            return prior, StepInfo(nis, idx.size, True, prior.ess)
        logw = np.where(np.isfinite(logw), logw, -np.inf)
        post = ParticleBelief(prior.particles, normalise_log_weights(logw))
        ess = post.ess
        resampled = ess < self.resample_below * self.n_particles
        if resampled:
            keep = systematic_resample(post.weights, rng)
            moved = post.particles[keep]
            if self.roughen > 0:
                cov = (
                    self._kalman_cov(prior, dz, ls)
                    if self.roughen_cov == "kalman"
                    else self.gaussian(post).cov
                )
                moved = self._roughen(moved, cov, rng)
            post = ParticleBelief(moved, np.full(keep.size, -math.log(keep.size)))
        return post, StepInfo(nis, idx.size, implausible(nis, idx.size), ess, resampled)

    def _roughen(self, moved: FloatArray, cov: FloatArray, rng: np.random.Generator) -> FloatArray:
        m, n = moved.shape
        h = self.roughen * (4.0 / (m * (n + 2))) ** (1.0 / (n + 4))
        l = make_pd(cov)[1]
        return self._wrap.state_value(moved + h * rng.standard_normal(moved.shape) @ l.T)

    def _innovation(
        self, w: FloatArray, zs: FloatArray, var: FloatArray, z: FloatArray, idx
    ) -> tuple[float, FloatArray, FloatArray | None]:
        """The NIS of ``z (q,)`` under the particles' predicted observations ``zs (M, q)``
        (variances ``var (M, q)``), their deviations from their mean ``(M, q)`` and the
        Cholesky factor of their covariance ``S (q, q)`` (NaN and None when ``S`` is not
        positive definite)."""
        periods = self._wrap.obs[idx]
        zhat = weighted_mean(zs, w, periods) if np.any(periods) else w @ zs
        dz = self._wrap.obs_diff(zs - zhat, idx)
        s = (dz * w[:, None]).T @ dz + np.diag(w @ var)
        try:
            ls = np.linalg.cholesky(s)
        except np.linalg.LinAlgError:
            return math.nan, dz, None
        return nis_from_cholesky(ls, self._wrap.obs_diff(z - zhat, idx)), dz, ls

    def _kalman_cov(self, prior: ParticleBelief, dz: FloatArray, ls: FloatArray | None) -> FloatArray:
        """Kalman-updated covariance ``P - Pxz S^-1 Pxz^T (n, n)`` of the predicted cloud, from
        :meth:`_innovation`'s deviations and factor (``P`` alone when ``S`` had none)."""
        dx = self._deviations(prior)[1]
        weighted = dx * prior.weights[:, None]
        pxx = weighted.T @ dx
        if ls is None:
            return pxx
        v = sla.solve_triangular(ls, (weighted.T @ dz).T, lower=True, check_finite=False)  # L^-1 Pxz^T
        return pxx - v.T @ v

    def step(
        self, belief: ParticleBelief, u: FloatArray, z: FloatArray | None = None,
        valid: NDArray[np.bool_] | None = None, rng: np.random.Generator | None = None,
    ) -> tuple[ParticleBelief, StepInfo]:  # fmt: skip
        """One GP-PF step (Table 1) with control ``u (k,)`` and the valid entries of ``z (m,)``;
        ``rng`` (required) draws the process noise and the resampling: the policy of
        :func:`~estimator_service.filters.policy.step_many` for a batch of one."""
        return step_one(self, belief, u, z, valid, _need_rng(rng, "step"))


def _need_rng(rng: np.random.Generator | None, method: str) -> np.random.Generator:
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"PF.{method}: 'rng' must be a numpy.random.Generator, got {type(rng).__name__}")
    return rng
