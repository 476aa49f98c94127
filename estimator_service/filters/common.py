"""Beliefs, step reports, angle handling and covariance hygiene shared by all filters."""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import logsumexp
from scipy.stats import chi2

from estimator_service.angles import wrap_angle
from estimator_service.frozen import normalise
from estimator_service.reprs import short_repr

__all__ = [
    "GaussianBelief",
    "ParticleBelief",
    "StepInfo",
    "Wrapping",
    "distinct_indices",
    "factorable",
    "make_pd",
    "nis_from_cholesky",
    "sound_posterior",
]

FloatArray = NDArray[np.float64]
DIVERGENCE_P = 1e-9  # an innovation this improbable under chi^2 flags divergence
#: an updated covariance's eigenvalue below ``-ROUNDING * trace`` is not rounding error
ROUNDING = 1e-9


@dataclass(frozen=True)
class GaussianBelief:
    """``N(mean, cov)``: ``mean (n,)``, ``cov (n, n)``.

    ``inflation`` is the process-noise factor an adaptive Kalman filter carries from step
    to step (:mod:`estimator_service.filters.adaptive`); 1 for every other filter.
    """

    mean: FloatArray
    cov: FloatArray
    inflation: float = 1.0

    def __post_init__(self) -> None:
        m, c = np.asarray(self.mean, dtype=np.float64), np.asarray(self.cov, dtype=np.float64)
        if m.ndim != 1 or c.shape != (m.size, m.size):
            raise ValueError(f"belief mean (n,) and cov (n, n) expected, got {m.shape}, {c.shape}")
        if not (math.isfinite(self.inflation) and self.inflation > 0):
            raise ValueError(f"belief inflation must be finite and > 0, got {self.inflation!r}")
        normalise(self, mean=m, cov=c)

    def __repr__(self) -> str:
        with np.printoptions(precision=3, suppress=True, threshold=24, linewidth=400):
            return f"GaussianBelief(mean={self.mean}, std={np.sqrt(np.abs(np.diag(self.cov)))})"


@dataclass(frozen=True)
class ParticleBelief:
    """Weighted particles: ``particles (M, n)`` and normalised ``log_weights (M,)``."""

    __repr__ = short_repr

    particles: FloatArray
    log_weights: FloatArray

    @classmethod
    def from_gaussian(
        cls, belief: GaussianBelief, n_particles: int, rng: np.random.Generator
    ) -> ParticleBelief:
        """``n_particles`` equally weighted draws from a Gaussian belief."""
        l = make_pd(belief.cov)[1]
        x = belief.mean + rng.standard_normal((n_particles, belief.mean.size)) @ l.T
        return cls(x, np.full(n_particles, -math.log(n_particles)))

    @property
    def weights(self) -> FloatArray:
        return np.exp(self.log_weights)

    @property
    def ess(self) -> float:
        """Effective sample size ``1 / sum w^2``."""
        return float(1.0 / np.sum(np.exp(2.0 * self.log_weights)))


@dataclass(frozen=True)
class StepInfo:
    """What one filter step reports besides the belief.

    Attributes
    ----------
    nis
        Normalised innovation squared ``r^T S^-1 r`` (NaN when nothing was observed).
    dof
        Number of observation values used (its chi-square degrees of freedom).
    diverged
        True when the update was numerically unusable (it was then skipped) or the
        innovation is implausible (chi-square tail below ``1e-9``).
    ess
        Effective sample size after weighting (particle filter only).
    resampled
        Whether the particle filter resampled.
    gated
        Whether an innovation gate refused the update (the belief is the prediction; ``nis``
        is the refused update's and ``dof`` 0).
    """

    nis: float = math.nan
    dof: int = 0
    diverged: bool = False
    ess: float | None = None
    resampled: bool = False
    gated: bool = False

    def refused(self) -> StepInfo:
        """This update's report after an innovation gate refused it: the belief is the
        prediction (``dof`` 0), the refused update's NIS is kept."""
        return StepInfo(self.nis, 0, False, gated=True)


@dataclass(frozen=True)
class Wrapping:
    """Periodic components of the state and the observation (0 = not periodic).

    E.g. Euler angles have period ``2 pi``; an ellipse orientation has period ``pi``.
    """

    state: FloatArray
    obs: FloatArray

    @classmethod
    def none(cls, n: int, m: int) -> Wrapping:
        return cls(np.zeros(n), np.zeros(m))

    def state_diff(self, d: FloatArray) -> FloatArray:
        return wrap_periodic(d, self.state)

    def obs_diff(self, d: FloatArray, idx: NDArray[np.intp] | slice = slice(None)) -> FloatArray:
        return wrap_periodic(d, self.obs[idx])

    def state_value(self, x: FloatArray) -> FloatArray:
        """Angles of a state wrapped into ``[-p/2, p/2)`` (:mod:`estimator_service.angles`)."""
        return wrap_periodic(x, self.state)

    def circular_mean(self, values: FloatArray, weights: FloatArray) -> FloatArray:
        """Weighted mean of particles with non-negative weights (atan2 for angles)."""
        lin = weights @ values
        p = np.where(self.state > 0, self.state, 2 * math.pi)
        ang = 2 * math.pi * values / p
        circ = p / (2 * math.pi) * np.arctan2(weights @ np.sin(ang), weights @ np.cos(ang))
        return np.where(self.state > 0, circ, lin)


