"""Sparse pseudo-input GP (SPGP / FITC, Snelson & Ghahramani 2006; paper Sect. 3.1.3).

The covariance of the targets is ``C = Q + Lambda`` with ``Q = K_nm K_mm^-1 K_mn`` and the
diagonal ``Lambda = diag(K_nn - Q) + sn^2``. Pseudo-input locations and hyperparameters
are learned together by L-BFGS-B on the exact gradient of ``-log N(y; 0, C)``, in
``O(n m^2)`` per evaluation. Prediction costs ``O(m)`` for the mean and ``O(m^2)`` for the
variance per query and output.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from estimator_service.gp.base import (
    GPPrediction,
    ProgressCallback,
    Scaler,
    check_conditioning_data,
    check_query,
    check_training_data,
)
from estimator_service.gp.exact import unscale
from estimator_service.gp.hyper import initial_thetas, optimize_theta, theta_bounds
from estimator_service.gp.kernel import CrossKernel, split_theta, sq_dist
from estimator_service.gp.linalg import (
    chol_solve,
    inverse_factor,
    robust_cholesky,
    single_threaded_blas,
    tri_solve,
)
from estimator_service.gp.parallel import over_outputs
from estimator_service.reprs import short_repr

__all__ = ["SparseGP", "fit_sparse", "sparse_nll"]

FloatArray = NDArray[np.float64]
#: queries above which a batch goes output by output over threads; measured:
#: docs/measurements.md#sparse-gp-queries-by-output
BY_OUTPUT_MIN_QUERIES = 600


def _lower_solve(l: FloatArray, b: FloatArray) -> FloatArray:
    return sla.solve_triangular(l, b, lower=True, check_finite=False)


def _pieces(theta: FloatArray, z: FloatArray, x: FloatArray) -> dict[str, FloatArray]:
    """Shared FITC quantities in the numerically stable (whitened) form."""
    ell, sf2, sn2 = split_theta(theta)
    zs, xs = z / ell, x / ell
    kmm = sf2 * np.exp(-0.5 * sq_dist(zs, zs))
    lm, jitter = robust_cholesky(kmm)
    kmn = sf2 * np.exp(-0.5 * sq_dist(zs, xs))
    v = _lower_solve(lm, kmn)  # (m, n), V^T V = Q
    lam = np.maximum(sf2 - np.sum(v * v, axis=0), 0.0) + sn2
    vl = v / lam
    b_mat = np.eye(len(z)) + vl @ v.T
    lb, _ = robust_cholesky(b_mat)
    return {"ell": ell, "sf2": sf2, "sn2": sn2, "zs": zs, "xs": xs, "kmm": kmm, "jitter": jitter,
            "kmn": kmn, "lm": lm, "v": v, "lam": lam, "vl": vl, "lb": lb}  # fmt: skip


def sparse_nll(params: FloatArray, x: FloatArray, y: FloatArray, m: int) -> tuple[float, FloatArray]:
    """FITC negative log marginal likelihood and its gradient.

    Parameters
    ----------
    params: (d + 2 + m * d,)
        ``[theta, pseudo-inputs.ravel()]`` with ``theta = [log ell, log sf, log sn]``.
    x: (n, d)
    y: (n,)
    m
        Number of pseudo-inputs.
    """
    n, d = x.shape
    theta, z = params[: d + 2], params[d + 2 :].reshape(m, d)
    q = _pieces(theta, z, x)
    lm, lb, v, vl, lam = q["lm"], q["lb"], q["v"], q["vl"], q["lam"]
    bc = chol_solve(lb, vl @ y)
    b = y / lam - vl.T @ bc  # C^-1 y
    nll = np.sum(np.log(np.diag(lb))) + 0.5 * np.sum(np.log(lam)) + 0.5 * y @ b
    nll += 0.5 * n * math.log(2 * math.pi)
    # Gradient via dnll = sum(Gmn * dKmn) + sum(Gmm * dKmm) + 1/2 sum(g * dLambda_direct).
    lbv = _lower_solve(lb, vl)
    g = (1.0 / lam - np.sum(lbv * lbv, axis=0)) - b * b  # diag(C^-1) - b^2
    u = sla.solve_triangular(lm, v, lower=True, trans="T", check_finite=False)  # Kmm^-1 Kmn
    r = sla.solve_triangular(lm, chol_solve(lb, vl), lower=True, trans="T", check_finite=False)
    ub = u @ b
    lmi = _lower_solve(lm, np.eye(m))
    binv = chol_solve(lb, np.eye(m))
    kmm_minus_a = lmi.T @ (np.eye(m) - binv) @ lmi  # Kmm^-1 - A^-1
    gam_mn = r - u * g[None, :] - np.outer(ub, b)
    gam_mm = 0.5 * ((u * g[None, :]) @ u.T - kmm_minus_a + np.outer(ub, ub))
    kmm_tot = q["kmm"] + q["jitter"] * np.eye(m)
    gmn, gmm = gam_mn * q["kmn"], gam_mm * kmm_tot
    zs, xs, ell = q["zs"], q["xs"], q["ell"]
    rs_mn, cs_mn, rs_mm = gmn.sum(axis=1), gmn.sum(axis=0), gmm.sum(axis=1)
    gmn_x, gmm_z = gmn @ xs, gmm @ zs
    d_ell = (
        (zs * zs).T @ rs_mn + (xs * xs).T @ cs_mn - 2.0 * np.sum(zs * gmn_x, axis=0)
        + 2.0 * (zs * zs).T @ rs_mm - 2.0 * np.sum(zs * gmm_z, axis=0)
    )  # fmt: skip
    d_sf = 2.0 * gmn.sum() + 2.0 * gmm.sum() + q["sf2"] * g.sum()
    d_sn = q["sn2"] * g.sum()
    d_z = -((zs * rs_mn[:, None] - gmn_x) + 2.0 * (zs * rs_mm[:, None] - gmm_z)) / ell
    return float(nll), np.concatenate([d_ell, [d_sf, d_sn], d_z.ravel()])


@dataclass(frozen=True, eq=False)
class SparseGP:
    """A fitted multi-output FITC GP (one set of pseudo-inputs per output).

    Attributes
    ----------
    theta: (P, d + 2)
    pseudo_inputs: (P, m, d)
        Standardised pseudo-input locations.
    beta: (P, m)
        ``A^-1 K_mn Lambda^-1 y`` (mean weights, ``A = K_mm + K_mn Lambda^-1 K_nm``).
    chol_mm_t, chol_b_t: (P, m, m)
        Transposed lower Cholesky factors of ``K_mm`` and of ``B = L_m^-1 A L_m^-T``.
    inverse: bool
        Predictive means and variances from one stacked product with :meth:`projection`
        (built once from the explicit inverse factors of both, on the first variance
        request, when every output's factors are well conditioned; see
        :func:`~estimator_service.gp.linalg.inverse_factor`) instead of two triangular
        solves per output; ``tests/test_gp.py`` bounds the difference on a near-noiseless
        GP.
    """

    __repr__ = short_repr

    x_scaler: Scaler
    y_scaler: Scaler
    theta: FloatArray
    pseudo_inputs: FloatArray
    beta: FloatArray
    chol_mm_t: FloatArray
    chol_b_t: FloatArray
    kind: str = "sparse"
    inverse: bool = True

    def __post_init__(self) -> None:
        for arr in (self.theta, self.pseudo_inputs, self.beta, self.chol_mm_t, self.chol_b_t):
            arr.flags.writeable = False
        _ = self._kernel  # built with the posterior; the inverse factors on the first variance request

    @functools.cached_property
    def _kernel(self) -> CrossKernel:
        return CrossKernel.build(self.pseudo_inputs, self.theta, self.beta)

    def inverse_factors(self) -> tuple[FloatArray, FloatArray] | None:
        """``L_m^-1`` and ``L_B^-1``, each ``(P, m, m)``, or None where the solves are kept
        (some output's factor is too ill-conditioned for the product to match them)."""
        return self._inverse_factors

    @functools.cached_property
    def _inverse_factors(self) -> tuple[FloatArray, FloatArray] | None:
        lm = [inverse_factor(t.T) for t in self.chol_mm_t]
        lb = [inverse_factor(t.T) for t in self.chol_b_t]
        if not all(f is not None for f in lm + lb):
            return None
        both = (np.stack(lm), np.stack(lb))
        for f in both:
            f.flags.writeable = False
        return both

    @classmethod
    def from_params(
        cls,
        x: FloatArray,
        y: FloatArray,
        theta: FloatArray,
        z: FloatArray,
        xsc: Scaler,
        ysc: Scaler,
    ) -> SparseGP:
        """Posterior for standardised ``x (n, d)``, ``y (n, P)``, ``theta``, ``z (P, m, d)``."""
        p_out, m = z.shape[0], z.shape[1]
        beta, lmt, lbt = np.empty((p_out, m)), np.empty((p_out, m, m)), np.empty((p_out, m, m))
        for p in range(p_out):  # training-time only
            q = _pieces(theta[p], z[p], x)
            bc = chol_solve(q["lb"], q["vl"] @ y[:, p])
            beta[p] = sla.solve_triangular(q["lm"], bc, lower=True, trans="T", check_finite=False)
            lmt[p], lbt[p] = q["lm"].T, q["lb"].T
        return cls(
            xsc,
            ysc,
            np.asarray(theta, dtype=np.float64),
            np.asarray(z, dtype=np.float64),
            beta,
            lmt,
            lbt,
        )

    def conditioned(self, x: FloatArray, y: FloatArray) -> SparseGP:
        """The same hyperparameters, pseudo-inputs and scalers, conditioned on other data
        ``x (n, d)``, ``y (n, P)`` (original units)."""
        xa, ya = check_conditioning_data(x, y, self.input_dim, self.output_dim)
        xs, ys = self.x_scaler.apply(xa), self.y_scaler.apply(ya)
        return SparseGP.from_params(xs, ys, self.theta, self.pseudo_inputs, self.x_scaler, self.y_scaler)

    @property
    def input_dim(self) -> int:
        return self.pseudo_inputs.shape[2]

    @property
    def output_dim(self) -> int:
        return self.theta.shape[0]

    def projection(self) -> FloatArray | None:
        """``W (P, m, m + 1)``: ``ks @ W`` gives, per output, ``G k`` (first ``m`` columns,
        latent variance ``sf^2 - |G k|^2``) and the mean ``beta^T k`` (last column); None
        where the solves are kept (:meth:`inverse_factors`).

        FITC's variance ``sf^2 - |L_m^-1 k|^2 + |L_B^-1 L_m^-1 k|^2`` is
        ``sf^2 - k^T L_m^-T (I - B^-1) L_m^-1 k``; with ``I - B^-1 = U diag(mu) U^T``
        (``mu`` in [0, 1), from ``B^-1 = L_B^-T L_B^-1``, whose entries are accurate to
        rounding because ``|L_B^-1| <= 1``), ``G = diag(sqrt(mu)) U^T L_m^-1``: one ``m x m``
        product per query instead of two, and the mean in the same product.
        """
        return self._projection

    @functools.cached_property
    def _projection(self) -> FloatArray | None:
        inv = self.inverse_factors()
        if inv is None:
            return None
        lmi, lbi = inv
        b_inv = lbi.transpose(0, 2, 1) @ lbi
        mu, u = np.linalg.eigh(np.eye(b_inv.shape[-1]) - b_inv)
        g = np.sqrt(np.clip(mu, 0.0, 1.0))[:, :, None] * (u.transpose(0, 2, 1) @ lmi)
        proj = np.ascontiguousarray(np.concatenate([g.transpose(0, 2, 1), self.beta[:, :, None]], axis=2))
        proj.flags.writeable = False
        return proj

    def latent(
        self, xs: FloatArray, return_var: bool, return_jac: bool
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        """Standardised latent mean ``(M, P)``, variance ``(M, P)``, Jacobian ``(M, P, d)``."""
        proj = self.projection() if return_var and self.inverse else None
        if proj is not None and not return_jac and xs.shape[0] > BY_OUTPUT_MIN_QUERIES:
            return (*self._batch_latent(xs, proj), None)
        if proj is not None:  # every output at once: (P, M, m) @ (P, m, m + 1)
            ks = self._kernel.block(xs)
            out = ks @ proj
            mean = out[:, :, -1].T
            g = out[:, :, :-1]
            var = np.exp(2.0 * self.theta[:, -2]) - np.einsum("pqm,pqm->qp", g, g)
            jac = self._kernel.jacobian(ks, xs, mean) if return_jac else None
            return mean, np.maximum(var, 0.0, out=var), jac
        if not return_var:
            return self._latent(xs, False, return_jac)
        with single_threaded_blas():  # m x m solves: a second BLAS thread only contends
            return self._latent(xs, True, return_jac)

    def _batch_latent(self, xs: FloatArray, proj: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Mean and variance ``(M, P)`` of a batch, output by output over threads
        (:func:`~estimator_service.gp.parallel.over_outputs`)."""
        p_out = self.output_dim
        mean, var = np.empty((xs.shape[0], p_out)), np.empty((xs.shape[0], p_out))
        sf2 = np.exp(2.0 * self.theta[:, -2])

        def one(p: int) -> None:
            out = self._kernel.block_one(xs, p) @ proj[p]
            mean[:, p] = out[:, -1]
            g = out[:, :-1]
            var[:, p] = sf2[p] - np.einsum("qm,qm->q", g, g)

        over_outputs(one, p_out)
        return mean, np.maximum(var, 0.0, out=var)

    def _latent(
        self, xs: FloatArray, return_var: bool, return_jac: bool
    ) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
        ks, mean, jac = self._kernel(xs, return_jac)
        var = None
        if return_var:
            sf2 = np.exp(2.0 * self.theta[:, -2])
            var = np.empty_like(mean)
            for p in range(self.output_dim):  # one BLAS-3 solve pair per output, all queries
                w = tri_solve(self.chol_mm_t[p].T, ks[p].T, overwrite_b=True)
                wb = tri_solve(self.chol_b_t[p].T, w)
                var[:, p] = sf2[p] - np.einsum("mq,mq->q", w, w) + np.einsum("mq,mq->q", wb, wb)
            np.maximum(var, 0.0, out=var)
        return mean, var, jac

    def predict(
        self, x: FloatArray, *, return_var: bool = True, return_jac: bool = False,
        include_noise: bool = True,
    ) -> GPPrediction:  # fmt: skip
        """Batched prediction for queries ``x (M, d)``; see :class:`GPPrediction`."""
        xs = self.x_scaler.apply(check_query(x, self.input_dim))
        mean, var, jac = self.latent(xs, return_var, return_jac)
        if var is not None and include_noise:
            var = var + np.exp(2.0 * self.theta[:, -1])
        return unscale(self.x_scaler, self.y_scaler, mean, var, jac)


def fit_sparse(
    x: FloatArray,
    y: FloatArray,
    *,
    n_pseudo: int = 50,
    restarts: int = 1,
    max_iter: int = 300,
    rng: np.random.Generator | None = None,
    callback: ProgressCallback | None = None,
) -> SparseGP:
    """Learn pseudo-inputs and hyperparameters per output column (paper: m = 50).

    Pseudo-inputs start at a random subset of the training inputs (``rng``).
    """
    xa, ya = check_training_data(x, y, min_points=max(3, n_pseudo))
    rng = np.random.default_rng(0) if rng is None else rng
    xsc, ysc = Scaler.fit(xa), Scaler.fit(ya)
    xs, ys = xsc.apply(xa), ysc.apply(ya)
    n, d = xs.shape
    bounds = theta_bounds(d) + [(None, None)] * (n_pseudo * d)
    thetas, zs = [], []
    for p in range(ys.shape[1]):  # one BLAS thread: docs/measurements.md#one-blas-thread
        starts = [
            np.concatenate([t, xs[rng.choice(n, n_pseudo, replace=False)].ravel()])
            for t in initial_thetas(xs, max(1, restarts), rng)
        ]
        with single_threaded_blas():
            best = optimize_theta(
                lambda prm, p=p: sparse_nll(prm, xs, ys[:, p], n_pseudo),
                starts, bounds, max_iter, "sparse", p, callback,
            )  # fmt: skip
        thetas.append(best[: d + 2])
        zs.append(best[d + 2 :].reshape(n_pseudo, d))
    return SparseGP.from_params(xs, ys, np.stack(thetas), np.stack(zs), xsc, ysc)
