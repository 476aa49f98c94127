"""GP-EKF (paper Table 2) and GP-UKF (paper Table 3)."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from estimator_service.filters.adaptive import MAX_INFLATION, adapted, check_adaptation, inflation_factors
from estimator_service.filters.batched import joseph, joseph_update_many
from estimator_service.filters.common import (
    GaussianBelief,
    StepInfo,
    Wrapping,
    distinct_indices,
    factorable,
    finite,
    implausible,
    nis_from_cholesky,
    sound_posterior,
    weighted_mean,
    wrap_periodic,
)
from estimator_service.filters.policy import step_one
from estimator_service.models.base import ObservationModel, PredictionModel, observe_columns
from estimator_service.reprs import short_repr

__all__ = ["EKF", "UKF", "kalman_update", "sigma_weights", "unscented_transform"]

FloatArray = NDArray[np.float64]


def kalman_update(
    prior: GaussianBelief, r: FloatArray, s: FloatArray, pxz: FloatArray,
    wrap: Wrapping, joseph_h: FloatArray | None = None, r_noise: FloatArray | None = None,
) -> tuple[GaussianBelief, StepInfo]:  # fmt: skip
    """Kalman update from innovation ``r``, its covariance ``s`` and cross-covariance ``pxz``.

    Skips the update (flagging divergence) when ``s`` is not positive definite or the
    result is not finite, cannot be factored or is not positive definite beyond rounding
    (:func:`sound_posterior`); never returns NaN.
    """
    try:
        ls = np.linalg.cholesky(0.5 * (s + s.T))
    except np.linalg.LinAlgError:
        return prior, StepInfo(math.nan, len(r), True)
    k = sla.cho_solve((ls, True), pxz.T, check_finite=False).T  # Pxz S^-1
    mean = wrap.state_value(prior.mean + k @ r)
    if joseph_h is not None:  # EKF: the Joseph form
        cov = joseph(prior.cov, k, joseph_h, r_noise)
    else:  # UKF: P - K S K^T
        cov = prior.cov - k @ s @ k.T
    nis = nis_from_cholesky(ls, r)
    pd = sound_posterior(cov) if finite(mean) else None  # refuses one that overflowed or went indefinite
    if pd is None:
        return prior, StepInfo(nis, len(r), True)
    return GaussianBelief(mean, pd[0]), StepInfo(nis, len(r), implausible(nis, len(r)))


class _GaussianFilter:
    """What the EKF and UKF share: angle handling and the predict-then-update step."""

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None

    adapt_rate: float
    max_inflation: float
    adapt_reference: float
    adapt_states: tuple[int, ...] | None

    @property
    def _wrap(self) -> Wrapping:
        return self.wrapping or Wrapping.none(self.prediction.state_dim, self.observation.obs_dim)

    def _check_adaptation(self) -> None:
        check_adaptation(self.adapt_rate, self.max_inflation, self.adapt_reference)
        if self.adapt_states is not None:
            n = self.prediction.state_dim
            if distinct_indices(self.adapt_states, n) is None:
                bad = self.adapt_states
                raise ValueError(f"adapt_states must be distinct state indices in [0, {n}), got {bad!r}")

    def _factors(self, lam: FloatArray, n: int) -> FloatArray:
        """The factors on the process variance ``(B, n)`` for the beliefs' inflations ``(B,)``."""
        return inflation_factors(lam, n, self.adapt_states)

    def _adapted(self, post: GaussianBelief, prior: GaussianBelief, info: StepInfo) -> GaussianBelief:
        return adapted(post, prior, info, self.adapt_rate, self.max_inflation, self.adapt_reference)

    def predict(
        self, belief: GaussianBelief, u: FloatArray, rng: np.random.Generator | None = None
    ) -> GaussianBelief:
        """The prediction (EKF: Table 2 steps 2-5; UKF: Table 3 steps 2-6) as a batch of one
        (``rng`` unused: the common filter interface)."""
        return self.predict_many([belief], np.asarray(u, dtype=np.float64)[None])[0]

    def update(
        self, prior: GaussianBelief, z: FloatArray, valid: NDArray[np.bool_] | None = None,
        rng: np.random.Generator | None = None,
    ) -> tuple[GaussianBelief, StepInfo]:  # fmt: skip
        """The update (EKF: Table 2 steps 6-11; UKF: Table 3 steps 7-15) with exactly the
        observation entries marked ``valid``, as a batch of one."""
        z = np.asarray(z, dtype=np.float64)
        v = np.ones(z.shape, bool) if valid is None else np.asarray(valid, dtype=bool)
        return self.update_many([prior], z[None], v[None])[0]

    def initial(self, belief: GaussianBelief, rng: np.random.Generator | None = None) -> GaussianBelief:
        """The filter's belief for a Gaussian start: the Gaussian itself."""
        return belief

    def gaussian(self, belief: GaussianBelief) -> GaussianBelief:
        """The Gaussian summary of a belief: the belief itself."""
        return belief

    def predict_many(self, beliefs: Sequence[GaussianBelief], u: FloatArray) -> list[GaussianBelief]:
        """:meth:`predict` of ``B`` beliefs with controls ``u (B, k)`` in one model call."""
        raise NotImplementedError

    def update_many(
        self, priors: Sequence[GaussianBelief], z: FloatArray, valid: NDArray[np.bool_]
    ) -> list[tuple[GaussianBelief, StepInfo]]:
        """:meth:`update` of ``B`` beliefs with ``z, valid: (B, m)`` in one model call."""
        raise NotImplementedError

    def step(
        self, belief: GaussianBelief, u: FloatArray, z: FloatArray | None = None,
        valid: NDArray[np.bool_] | None = None, rng: np.random.Generator | None = None,
    ) -> tuple[GaussianBelief, StepInfo]:  # fmt: skip
        """Predict with control ``u (k,)``, then update with the valid entries of ``z (m,)``:
        :func:`~estimator_service.filters.policy.step_many` for a batch of one (a non-finite
        prediction keeps ``belief`` and flags divergence). ``rng`` is accepted for the
        common filter interface (the Kalman filters draw nothing)."""
        return step_one(self, belief, u, z, valid, rng)


