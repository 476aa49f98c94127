"""Exact GP regression: learning (paper eq. 5-10) and batched prediction (eq. 1-3, 20-22)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from estimator_service.gp.base import (
    GPPrediction,
    Progress,
    ProgressCallback,
    Scaler,
    check_query,
    check_training_data,
    report,
)
from estimator_service.gp.kernel import CrossKernel, se_kernel, split_theta, sq_dist
from estimator_service.gp.linalg import (
    chol_inverse,
    chol_solve,
    robust_cholesky,
    single_threaded_blas,
    tri_solve,
)

__all__ = ["ExactGP", "exact_nll", "fit_exact", "initial_thetas", "learn_thetas", "optimize_theta"]

FloatArray = NDArray[np.float64]
_CHUNK_BYTES = 256 * 2**20  # cap on the (P, M, n) kernel block held at once


def exact_nll(
    theta: FloatArray, x: FloatArray, y: FloatArray, noise_profile: FloatArray | None = None
) -> tuple[float, FloatArray]:
    """Negative log marginal likelihood of one output and its gradient (eq. 5-10).

    Parameters
    ----------
    theta: (d + 2,)
        ``[log ell_1..d, log sf, log sn]``.
    x: (n, d)
    y: (n,)
    noise_profile: (n,), optional
        Relative noise per point; the noise covariance is ``sn^2 diag(profile)`` (the
        heteroscedastic GP), ``sn^2 I`` when omitted.

    Returns
    -------
    nll, grad: float, (d + 2,)
    """
    ell, sf2, sn2 = split_theta(theta)
    xs = x / ell
    kf = sf2 * np.exp(-0.5 * sq_dist(xs, xs))
    noise = sn2 * (np.ones(len(y)) if noise_profile is None else noise_profile)
    k = kf.copy()
    k[np.diag_indices_from(k)] += noise
    l, _ = robust_cholesky(k)
    alpha = chol_solve(l, y)
    nll = 0.5 * y @ alpha + np.sum(np.log(np.diag(l))) + 0.5 * len(y) * math.log(2 * math.pi)
    w = np.outer(alpha, alpha) - chol_inverse(l)  # dnll = -1/2 tr(W dK)
    a = w * kf
    rs = a.sum(axis=1)
    sum_d = 2.0 * (xs * xs).T @ rs - 2.0 * np.sum(xs * (a @ xs), axis=0)
    grad = np.concatenate([-0.5 * sum_d, [-np.sum(a), -np.sum(np.diag(w) * noise)]])
    return float(nll), grad


def initial_thetas(x: FloatArray, restarts: int, rng: np.random.Generator) -> list[FloatArray]:
    """Data-driven starting points for standardised data (unit signal variance).

    The first uses per-dimension median pairwise distances times ``sqrt(d)`` and noise
    ``0.1``; the next two scale the length scales by 0.3 and 3; later ones are random
    around the first.
    """
    n, d = x.shape
    idx = rng.integers(0, n, size=(min(2000, n * n), 2))
    med = np.median(np.abs(x[idx[:, 0]] - x[idx[:, 1]]), axis=0)
    base = np.log(np.maximum(med, 1e-3) * math.sqrt(d))
    starts = []
    for r in range(restarts):
        if r < 3:
            log_ell = base + math.log((1.0, 0.3, 3.0)[r])
            log_sn = math.log((0.3, 0.1, 0.5)[r])
        else:
            log_ell = base + rng.normal(0.0, 1.0, size=d)
            log_sn = rng.uniform(math.log(0.03), math.log(0.5))
        starts.append(np.concatenate([log_ell, [0.0, log_sn]]))
    return starts


def theta_bounds(d: int) -> list[tuple[float, float]]:
    """L-BFGS-B box: length scales 1e-2..1e3, signal std 1e-2..1e2, noise std 1e-3..10."""
    return [(math.log(1e-2), math.log(1e3))] * d + [
        (math.log(1e-2), math.log(1e2)),
        (math.log(1e-3), math.log(10.0)),
    ]


def optimize_theta(
    objective, starts: list[FloatArray], bounds, max_iter: int, name: str, output: int,
    callback: ProgressCallback | None,
) -> FloatArray:  # fmt: skip
    """Minimise ``objective(theta) -> (f, grad)`` with L-BFGS-B from each start; best wins."""
    best_f, best_theta = math.inf, starts[0]
    for r, theta0 in enumerate(starts):
        last = {"f": math.nan, "it": 0}

        def fun(t: FloatArray, last: dict = last) -> tuple[float, FloatArray]:
            try:
                f, g = objective(t)
            except np.linalg.LinAlgError:
                return 1e25, np.zeros_like(t)
            last["f"] = f
            return f, g

        def step(_: FloatArray, last: dict = last, r: int = r) -> None:
            last["it"] += 1
            report(callback, Progress(name, output, r, last["it"], last["f"]))

        res = minimize(
            fun, theta0, jac=True, method="L-BFGS-B", bounds=bounds, callback=step,
            options={"maxiter": max_iter},
        )  # fmt: skip
        if np.isfinite(res.fun) and res.fun < best_f:
            best_f, best_theta = float(res.fun), res.x
    return np.asarray(best_theta)


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
    """

    x_scaler: Scaler
    y_scaler: Scaler
    theta: FloatArray
    x_train: FloatArray
    chol_t: FloatArray
    alpha: FloatArray
    noise_profile: FloatArray | None = None
    kind: str = "exact"

    _kernel: CrossKernel = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for arr in (self.theta, self.x_train, self.chol_t, self.alpha):
            arr.flags.writeable = False
        object.__setattr__(self, "_kernel", CrossKernel.build(self.x_train, self.theta, self.alpha))

    @classmethod
    def from_theta(
        cls, x: FloatArray, y: FloatArray, theta: FloatArray, x_scaler: Scaler, y_scaler: Scaler,
        noise_profile: FloatArray | None = None,
    ) -> ExactGP:  # fmt: skip
        """Posterior for standardised data ``x (n, d)``, ``y (n, P)`` and ``theta (P, d+2)``."""
        n, p_out = y.shape
        chol_t = np.empty((p_out, n, n))
        alpha = np.empty((p_out, n))
        prof = np.ones((p_out, n)) if noise_profile is None else noise_profile
        for p in range(p_out):  # training-time only
            ell, sf2, sn2 = split_theta(theta[p])
            k = se_kernel(x, x, ell, sf2)
            k[np.diag_indices_from(k)] += sn2 * prof[p]
            l, _ = robust_cholesky(k)
            chol_t[p] = l.T
            alpha[p] = chol_solve(l, y[:, p])
        return cls(x_scaler, y_scaler, np.asarray(theta, dtype=np.float64), x, chol_t, alpha, noise_profile)

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
        ks, mean, jac = self._kernel(xs, return_jac)
        sf2 = np.exp(2.0 * self.theta[:, -2])
        var = None
        if return_var:
            var = np.empty_like(mean)
            for p in range(p_out):  # one BLAS-3 triangular solve per output, all queries at once
                v = tri_solve(self.chol_t[p].T, ks[p].T, overwrite_b=True)
                var[:, p] = sf2[p] - np.einsum("nm,nm->m", v, v)
            np.maximum(var, 0.0, out=var)
        return mean, var, jac

    def noise_std_units(self, xs: FloatArray) -> FloatArray:
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
            var = var + self.noise_std_units(xs)
        return unscale(self.x_scaler, self.y_scaler, mean, var, jac)


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


