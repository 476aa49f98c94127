"""Most-likely heteroscedastic GP (Kersting et al. 2007; paper Sect. 3.1.4).

An EM-like loop per output: (1) fit a GP to the data; (2) estimate the noise level at
every training point as ``z_i = log((y_i - mu_i)^2 + var_i)``, the log expected squared
residual under the current predictive distribution; (3) fit a second GP to ``z``; (4) refit
the first GP with per-point noise ``sn^2 exp(z_hat(x_i))``; repeat. Predicted noise then
depends on the input: ``var(x) = var_latent(x) + sn^2 exp(z_hat(x))``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.base import (
    GPPrediction,
    ProgressCallback,
    Scaler,
    check_conditioning_data,
    check_query,
    check_training_data,
)
from estimator_service.gp.exact import ExactGP, fit_exact, unscale
from estimator_service.gp.hyper import learn_thetas, random_subset
from estimator_service.reprs import short_repr

__all__ = ["HeteroscedasticGP", "fit_hetero"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class HeteroscedasticGP:
    """Mean GP with per-point training noise plus a GP on the log noise level.

    Attributes
    ----------
    main: ExactGP
        The GP of the targets, trained with ``noise_profile = exp(z_hat(x_i))``.
    noise: ExactGP
        GP of ``log`` relative noise over standardised inputs (one output per target).
    """

    __repr__ = short_repr

    main: ExactGP
    noise: ExactGP
    kind: str = "hetero"

    @property
    def input_dim(self) -> int:
        return self.main.input_dim

    @property
    def output_dim(self) -> int:
        return self.main.output_dim

    def conditioned(self, x: FloatArray, y: FloatArray) -> HeteroscedasticGP:
        """The same hyperparameters, scalers and noise GP, conditioned on other data
        ``x (n, d)``, ``y (n, P)`` (original units): the mean GP's per-point noise comes from
        the noise GP at the new inputs."""
        m = self.main
        xa, ya = check_conditioning_data(x, y, self.input_dim, self.output_dim)
        xs, ys = m.x_scaler.apply(xa), m.y_scaler.apply(ya)
        profile = np.exp(self.noise.predict(xs, return_var=False).mean).T  # (P, n)
        main = ExactGP.from_theta(xs, ys, m.theta, m.x_scaler, m.y_scaler, noise_profile=profile)
        return HeteroscedasticGP(main, self.noise)

    def noise_var(self, x: FloatArray) -> FloatArray:
        """Input-dependent noise variance ``(M, P)`` in original units."""
        xs = self.main.x_scaler.apply(check_query(x, self.input_dim))
        return self._noise_var_standardised(xs) * self.main.y_scaler.std**2

    def _noise_var_standardised(self, xs: FloatArray) -> FloatArray:
        log_rel = self.noise.predict(xs, return_var=False).mean
        return np.exp(2.0 * self.main.theta[:, -1]) * np.exp(log_rel)

    def predict(
        self, x: FloatArray, *, return_var: bool = True, return_jac: bool = False,
        include_noise: bool = True,
    ) -> GPPrediction:  # fmt: skip
        """Batched prediction for queries ``x (M, d)``; see :class:`GPPrediction`."""
        xs = self.main.x_scaler.apply(check_query(x, self.input_dim))
        mean, var, jac = self.main.latent(xs, return_var, return_jac)
        if var is not None and include_noise:
            var = var + self._noise_var_standardised(xs)
        return unscale(self.main.x_scaler, self.main.y_scaler, mean, var, jac)


def fit_hetero(
    x: FloatArray,
    y: FloatArray,
    *,
    iterations: int = 3,
    restarts: int = 2,
    max_iter: int = 150,
    rng: np.random.Generator | None = None,
    callback: ProgressCallback | None = None,
    hyper_points: int | None = None,
    polish_iter: int = 15,
) -> HeteroscedasticGP:
    """Learn a most-likely heteroscedastic GP per output column.

    Parameters
    ----------
    x: (n, d)
    y: (n, P) or (n,)
    iterations
        EM-like rounds (noise estimate, noise GP, refit).
    restarts, max_iter, hyper_points, polish_iter
        For the first mean GP and each noise GP, as in :func:`fit_exact`. Each refit of the
        mean GP under a new noise profile starts from the previous hyperparameters and runs
        ``max_iter`` iterations on the ``hyper_points`` subset (then ``polish_iter`` on all)
        when set, else ``max_iter`` on all points.
    """
    xa, ya = check_training_data(x, y, min_points=3)
    rng = np.random.default_rng(0) if rng is None else rng
    xsc, ysc = Scaler.fit(xa), Scaler.fit(ya)
    xs, ys = xsc.apply(xa), ysc.apply(ya)
    opts = {"max_iter": max_iter, "rng": rng, "callback": callback, "hyper_points": hyper_points,
            "polish_iter": polish_iter}  # fmt: skip
    main = fit_exact(xs, ys, restarts=restarts, **opts)
    main = ExactGP.from_theta(xs, ys, main.theta, xsc, ysc)  # same fit, our scalers
    noise_gp: ExactGP | None = None
    for _ in range(max(1, iterations)):
        mu, var, _ = main.latent(xs, True, False)
        z = np.log((ys - mu) ** 2 + var + 1e-12)
        noise_gp = fit_exact(xs, z, restarts=1, **opts)
        log_rel = noise_gp.predict(xs, return_var=False).mean
        profile = np.exp(log_rel - log_rel.mean(axis=0)).T  # (P, n), geometric mean 1
        subset = random_subset(len(xs), hyper_points, rng)
        theta = learn_thetas(
            xs, ys, [[t] for t in main.theta], max_iter=max_iter, name="hetero", callback=callback,
            profile=profile, subset=subset, polish_iter=polish_iter,
        )  # fmt: skip
        main = ExactGP.from_theta(xs, ys, theta, xsc, ysc, noise_profile=profile)
        # the noise GP predicts log_rel; shift so that exp(shifted) equals the profile
        noise_gp = _shift_mean(noise_gp, -log_rel.mean(axis=0))
    assert noise_gp is not None
    return HeteroscedasticGP(main, noise_gp)


def _shift_mean(gp: ExactGP, shift: FloatArray) -> ExactGP:
    """The same GP with its output mean moved by ``shift (P,)``."""
    return dataclasses.replace(gp, y_scaler=Scaler(gp.y_scaler.mean + shift, gp.y_scaler.std))
