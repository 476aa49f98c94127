"""GP-PF (paper Table 1): particles sampled from their own predictive Gaussians."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray
from scipy.special import logsumexp

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

__all__ = ["BRIDGE_ESS", "BRIDGE_GAMMAS", "PF", "UPDATE_RULES", "systematic_resample"]

FloatArray = NDArray[np.float64]

#: the fraction of ``M`` the bridged update's weights keep as effective sample size (Frei &
#: Kuensch 2013 choose gamma so the particle part keeps about half the sample)
BRIDGE_ESS = 0.5
#: the gammas tried, smallest first: the least Kalman correction whose weights keep
#: :data:`BRIDGE_ESS` (gamma 1 is the ensemble Kalman filter's update alone)
BRIDGE_GAMMAS = np.linspace(0.1, 1.0, 10)
#: the PF's updates: the paper's Table 1, or bridged to an ensemble Kalman move (``PF.update_rule``)
UPDATE_RULES = ("table1", "bridge")


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
    update_rule
        ``"table1"``: weight by the likelihood (steps 5-11). ``"bridge"``: the same while the
        weights keep an effective sample size of :data:`BRIDGE_ESS` ``M``; when a reading is
        too sharp for the cloud (the weights collapse) the ensemble Kalman particle filter of
        Frei & Kuensch (2013, Biometrika 100, 781-800): the reading's likelihood is split
        into ``L^gamma`` (an ensemble Kalman move of every particle, with the particles'
        own predicted readings as the linearisation) and ``L^(1-gamma)`` (particle weights
        and resampling), with the smallest ``gamma`` of :data:`BRIDGE_GAMMAS` whose weights
        keep that sample size, or gamma 1 when none does. The ensemble part uses the
        particles' mean reading noise variance ``R`` (Table 1's weights, each particle's own).
        No roughening follows a bridged update: its particles are drawn from a Gaussian
        mixture, not copied.
    """

    __repr__ = short_repr

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None = None
    n_particles: int = 2000
    resample_below: float = 0.5
    roughen: float = 0.0
    roughen_cov: Literal["posterior", "kalman"] = "posterior"
    update_rule: Literal["table1", "bridge"] = "table1"
    name: str = "PF"

    def __post_init__(self) -> None:
        if self.roughen_cov not in ("posterior", "kalman"):
            raise ValueError(f"roughen_cov must be 'posterior' or 'kalman', got {self.roughen_cov!r}")
        if self.update_rule not in UPDATE_RULES:
            raise ValueError(f"update_rule must be one of {UPDATE_RULES}, got {self.update_rule!r}")

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
        """Steps 5-11: weight by the observation likelihood, resample when ESS is low; with
        ``update_rule="bridge"``, the bridged update instead when the weights keep less than
        :data:`BRIDGE_ESS` of the particles and every particle's predicted reading and its
        variance are finite (``rng`` required)."""
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
        m = prior.particles.shape[0]
        if self.update_rule == "bridge" and ess < BRIDGE_ESS * m and ls is not None and finite(zs, var):
            moved, ess, _ = self._bridge(prior, r, dz, prior.weights @ var, rng)
            post = ParticleBelief(moved, np.full(moved.shape[0], -math.log(moved.shape[0])))
            return post, StepInfo(nis, idx.size, implausible(nis, idx.size), ess, True)
        resampled = ess < self.resample_below * m
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

    def _bridge(
        self, prior: ParticleBelief, r: FloatArray, dz: FloatArray, rvar: FloatArray,
        rng: np.random.Generator,
    ) -> tuple[FloatArray, float, float]:  # fmt: skip
        """The ensemble Kalman particle update (Frei & Kuensch 2013): particles ``(M, n)``, the
        effective sample size of its weights and the ``gamma`` chosen.

        ``r (M, q)``: the reading minus each particle's predicted reading; ``dz (M, q)``: the
        predicted readings' deviations from their mean; ``rvar (q,)``: the reading's mean
        noise variance ``R``. With ``C = Pzz``, ``A = (C + R / gamma)^-1`` and ``B = A C``
        (``H`` is the particles' statistical linearisation, ``H K1 = C A``):
        ``nu = x + K1 r`` with ``K1 = Pxz A``; weights ``w N(d; 0, S2)`` with
        ``d = (R / gamma) A r`` and ``S2 = B^T R B / gamma + R / (1 - gamma)``; then
        ``nu + eta + K2 (d - H eta - zeta)`` for resampled ``nu``, with
        ``eta ~ N(0, K1 (R / gamma) K1^T)``, ``zeta ~ N(0, R / (1 - gamma))`` and
        ``K2 = K1 R B S2^-1 / gamma``.
        """
        w, lw = prior.weights, normalise_log_weights(prior.log_weights)
        dx = self._deviations(prior)[1]
        pxz, c = (dx * w[:, None]).T @ dz, (dz * w[:, None]).T @ dz
        gam, eye = BRIDGE_GAMMAS, np.eye(rvar.size)
        r_gamma = (rvar / gam[:, None])[:, :, None]  # R / gamma (G, q, 1)
        p = c + r_gamma * eye  # C + R / gamma (G, q, q)
        d = r_gamma * np.linalg.solve(p, np.broadcast_to(r.T, (gam.size, *r.T.shape)))  # (G, q, M)
        b = np.linalg.solve(p, np.broadcast_to(c, p.shape))  # A C (G, q, q)
        part = gam < 1.0  # gamma 1 leaves nothing to weight
        s2 = (b[part].transpose(0, 2, 1) @ (rvar[:, None] * b[part]) / gam[part, None, None]
              + (rvar / (1.0 - gam[part, None]))[:, :, None] * eye)  # fmt: skip
        logw = np.tile(lw, (gam.size, 1))
        logw[part] -= 0.5 * np.sum(d[part] * np.linalg.solve(s2, d[part]), axis=1)
        logw -= logsumexp(logw, axis=1, keepdims=True)
        ess = 1.0 / np.sum(np.exp(2 * logw), axis=1)
        ok = ess >= BRIDGE_ESS * w.size
        g = int(np.argmax(ok)) if ok.any() else gam.size - 1  # the smallest gamma that keeps it
        gamma = float(gam[g])
        k1t = sla.solve(p[g], pxz.T, assume_a="pos")  # (Pxz A)^T (q, n)
        keep = systematic_resample(np.exp(logw[g]), rng)
        noise = rng.standard_normal(r.shape) * np.sqrt(rvar / gamma)  # eta = K1 noise
        moved = prior.particles[keep] + (r[keep] + noise) @ k1t
        if part[g]:
            k2t = sla.solve(s2[g], b[g].T @ (rvar[:, None] * k1t), assume_a="pos") / gamma  # K2^T (q, n)
            zeta = rng.standard_normal(r.shape) * np.sqrt(rvar / (1.0 - gamma))
            moved = moved + (d[g].T[keep] - noise @ b[g] - zeta) @ k2t
        return self._wrap.state_value(moved), float(ess[g]), gamma

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
