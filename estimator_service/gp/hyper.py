"""Hyperparameter learning shared by the GP kinds: the exact GP's negative log marginal
likelihood and its gradient (paper eq. 5-10), starting points, bounds and L-BFGS-B runs."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize

from estimator_service.gp.base import Progress, ProgressCallback, report
from estimator_service.gp.kernel import split_theta, sq_dist
from estimator_service.gp.linalg import chol_inverse, chol_solve, robust_cholesky, single_threaded_blas

__all__ = [
    "exact_nll",
    "initial_thetas",
    "learn_thetas",
    "optimize_theta",
    "random_subset",
    "theta_bounds",
]

FloatArray = NDArray[np.float64]


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

    The first uses per-dimension median pairwise distances (of up to 2,000 random pairs)
    times ``sqrt(d)`` and noise std 0.3; the next two scale the length scales by 0.3 and 3,
    with noise std 0.1 and 0.5; later ones draw log length scales from ``N(first, 1)`` and
    the noise std log-uniformly from 0.03 to 0.5. The signal std starts at 1.
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
    with single_threaded_blas():  # docs/measurements.md#one-blas-thread
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