def wrap_periodic(d: FloatArray, periods: FloatArray) -> FloatArray:
    """``d`` with its components of period ``> 0`` wrapped (:mod:`estimator_service.angles`)."""
    return wrap_angle(d, periods) if np.any(periods) else d


def weighted_mean(values: FloatArray, weights: FloatArray, periods: FloatArray) -> FloatArray:
    """Weighted mean ``(n,)`` of rows ``values (K, n)`` with periodic components (``periods``).

    Periodic components average the wrapped offsets from the first row, which is exact
    for a linear spread and allows the UKF's negative centre weight.
    """
    ref = values[0]
    return wrap_periodic(ref + weights @ wrap_periodic(values - ref, periods), periods)


def make_pd(cov: FloatArray, floor: float = 1e-12) -> tuple[FloatArray, FloatArray]:
    """Symmetrise ``cov`` and return it with its lower Cholesky factor.

    If it is not positive definite, eigenvalues are raised to ``floor * trace / n``.
    """
    c = 0.5 * (cov + cov.T)
    try:
        return c, np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        pass
    w, v = np.linalg.eigh(c)
    eps = max(floor * float(np.trace(c)) / len(c), floor)
    c = (v * np.maximum(w, eps)) @ v.T
    c = 0.5 * (c + c.T)
    return c, np.linalg.cholesky(c + eps * np.eye(len(c)))


def factorable(cov: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """:func:`make_pd` of ``cov``, or None where no finite factor exists (a covariance that
    blew up: overflowing entries, or one that no eigenvalue floor makes factorable)."""
    try:
        with np.errstate(all="ignore"):
            c, l = make_pd(cov)
    except np.linalg.LinAlgError:
        return None
    return (c, l) if np.isfinite(c).all() and np.isfinite(l).all() else None


def sound_posterior(cov: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """:func:`factorable` of an updated covariance, or None where it is not positive
    definite beyond rounding: an eigenvalue below ``-ROUNDING * trace`` means the update
    claimed more than the prior knew (a UKF's ``P - K S K^T`` with sigma points far in a
    nonlinear model's tails), which no eigenvalue floor repairs honestly. Measured on a
    held-out lab flight with a knocked camera (200-point GP-UKF): one update left an
    eigenvalue of -0.22 against a trace of 1.57; floored, the next truth's NEES was 2.3e11."""
    c = 0.5 * (cov + cov.T)
    if np.isfinite(c).all():
        try:
            return c, np.linalg.cholesky(c)
        except np.linalg.LinAlgError:
            lowest = float(np.linalg.eigvalsh(c)[0])
            if lowest < -ROUNDING * max(float(np.trace(c)), 0.0):
                return None
    return factorable(cov)


def nis_from_cholesky(ls: FloatArray, r: FloatArray) -> float:
    """``r^T S^-1 r`` given the lower Cholesky factor of ``S``."""
    from scipy.linalg import solve_triangular

    w = solve_triangular(ls, r, lower=True, check_finite=False)
    return float(w @ w)


def implausible(nis: float, dof: int) -> bool:
    """Chi-square tail probability of ``nis`` below :data:`DIVERGENCE_P`."""
    return dof > 0 and (not math.isfinite(nis) or chi2.sf(nis, dof) < DIVERGENCE_P)


def normalise_log_weights(logw: FloatArray) -> FloatArray:
    """``logw - logsumexp(logw)``."""
    return logw - logsumexp(logw)


def finite(*arrays: FloatArray) -> bool:
    return all(bool(np.isfinite(a).all()) for a in arrays)


def distinct_indices(values: object, n: int) -> tuple[int, ...] | None:
    """``values`` as distinct integer indices into ``n`` components, or None when they are
    not (not a sequence of integers, empty, repeated or out of range): the one rule for a
    system's ``disturbed`` states and a filter's ``adapt_states``."""
    try:
        idx = tuple(operator.index(i) for i in values)  # type: ignore[attr-defined]
    except TypeError:
        return None
    return idx if idx and len(set(idx)) == len(idx) and all(0 <= i < n for i in idx) else None
