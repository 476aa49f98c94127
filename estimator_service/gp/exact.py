"""Exact GP regression: the fitted posterior and its batched prediction (paper eq. 1-3,
20-22); hyperparameters are learned in :mod:`estimator_service.gp.hyper` (eq. 5-10)."""

from __future__ import annotations

import functools
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
from estimator_service.gp.hyper import initial_thetas, learn_thetas, random_subset
from estimator_service.gp.inverse import InverseBlocks
from estimator_service.gp.kernel import CrossKernel, se_kernel, split_theta
from estimator_service.gp.linalg import (
    chol_solve,
    inverse_factor,
    robust_cholesky,
    single_threaded_blas,
    tri_solve,
)
from estimator_service.gp.parallel import over_outputs
from estimator_service.reprs import short_repr

__all__ = ["ExactGP", "cholesky_factors", "fit_exact", "unscale"]

FloatArray = NDArray[np.float64]
#: more queries than this, a prediction with variances goes output by output over threads
#: (kernel block, mean, variance by the inverse factor's row blocks); up to it, all outputs at
#: once: one kernel block, one stacked product per row block
#: (:meth:`~estimator_service.gp.inverse.InverseBlocks.sq_norms`); measured:
#: docs/measurements.md#exact-gp-stacked-queries
STACKED_MAX_QUERIES = 32
_CHUNK_BYTES = 256 * 2**20  # cap on the (P, M, n) kernel block held at once