@dataclass(frozen=True)
class EKF(_GaussianFilter):
    """GP-EKF: linearise the models' means at the current estimate (paper Table 2).

    ``G = I + d(mean change)/dx`` and ``H = d(mean obs)/dx`` come from the models'
    Jacobians (paper eq. 20-22 for GPs); ``Q`` and ``R`` are the models' variances at the
    mean. The covariance update uses the Joseph form, which equals Table 2's
    ``(I - K H) Sigma`` for the optimal gain and stays symmetric positive definite.
    """

    __repr__ = short_repr

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None = None
    name: str = "EKF"
    adapt_rate: float = 0.0
    max_inflation: float = MAX_INFLATION
    adapt_reference: float = 1.0
    adapt_states: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        self._check_adaptation()

    def predict_many(self, beliefs: Sequence[GaussianBelief], u: FloatArray) -> list[GaussianBelief]:
        """:meth:`predict` for ``B`` independent beliefs in one model call (``u: (B, k)``).

        The service uses it to serve many blimps at once: one batched GP call instead of
        ``B`` single-query calls. Each result equals :meth:`predict` up to rounding.
        """
        means = np.stack([b.mean for b in beliefs])
        out = self.prediction.predict(means, u, jac=True)
        g = np.eye(means.shape[1]) + out.jac
        covs = g @ np.stack([b.cov for b in beliefs]) @ g.transpose(0, 2, 1)
        lam = np.array([b.inflation for b in beliefs])
        covs[:, *np.diag_indices(means.shape[1])] += out.var * self._factors(lam, means.shape[1])
        covs = 0.5 * (covs + covs.transpose(0, 2, 1))
        new_means = self._wrap.state_value(means + out.mean)
        return [GaussianBelief(m, c, f) for m, c, f in zip(new_means, covs, lam.tolist(), strict=True)]

    def update_many(
        self, priors: Sequence[GaussianBelief], z: FloatArray, valid: NDArray[np.bool_]
    ) -> list[tuple[GaussianBelief, StepInfo]]:
        """:meth:`update` for ``B`` beliefs, ``z: (B, m)``, ``valid: (B, m)``: one model call
        for all beliefs with any valid entry, then a small Kalman update each."""
        results: list[tuple[GaussianBelief, StepInfo]] = [(p, StepInfo()) for p in priors]
        rows = np.flatnonzero(valid.any(axis=1))
        if rows.size == 0:
            return results
        cols = np.flatnonzero(valid[rows].any(axis=0))  # only what some belief read is evaluated
        obs = observe_columns(self.observation, np.stack([priors[i].mean for i in rows]), cols, jac=True)
        groups: dict[bytes, list[int]] = {}
        for j, i in enumerate(rows):
            groups.setdefault(valid[i].tobytes(), []).append(j)
        for members in groups.values():  # blimps that saw the same entries: one batched update
            j = np.array(members)
            idx = np.flatnonzero(valid[rows[j[0]]])
            pos = np.searchsorted(cols, idx)  # idx among the evaluated columns
            h, r_noise = obs.jac[j][:, pos], obs.var[j][:, pos]
            r = self._wrap.obs_diff(z[rows[j]][:, idx] - obs.mean[j][:, pos], idx)
            mean = np.stack([priors[i].mean for i in rows[j]])
            cov = np.stack([priors[i].cov for i in rows[j]])

            def single(b: int, r=r, h=h, r_noise=r_noise, cov=cov, i=rows[j]) -> tuple:
                s = h[b] @ cov[b] @ h[b].T + np.diag(r_noise[b])
                return kalman_update(priors[i[b]], r[b], s, cov[b] @ h[b].T, self._wrap, h[b], r_noise[b])

            out = joseph_update_many(mean, cov, r, h, r_noise, self._wrap, single)
            for i, (post, info) in zip(rows[j], out, strict=True):
                results[i] = self._adapted(post, priors[i], info), info
        return results