def random_subset(n: int, k: int | None, rng: np.random.Generator) -> NDArray[np.intp] | None:
    """Sorted ``k`` of ``range(n)`` without replacement, or None when ``k`` is None or >= ``n``."""
    if k is None or k >= n:
        return None
    return np.sort(rng.choice(n, size=max(3, k), replace=False))


def learn_thetas(
    xs: FloatArray, ys: FloatArray, starts: list[list[FloatArray]], *, max_iter: int, name: str,
    callback: ProgressCallback | None, profile: FloatArray | None = None,
    subset: NDArray[np.intp] | None = None, polish_iter: int = 0,
) -> FloatArray:  # fmt: skip
    """Log hyperparameters ``(P, d + 2)`` of standardised data ``xs (n, d)``, ``ys (n, P)``.

    Output ``p`` starts from each of ``starts[p]``; with ``subset`` the runs use those
    rows and ``polish_iter`` more iterations then use all rows. ``profile (P, n)`` is the
    relative per-point noise of a heteroscedastic GP.
    """
    bounds = theta_bounds(xs.shape[1])
    out = []
    with single_threaded_blas():  # bench_training: 53.8 -> 42.6 ms per n = 900 evaluation
        for p in range(ys.shape[1]):
            prof = None if profile is None else profile[p]
            args = (bounds, max_iter, name, p, callback, prof, subset, polish_iter)
            out.append(_learn_one(xs, ys[:, p], starts[p], *args))
    return np.stack(out)


def _learn_one(
    xs: FloatArray, y: FloatArray, starts: list[FloatArray], bounds, max_iter: int, name: str,
    p: int, callback: ProgressCallback | None, profile: FloatArray | None,
    subset: NDArray[np.intp] | None, polish_iter: int,
) -> FloatArray:  # fmt: skip
    """One output ``y (n,)`` of :func:`learn_thetas`."""

    def objective(t: FloatArray, rows: slice | NDArray[np.intp] = slice(None)) -> tuple[float, FloatArray]:
        return exact_nll(t, xs[rows], y[rows], None if profile is None else profile[rows])

    rows = slice(None) if subset is None else subset
    theta = optimize_theta(lambda t: objective(t, rows), starts, bounds, max_iter, name, p, callback)
    if subset is not None and polish_iter > 0:
        theta = optimize_theta(objective, [theta], bounds, polish_iter, name, p, callback)
    return theta