@dataclass(frozen=True, eq=False)
class ExactGP:
    """A fitted exact multi-output GP: one independent SE-ARD GP per output.

    Built by :func:`fit_exact` (or :meth:`from_theta`); holds everything prediction needs,
    computed once. Inputs and targets are standardised internally.

    Attributes
    ----------
    theta: (P, d + 2)
        Log hyperparameters per output, in standardised units.
    x_train: (n, d)
        Standardised training inputs.
    chol_t: (P, n, n)
        Transposed lower Cholesky factors of ``K + noise`` (so ``chol_t[p].T`` is
        Fortran-ordered for BLAS).
    alpha: (P, n)
        ``(K + noise)^-1 y`` per output.
    noise_profile: (P, n) or None
        Relative per-point training noise (heteroscedastic GP), None when homoscedastic.
    inverse: bool
        Predictive variances from the explicit inverse factors ``L^-1`` (computed once, on
        the first variance request, per output whose factor is well conditioned; see
        :func:`~estimator_service.gp.linalg.inverse_factor`), held as stacked row blocks
        (:class:`~estimator_service.gp.inverse.InverseBlocks`), instead of a triangular
        solve. ``tests/test_gp.py`` bounds the difference on a near-noiseless GP.
    """

    __repr__ = short_repr

    x_scaler: Scaler
    y_scaler: Scaler
    theta: FloatArray
    x_train: FloatArray
    chol_t: FloatArray
    alpha: FloatArray
    noise_profile: FloatArray | None = None
    kind: str = "exact"
    inverse: bool = True

    def __post_init__(self) -> None:
        for arr in (self.theta, self.x_train, self.chol_t, self.alpha):
            arr.flags.writeable = False
        _ = self._kernel  # built with the posterior; the inverse factors on the first variance request

    @functools.cached_property
    def _kernel(self) -> CrossKernel:
        return CrossKernel.build(self.x_train, self.theta, self.alpha)

    def inverse_blocks(self) -> InverseBlocks:
        """The outputs' ``L^-1`` as row blocks (computed on the first call, then held)."""
        return self._inverse_blocks

    @functools.cached_property
    def _inverse_blocks(self) -> InverseBlocks:
        factors = (inverse_factor(self.chol_t[p].T) for p in range(self.output_dim))
        return InverseBlocks.from_factors(factors, self.output_dim, self.alpha.shape[1])

    @classmethod
    def from_theta(
        cls, x: FloatArray, y: FloatArray, theta: FloatArray, x_scaler: Scaler, y_scaler: Scaler,
        noise_profile: FloatArray | None = None,
    ) -> ExactGP:  # fmt: skip
        """Posterior for standardised data ``x (n, d)``, ``y (n, P)`` and ``theta (P, d+2)``."""
        chol_t = cholesky_factors(x, theta, noise_profile)
        alpha = np.stack([chol_solve(chol_t[p].T, y[:, p]) for p in range(y.shape[1])])
        return cls(x_scaler, y_scaler, np.asarray(theta, dtype=np.float64), x, chol_t, alpha, noise_profile)

    def conditioned(self, x: FloatArray, y: FloatArray) -> ExactGP:
        """The same hyperparameters and scalers, conditioned on other data ``x (n, d)``,
        ``y (n, P)`` (original units): e.g. a fold of the training data that leaves out the
        block a calibration scores it on (:mod:`estimator_service.crossfit`)."""
        xa, ya = check_conditioning_data(x, y, self.input_dim, self.output_dim)
        xs, ys = self.x_scaler.apply(xa), self.y_scaler.apply(ya)
        return ExactGP.from_theta(xs, ys, self.theta, self.x_scaler, self.y_scaler)

    @property
    def input_dim(self) -> int:
        return self.x_train.shape[1]

    @property
    def output_dim(self) -> int:
        return self.theta.shape[0]

    @property
    def noise_var(self) -> FloatArray:
        """Noise variance per output ``(P,)`` in original units (homoscedastic part)."""
        return np.exp(2 * self.theta[:, -1]) * self.y_scaler.std**2

    def latent(
        self, xs: FloatArray, return_var: bool, return_jac: bool
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        """Standardised latent mean ``(M, P)``, variance ``(M, P)``, Jacobian ``(M, P, d)``."""
        p_out, n = self.alpha.shape
        chunk = max(1, _CHUNK_BYTES // (8 * p_out * n))
        if xs.shape[0] > chunk:
            parts = [
                self.latent(xs[i : i + chunk], return_var, return_jac) for i in range(0, xs.shape[0], chunk)
            ]
            return tuple(
                None if parts[0][j] is None else np.concatenate([q[j] for q in parts]) for j in range(3)
            )  # type: ignore[return-value]
        if return_var and xs.shape[0] > STACKED_MAX_QUERIES:
            return self._latent_by_output(xs, return_jac)
        ks, mean, jac = self._kernel(xs, return_jac)
        return mean, self._variance(ks) if return_var else None, jac

    def _variance(self, ks: FloatArray) -> FloatArray:
        """Latent variances ``(M, P)`` from the kernel block ``ks (P, M, n)`` (overwritten for
        outputs that solve): the inverse factors' blocks for all outputs, the triangular
        solve for outputs without a factor."""
        if self.inverse:
            inv = self.inverse_blocks()
            sq, solve = inv.sq_norms_threaded(ks), np.flatnonzero(~inv.has_factor)
        else:
            sq, solve = np.zeros(ks.shape[:2]), np.arange(self.output_dim)
        for p in solve:
            sq[p] = self._solved_sq_norms(ks[p], p)
        sf2 = np.exp(2.0 * self.theta[:, -2])
        return np.maximum(sf2[:, None] - sq, 0.0).T

    def _solved_sq_norms(self, k: FloatArray, p: int) -> FloatArray:
        """``|L_p^-1 k_q|^2 (M,)`` by the triangular solve, for output ``p``'s kernel rows
        ``k (M, n)`` (overwritten)."""
        v = tri_solve(self.chol_t[p].T, k.T, overwrite_b=True)
        return np.einsum("nm,nm->m", v, v)

    def _latent_by_output(
        self, xs: FloatArray, return_jac: bool
    ) -> tuple[FloatArray, FloatArray, FloatArray | None]:
        """Mean, variance ``(M, P)`` and Jacobian ``(M, P, d)``, output by output (kernel
        block, mean, variance by row blocks of ``L^-1`` or by the solve), the outputs spread
        over threads (:func:`~estimator_service.gp.parallel.over_outputs`)."""
        p_out = self.output_dim
        mean, var = np.empty((xs.shape[0], p_out)), np.empty((xs.shape[0], p_out))
        jac = np.empty((xs.shape[0], p_out, xs.shape[1])) if return_jac else None
        sf2 = np.exp(2.0 * self.theta[:, -2])
        inv = self.inverse_blocks() if self.inverse else None
        kern = self._kernel

        def one(p: int) -> None:
            k = kern.block_one(xs, p)
            mean[:, p] = k @ self.alpha[p]
            if jac is not None:
                jac[:, p] = (k @ kern.weighted_centres[p] - xs * mean[:, p, None]) / kern.ell[p] ** 2
            if inv is not None and inv.has_factor[p]:
                var[:, p] = sf2[p] - inv.sq_norms(k[None], slice(p, p + 1))[0]
            else:
                var[:, p] = sf2[p] - self._solved_sq_norms(k, p)

        over_outputs(one, p_out)
        return mean, np.maximum(var, 0.0, out=var), jac

    def noise_var_standardised(self, xs: FloatArray) -> FloatArray:
        """Standardised noise variance at queries ``xs (M, d)`` -> ``(M, P)``."""
        return np.broadcast_to(np.exp(2 * self.theta[:, -1]), (xs.shape[0], self.output_dim))

    def predict(
        self, x: FloatArray, *, return_var: bool = True, return_jac: bool = False,
        include_noise: bool = True,
    ) -> GPPrediction:  # fmt: skip
        """Batched prediction for queries ``x (M, d)``; see :class:`GPPrediction`."""
        xq = check_query(x, self.input_dim)
        xs = self.x_scaler.apply(xq)
        mean, var, jac = self.latent(xs, return_var, return_jac)
        if var is not None and include_noise:
            var = var + self.noise_var_standardised(xs)
        return unscale(self.x_scaler, self.y_scaler, mean, var, jac)


def cholesky_factors(x: FloatArray, theta: FloatArray, noise_profile: FloatArray | None = None) -> FloatArray:
    """Transposed lower Cholesky factors of ``K + noise`` per output: ``chol_t (P, n, n)``
    for standardised inputs ``x (n, d)``, ``theta (P, d + 2)`` and the relative per-point
    noise ``noise_profile (P, n)`` (None: homoscedastic).

    Factored on one BLAS thread, so the factors are the same bits whatever thread count the
    caller runs with (a multi-threaded ``potrf`` rounds differently): a model file keeps
    ``alpha`` but not these factors, and a loaded GP predicts exactly as the fitted one.
    """
    n, p_out = x.shape[0], theta.shape[0]
    chol_t = np.empty((p_out, n, n))
    prof = np.ones((p_out, n)) if noise_profile is None else noise_profile
    with single_threaded_blas():
        for p in range(p_out):  # training or load time only
            ell, sf2, sn2 = split_theta(theta[p])
            k = se_kernel(x, x, ell, sf2)
            k[np.diag_indices_from(k)] += sn2 * prof[p]
            chol_t[p] = robust_cholesky(k)[0].T
    return chol_t


def unscale(
    xsc: Scaler, ysc: Scaler, mean: FloatArray, var: FloatArray | None, jac: FloatArray | None
) -> GPPrediction:
    """Standardised predictions back to original units."""
    return GPPrediction(
        mean=mean * ysc.std + ysc.mean,
        var=None if var is None else var * ysc.std**2,
        jac=None if jac is None else jac * (ysc.std[:, None] / xsc.std[None, :]),
    )


def fit_exact(
    x: FloatArray,
    y: FloatArray,
    *,
    restarts: int = 3,
    max_iter: int = 200,
    rng: np.random.Generator | None = None,
    callback: ProgressCallback | None = None,
    hyper_points: int | None = None,
    polish_iter: int = 15,
) -> ExactGP:
    """Learn one SE-ARD GP per output column by maximising the marginal likelihood.

    Parameters
    ----------
    x: (n, d)
        Training inputs.
    y: (n, P) or (n,)
        Training targets.
    restarts
        L-BFGS-B runs per output from :func:`initial_thetas`; the best is kept.
    max_iter
        Iterations per run.
    rng
        For the random restarts (beyond the third), the distance sample and the subset.
    callback
        Receives a :class:`Progress` every optimiser iteration.
    hyper_points
        When set and smaller than ``n``: the restarts run on a random subset of this many
        points (``(n / hyper_points)^3`` times cheaper per iteration), then ``polish_iter``
        iterations on all points start from the subset's optimum. The posterior always
        uses all points.
    """
    xa, ya = check_training_data(x, y, min_points=3)
    rng = np.random.default_rng(0) if rng is None else rng
    xsc, ysc = Scaler.fit(xa), Scaler.fit(ya)
    xs, ys = xsc.apply(xa), ysc.apply(ya)
    starts = initial_thetas(xs, max(1, restarts), rng)
    subset = random_subset(len(xs), hyper_points, rng)
    theta = learn_thetas(
        xs, ys, [starts] * ys.shape[1], max_iter=max_iter, name="exact", callback=callback,
        subset=subset, polish_iter=polish_iter,
    )  # fmt: skip
    return ExactGP.from_theta(xs, ys, theta, xsc, ysc)