def sigma_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[FloatArray, FloatArray, float]:
    """Unscented-transform weights: mean weights ``(2n+1,)``, covariance weights, ``gamma``."""
    lam = alpha * alpha * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + (1.0 - alpha * alpha + beta)
    return wm, wc, math.sqrt(n + lam)


def unscented_transform(
    ys: FloatArray, wm: FloatArray, wc: FloatArray, periods: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The unscented transform's moments of sigma points ``ys (N, d)`` after a function.

    Parameters
    ----------
    ys: (N, d)
        The transformed sigma points (:meth:`UKF.sigma_points` through the model).
    wm, wc: (N,)
        Mean and covariance weights (:func:`sigma_weights`).
    periods: (d,)
        Period of each component (0: not an angle): angles are averaged and differenced
        wrapped (:func:`~estimator_service.filters.common.weighted_mean`).

    Returns
    -------
    mean: (d,), deviations: (N, d), covariance: (d, d)
        ``sum wm_i y_i``, ``y_i - mean`` and ``sum wc_i dev_i dev_i^T`` (Julier and Uhlmann;
        Wan and van der Merwe's scaled form).
    """
    mean = weighted_mean(ys, wm, periods)
    dev = wrap_periodic(ys - mean, periods)
    return mean, dev, (dev * wc[:, None]).T @ dev


@dataclass(frozen=True)
class UKF(_GaussianFilter):
    """GP-UKF: unscented transform through the models' means (paper Table 3).

    All ``2n + 1`` sigma points go through a model in one batched call. ``Q`` and ``R`` are
    the models' variances at the mean (the paper's choice, ``noise="mean"``) or the
    plain average over the sigma points (``noise="sigma"``).

    ``alpha`` defaults to 1 (sigma points at ``+-sqrt(n + kappa)`` standard deviations), not
    the often quoted 1e-3: the mean weights then grow as ``1 / alpha^2`` (about 4e4 each for
    n = 12) and amplify a model's rounding noise a million-fold; a GP's mean is accurate to
    about 1e-8 of its scale (measured: docs/measurements.md#ukf-alpha).
    """

    __repr__ = short_repr

    prediction: PredictionModel
    observation: ObservationModel
    wrapping: Wrapping | None = None
    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    noise: str = "mean"
    name: str = "UKF"
    adapt_rate: float = 0.0
    max_inflation: float = MAX_INFLATION
    adapt_reference: float = 1.0
    adapt_states: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        if self.noise not in ("mean", "sigma"):
            raise ValueError(f"noise must be 'mean' or 'sigma', got {self.noise!r}")
        n = self.prediction.state_dim
        if not (self.alpha > 0 and n + self.kappa > 0):
            raise ValueError(
                f"UKF needs alpha > 0 and n + kappa > 0 (n = {n}), got {self.alpha}, {self.kappa}"
            )
        self._check_adaptation()
        _ = self._w  # the weights are computed once, with the filter

    @functools.cached_property
    def _w(self) -> tuple[FloatArray, FloatArray, float]:
        """Mean and covariance weights and ``gamma`` (:func:`sigma_weights`)."""
        return sigma_weights(self.prediction.state_dim, self.alpha, self.beta, self.kappa)

    def sigma_points(self, belief: GaussianBelief) -> FloatArray:
        """``(2n + 1, n)``: the mean, then ``mean +- gamma`` times the Cholesky columns (NaN
        where the covariance cannot be factored)."""
        pd = factorable(belief.cov)
        return self._points(belief.mean, None if pd is None else pd[1])

    def _points(self, mean: FloatArray, l: FloatArray | None) -> FloatArray:
        if l is None:
            return np.full((2 * mean.size + 1, mean.size), np.nan)
        d = self._w[2] * l.T
        return np.concatenate([mean[None], mean + d, mean - d])

    def _sigma_batch(self, beliefs: Sequence[GaussianBelief]) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Sigma points ``(B, 2n + 1, n)`` of ``beliefs`` for one model call, and which beliefs
        have none (a covariance that cannot be factored): for those the model sees only their
        mean (no model is asked about NaN, the GPs refuse it) and the rest of the batch goes
        on; the callers flag them."""
        pds = [factorable(b.cov) for b in beliefs]
        bad = np.array([pd is None for pd in pds])
        x = np.stack(
            [self._points(b.mean, None if pd is None else pd[1]) for b, pd in zip(beliefs, pds, strict=True)]
        )
        x[bad] = np.nan_to_num(np.stack([b.mean for b in beliefs])[bad])[:, None, :]
        return x, bad

    def predict_many(self, beliefs: Sequence[GaussianBelief], u: FloatArray) -> list[GaussianBelief]:
        """:meth:`predict` for ``B`` beliefs (``u: (B, k)``): every sigma point of every
        belief through the model in one call, then each belief's moments."""
        wm, wc, _ = self._w
        x, bad = self._sigma_batch(beliefs)  # (B, 2n + 1, n)
        nb, ns, n = x.shape
        out = self.prediction.predict(
            x.reshape(nb * ns, n), np.repeat(u, ns, axis=0), var=self.noise == "sigma"
        )
        xk = x + out.mean.reshape(nb, ns, n)
        if self.noise == "sigma":
            q = out.var.reshape(nb, ns, n).mean(axis=1)
        else:
            q = self.prediction.predict(x[:, 0], u).var
        results, factors = [], self._factors(np.array([b.inflation for b in beliefs]), n)
        for i, b in enumerate(beliefs):  # small algebra per belief; the model call was shared
            if bad[i]:  # no sigma points: a non-finite prediction, which the step flags
                results.append(GaussianBelief(np.full(n, np.nan), np.full((n, n), np.nan), b.inflation))
                continue
            mean, _, cov = unscented_transform(xk[i], wm, wc, self._wrap.state)
            cov = cov + np.diag(q[i] * factors[i])
            results.append(GaussianBelief(mean, 0.5 * (cov + cov.T), b.inflation))
        return results

    def update_many(
        self, priors: Sequence[GaussianBelief], z: FloatArray, valid: NDArray[np.bool_]
    ) -> list[tuple[GaussianBelief, StepInfo]]:
        """:meth:`update` for ``B`` beliefs, ``z: (B, m)``, ``valid: (B, m)``: the sigma points
        of every belief with any valid entry through the model in one call."""
        results: list[tuple[GaussianBelief, StepInfo]] = [(p, StepInfo()) for p in priors]
        rows = np.flatnonzero(valid.any(axis=1))
        if rows.size == 0:
            return results
        x, bad = self._sigma_batch([priors[i] for i in rows])  # (R, 2n + 1, n)
        nr, ns, n = x.shape
        cols = np.flatnonzero(valid[rows].any(axis=0))  # only what some belief read is evaluated
        out = observe_columns(self.observation, x.reshape(nr * ns, n), cols, var=self.noise == "sigma")
        zs_all = out.mean.reshape(nr, ns, -1)
        if self.noise == "sigma":
            r_all = out.var.reshape(nr, ns, -1).mean(axis=1)
        else:
            r_all = observe_columns(self.observation, x[:, 0], cols).var
        for j, i in enumerate(rows):
            idx = np.flatnonzero(valid[i])
            pos = np.searchsorted(cols, idx)
            if bad[j]:  # no sigma points: the update is refused, as for a non-factorable S
                results[i] = priors[i], StepInfo(math.nan, len(idx), True)
                continue
            results[i] = self._update_one(priors[i], x[j], zs_all[j][:, pos], r_all[j, pos], z[i], idx)
        return results

    def _update_one(
        self, prior: GaussianBelief, x: FloatArray, zs: FloatArray, r_noise: FloatArray, z: FloatArray,
        idx: NDArray[np.intp],
    ) -> tuple[GaussianBelief, StepInfo]:  # fmt: skip
        """Steps 9-15 of Table 3 for one belief: sigma points ``x``, their predicted valid
        observations ``zs`` and the observation noise ``r_noise`` of the valid entries ``idx``."""
        wm, wc, _ = self._w
        zhat, dz, s = unscented_transform(zs, wm, wc, self._wrap.obs[idx])
        s = s + np.diag(r_noise)
        dx = self._wrap.state_diff(x - prior.mean)
        pxz = (dx * wc[:, None]).T @ dz
        r = self._wrap.obs_diff(np.asarray(z, dtype=np.float64)[idx] - zhat, idx)
        post, info = kalman_update(prior, r, s, pxz, self._wrap)
        return self._adapted(post, prior, info), info
