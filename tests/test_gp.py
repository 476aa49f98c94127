"""GP regression: gradients, limits, learning, sparse/hetero/enhanced, persistence, errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from estimator_service.gp import (
    ExactGP,
    ModelFileError,
    Scaler,
    SparseGP,
    exact_nll,
    fit_enhanced,
    fit_exact,
    fit_hetero,
    fit_sparse,
    load_gp,
    save_gp,
    sparse_nll,
)
from estimator_service.gp.kernel import se_kernel
from tests.hostile_files import load_refused


def central_diff(f, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    g = np.zeros_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        g[i] = (f(x + e) - f(x - e)) / (2 * h)
    return g


def identity_scalers(d: int, p: int) -> tuple[Scaler, Scaler]:
    return Scaler(np.zeros(d), np.ones(d)), Scaler(np.zeros(p), np.ones(p))


@pytest.fixture(scope="module")
def toy() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    x = rng.uniform(-3, 3, (80, 2))
    y = np.stack([np.sin(x[:, 0]) + 0.3 * x[:, 1], np.cos(x[:, 1]) * x[:, 0]], axis=1)
    return x, y + 0.05 * rng.normal(size=y.shape)


@pytest.fixture(scope="module")
def models(toy) -> dict[str, object]:
    x, y = toy
    rng = np.random.default_rng(1)
    return {
        "exact": fit_exact(x, y, restarts=2, max_iter=80, rng=rng),
        "sparse": fit_sparse(x, y, n_pseudo=15, max_iter=80, rng=rng),
        "hetero": fit_hetero(x, y, iterations=1, restarts=1, max_iter=50, rng=rng),
        "enhanced": fit_enhanced(x, y, lambda q: 0.3 * q[:, ::-1], fit_exact, restarts=1, max_iter=50),
    }


# -- objectives: analytic gradients vs finite differences -------------------------------
@pytest.mark.parametrize("hetero", [False, True])
def test_exact_and_heteroscedastic_nll_gradients(toy, hetero: bool) -> None:
    x, y = toy
    rng = np.random.default_rng(2)
    profile = rng.uniform(0.3, 3.0, len(x)) if hetero else None
    theta = np.array([0.2, -0.4, 0.3, math.log(0.2)])
    _, grad = exact_nll(theta, x, y[:, 0], profile)
    fd = central_diff(lambda t: exact_nll(t, x, y[:, 0], profile)[0], theta)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6)


def test_sparse_nll_gradient_including_pseudo_inputs(toy) -> None:
    x, y = toy
    rng = np.random.default_rng(3)
    m = 6
    params = np.concatenate([[0.1, 0.4, 0.2, math.log(0.3)], rng.uniform(-2, 2, m * 2)])
    _, grad = sparse_nll(params, x, y[:, 1], m)
    fd = central_diff(lambda p: sparse_nll(p, x, y[:, 1], m)[0], params)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6)


def test_sparse_nll_gradient_counts_the_jitter_of_an_ill_conditioned_kmm(toy, monkeypatch) -> None:
    """The jitter :func:`robust_cholesky` adds to an ill-conditioned ``K_mm`` (clustered
    pseudo-inputs) is part of the objective: the gradient counts it. Forced here to 1e-3 of
    the signal variance, so that its effect is far above the finite differences' error."""
    import estimator_service.gp.sparse as sparse_module

    real = sparse_module.robust_cholesky

    def jittered(k: np.ndarray, max_tries: int = 8) -> tuple[np.ndarray, float]:
        diag = np.diag(k)
        if not np.allclose(diag, diag[0], rtol=1e-9, atol=0.0):  # B, not K_mm (diagonal sf^2)
            return real(k, max_tries)
        return np.linalg.cholesky(k + 1e-3 * diag[0] * np.eye(len(k))), 1e-3 * diag[0]

    monkeypatch.setattr(sparse_module, "robust_cholesky", jittered)
    x, y = toy
    m = 6
    params = np.concatenate([[0.1, 0.4, 0.2, math.log(0.3)], np.random.default_rng(0).uniform(-2, 2, m * 2)])
    _, grad = sparse_nll(params, x, y[:, 0], m)
    fd = central_diff(lambda p: sparse_nll(p, x, y[:, 0], m)[0], params)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("queries", [3, 41])  # all outputs at once, and output by output (> 32)
@pytest.mark.parametrize("kind", ["exact", "sparse", "hetero", "enhanced"])
def test_mean_jacobian_matches_finite_differences(models, kind: str, queries: int) -> None:
    gp = models[kind]
    x0 = np.array([[0.3, -1.1], [2.0, 0.5], [-2.5, 2.5]])
    if queries > 3:
        x0 = np.concatenate([x0, np.random.default_rng(5).uniform(-2.5, 2.5, (queries - 3, 2))])
    jac = gp.predict(x0, return_jac=True).jac
    assert jac.shape == (queries, 2, 2)
    h = 1e-5
    fd = np.stack(
        [(gp.predict(x0 + h * e).mean - gp.predict(x0 - h * e).mean) / (2 * h) for e in np.eye(2)],
        axis=-1,
    )
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-6)
    assert gp.predict(x0).jac is None  # a Jacobian only when asked for, on either path
    assert gp.predict(x0, return_var=False).var is None  # and a variance too
    np.testing.assert_allclose(
        gp.predict(x0, return_var=False, return_jac=True).jac, jac, rtol=1e-10, atol=1e-12
    )


def test_an_exact_gp_with_a_noise_profile_is_the_closed_form_posterior() -> None:
    """``ExactGP.from_theta`` with per-point noise ``sn2 r_i`` (the heteroscedastic GP's main
    GP): its weights are ``(K + sn2 diag(r))^-1 y`` by a dense solve, per output with its own
    hyperparameters; it keeps the profile (a saved model records it) and its posterior
    arrays are read-only (a frozen posterior)."""
    rng = np.random.default_rng(4)
    x = rng.normal(size=(30, 2))
    y = np.stack([np.sin(x[:, 0]), x[:, 1] ** 2 - 1.0], axis=1)
    theta = np.array([[0.1, -0.2, 0.3, -1.0], [-0.3, 0.4, 0.1, -0.5]])
    prof = rng.uniform(0.2, 5.0, size=(2, 30))
    one = Scaler(np.zeros(2), np.ones(2))
    gp = ExactGP.from_theta(x, y, theta, one, one, noise_profile=prof)
    for p in range(2):
        ell, sf2, sn2 = np.exp(theta[p, :2]), np.exp(2 * theta[p, 2]), np.exp(2 * theta[p, 3])
        k = se_kernel(x, x, ell, sf2) + np.diag(sn2 * prof[p])
        np.testing.assert_allclose(gp.alpha[p], np.linalg.solve(k, y[:, p]), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(gp.noise_profile, prof)
    for arr in (gp.theta, gp.x_train, gp.chol_t, gp.alpha):
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 0.0


def test_a_large_batch_is_predicted_in_chunks_with_the_same_results(models, monkeypatch) -> None:
    """Queries beyond the kernel block's byte cap go in row chunks of ``cap // (8 P n)``: the
    recursion sees exactly those chunks, and the results equal the one-block prediction."""
    import estimator_service.gp.exact as exact

    gp = models["exact"]
    x = np.random.default_rng(6).uniform(-3, 3, (35, 2))
    whole = gp.predict(x, return_jac=True)
    p_out, n = gp.alpha.shape
    monkeypatch.setattr(exact, "_CHUNK_BYTES", 10 * 8 * p_out * n)  # 10 queries a chunk
    sizes: list[int] = []
    latent = ExactGP.latent

    def spy(self, xs, return_var, return_jac):
        sizes.append(len(xs))
        return latent(self, xs, return_var, return_jac)

    monkeypatch.setattr(ExactGP, "latent", spy)
    parts = gp.predict(x, return_jac=True)
    assert sizes == [35, 10, 10, 10, 5]
    for a, b in zip((parts.mean, parts.var, parts.jac), (whole.mean, whole.var, whole.jac), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)  # the stacked and by-output paths


# -- GP limits ----------------------------------------------------------------------------
def test_far_from_data_prediction_reverts_to_prior(models, toy) -> None:
    gp = models["exact"]
    _, y = toy
    pred = gp.predict(np.array([[400.0, -300.0]]))
    sf2 = np.exp(2 * gp.theta[:, -2]) * gp.y_scaler.std**2
    np.testing.assert_allclose(pred.mean[0], y.mean(axis=0), rtol=1e-9)
    np.testing.assert_allclose(pred.var[0], sf2 + gp.noise_var, rtol=1e-9)


def test_interpolates_with_tiny_noise() -> None:
    rng = np.random.default_rng(4)
    x = rng.uniform(-2, 2, (30, 1))
    y = np.sin(2 * x)
    xs, ys = identity_scalers(1, 1)
    gp = ExactGP.from_theta(x, y, np.array([[math.log(0.7), 0.0, math.log(1e-5)]]), xs, ys)
    pred = gp.predict(x, include_noise=False)
    np.testing.assert_allclose(pred.mean, y, atol=1e-6)
    assert np.all(pred.var < 1e-6)


def test_variance_grows_in_a_gap_of_the_data() -> None:
    """Paper Fig. 1: uncertainty is larger where training data is missing."""
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.uniform(-4, -1, 40), rng.uniform(1, 4, 40)])[:, None]
    gp = fit_exact(x, np.sin(x[:, 0]) + 0.05 * rng.normal(size=80), restarts=2, rng=rng)
    query = np.array([[-2.5], [-1.5], [-0.5], [0.0], [2.5]])
    var = gp.predict(query, include_noise=False).var[:, 0]
    assert var[3] > var[2] > var[1]
    assert var[3] > 5 * var[0] and var[3] > 5 * var[4]


ELL, SN = np.array([0.6, 2.5]), 0.1


def gp_sample(rng: np.random.Generator, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """``n`` noisy draws from a GP with length scales ``ELL`` and noise ``SN`` on [-3, 3]^2."""
    x = rng.uniform(-3, 3, (n, 2))
    k = se_kernel(x, x, ELL, 1.0) + 1e-8 * np.eye(n)
    return x, np.linalg.cholesky(k) @ rng.normal(size=n) + SN * rng.normal(size=n)


def test_learning_recovers_length_scales_and_noise() -> None:
    rng = np.random.default_rng(6)
    x, y = gp_sample(rng)
    ell, sn = ELL, SN
    gp = fit_exact(x, y, restarts=3, rng=rng)
    learned_ell = np.exp(gp.theta[0, :2]) * gp.x_scaler.std
    learned_sn = math.sqrt(gp.noise_var[0])
    np.testing.assert_allclose(learned_ell, ell, rtol=0.3)
    assert learned_sn == pytest.approx(sn, rel=0.2)


def test_subset_hyperparameters_with_polish_match_the_full_optimum() -> None:
    """Learning on 150 of 400 points then polishing on all lands near the all-points optimum."""
    x, y = gp_sample(np.random.default_rng(6))
    full = fit_exact(x, y, restarts=2, rng=np.random.default_rng(0))
    sub = fit_exact(x, y, restarts=2, rng=np.random.default_rng(0), hyper_points=150, polish_iter=30)
    ys = (y - full.y_scaler.mean) / full.y_scaler.std
    xs = full.x_scaler.apply(x)
    nll_full = exact_nll(full.theta[0], xs, ys[:, 0] if ys.ndim == 2 else ys)[0]
    nll_sub = exact_nll(sub.theta[0], xs, ys[:, 0] if ys.ndim == 2 else ys)[0]
    assert nll_sub == pytest.approx(nll_full, abs=0.5)
    assert sub.x_train.shape == (400, 2)  # the posterior uses every point


def test_cholesky_inverse_matches_solve() -> None:
    from estimator_service.gp.linalg import chol_inverse

    rng = np.random.default_rng(2)
    a = rng.normal(size=(30, 30))
    k = a @ a.T + 30 * np.eye(30)
    inv = chol_inverse(np.linalg.cholesky(k))
    np.testing.assert_allclose(inv, np.linalg.solve(k, np.eye(30)), rtol=1e-10, atol=1e-13)
    np.testing.assert_array_equal(inv, inv.T)


def _same_up_to_rounding(fast, slow, q: np.ndarray, mean_rtol: float = 0.0) -> None:
    """Variances of the inverse-factor GP ``fast`` within rounding of the solving ``slow``
    at queries ``q``, none negative, means identical (or within ``mean_rtol`` relative and
    absolute: targets of order one)."""
    v_fast = fast.predict(q, include_noise=False).var
    v_slow = slow.predict(q, include_noise=False).var
    assert np.all(v_fast >= 0) and np.all(v_slow >= 0)
    np.testing.assert_allclose(v_fast, v_slow, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(fast.predict(q).mean, slow.predict(q).mean, rtol=mean_rtol, atol=mean_rtol)


@pytest.mark.parametrize("columns", [1, 2, 5])
def test_tri_solve_matches_the_solve_and_overwrites_a_fortran_right_hand_side(columns: int) -> None:
    """``tri_solve`` for one right-hand side (BLAS ``trsv``), two and more (LAPACK): the
    solution of ``L X = B``, and with ``overwrite_b`` a Fortran-ordered ``B`` is solved in
    place (no copy of the skinny kernel block)."""
    from estimator_service.gp.linalg import tri_solve

    rng = np.random.default_rng(columns)
    lower = np.asfortranarray(np.tril(rng.normal(size=(7, 7))) + 7.0 * np.eye(7))
    b = np.asfortranarray(rng.normal(size=(7, columns)))
    want = np.linalg.solve(lower, b)
    np.testing.assert_allclose(tri_solve(lower, b.copy(order="F")), want, rtol=1e-12, atol=1e-14)
    inplace = b.copy(order="F")
    got = tri_solve(lower, inplace, overwrite_b=True)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
    assert got.shape == (7, columns) and np.shares_memory(got, inplace)
    kept = b.copy(order="F")
    tri_solve(lower, kept)
    np.testing.assert_array_equal(kept, b)  # without overwrite_b the right-hand side is left as it was


@pytest.mark.parametrize("queries", [1, 7, 200])  # 200: the batch path's row blocks
def test_inverse_factor_variance_matches_the_solve_on_a_near_noiseless_gp(queries: int) -> None:
    """The explicit ``L^-1`` path against the triangular solve, where it is hardest: noise
    4e-7 of the signal (as the blimp's near-deterministic outputs), 600 points in 3-D, queries
    at and between training points. Its error must stay within rounding of the solve's."""
    rng = np.random.default_rng(11)
    x = rng.uniform(-2, 2, (600, 3))
    y = np.sin(x @ np.array([1.0, -0.7, 0.4]))[:, None]
    xs, ys = identity_scalers(3, 1)
    theta = np.array([[math.log(0.9), math.log(1.2), math.log(1.5), 0.0, 0.5 * math.log(4e-7)]])
    fast = ExactGP.from_theta(x, y, theta, xs, ys)
    slow = ExactGP(fast.x_scaler, fast.y_scaler, fast.theta, fast.x_train, fast.chol_t, fast.alpha,
                   inverse=False)  # fmt: skip
    assert fast.inverse_blocks().has_factor[0]  # well enough conditioned to be used
    q = np.concatenate([x[: queries // 2], rng.uniform(-2, 2, (queries - queries // 2, 3))])
    _same_up_to_rounding(fast, slow, q)


@pytest.mark.parametrize("queries", [1, 7, 200])  # one query, all outputs at once, by output
def test_outputs_with_and_without_an_inverse_factor_match_the_solve(queries: int, monkeypatch) -> None:
    """A GP whose middle output has no inverse factor (refused, as an ill-conditioned one is):
    that output solves, the others use the factor's blocks, and every path's variances equal
    the solve's."""
    import estimator_service.gp.exact as exact

    refused = iter([False, True, False])
    real = exact.inverse_factor
    monkeypatch.setattr(exact, "inverse_factor", lambda l: None if next(refused) else real(l))
    rng = np.random.default_rng(12)
    x = rng.uniform(-2, 2, (300, 3))
    y = np.stack([np.sin(x[:, 0]), np.cos(x[:, 1]), x[:, 2] ** 2], axis=1)
    xs, ys = identity_scalers(3, 3)
    theta = np.array([[math.log(0.9), math.log(1.2), math.log(1.5), 0.0, 0.5 * math.log(n2)]
                      for n2 in (4e-7, 1e-4, 1e-2)])  # fmt: skip
    fast = ExactGP.from_theta(x, y, theta, xs, ys)
    slow = ExactGP(fast.x_scaler, fast.y_scaler, fast.theta, fast.x_train, fast.chol_t, fast.alpha,
                   inverse=False)  # fmt: skip
    assert fast.inverse_blocks().has_factor.tolist() == [True, False, True]
    assert not fast.inverse_blocks().blocks[-1][1].any()  # nothing held for the refused output
    q = np.concatenate([x[: queries // 2], rng.uniform(-2, 2, (queries - queries // 2, 3))])
    _same_up_to_rounding(fast, slow, q)


def test_threaded_inverse_blocks_give_the_same_numbers(monkeypatch) -> None:
    """Outputs split over two threads (large blocks) give what one stacked call gives."""
    from threadpoolctl import threadpool_limits

    import estimator_service.gp.inverse as inverse

    rng = np.random.default_rng(13)
    factors = [np.tril(rng.normal(size=(40, 40))) for _ in range(5)]
    blocks = inverse.InverseBlocks.from_factors([*factors[:2], None, *factors[2:]], 6, 40)
    ks = rng.normal(size=(6, 3, 40))
    monkeypatch.setattr(inverse, "THREADED_MIN_BYTES", blocks.nbytes)  # at the threshold: threads
    monkeypatch.setattr(inverse, "blas_threads", lambda: 2)  # the split, on any machine
    groups, shares = [], []
    real, real_norms = inverse.over_outputs, inverse.InverseBlocks.sq_norms
    monkeypatch.setattr(inverse, "over_outputs", lambda fn, w: groups.append(w) or real(fn, w))
    monkeypatch.setattr(
        inverse.InverseBlocks,
        "sq_norms",
        lambda self, k, *a: shares.append(len(k)) or real_norms(self, k, *a),
    )
    with threadpool_limits(2):
        threaded = blocks.sq_norms_threaded(ks)
    assert groups == [2] and sorted(shares) == [3, 3]  # each thread its own half of the outputs
    np.testing.assert_array_equal(threaded, blocks.sq_norms(ks))
    direct = [np.sum((f @ k.T) ** 2, axis=0) for f, k in zip(factors, ks[[0, 1, 3, 4, 5]], strict=True)]
    np.testing.assert_allclose(threaded[[0, 1, 3, 4, 5]], direct, rtol=1e-12)
    assert not threaded[2].any()


def test_inverse_factor_refuses_an_ill_conditioned_factor() -> None:
    from estimator_service.gp.linalg import inverse_factor

    l = np.asfortranarray(np.diag([1.0, 1e-5, 1e-6]))
    assert inverse_factor(l, max_cond=1e4) is None  # condition 1e6: the solve is kept
    np.testing.assert_allclose(inverse_factor(l, max_cond=1e7) @ l, np.eye(3), atol=1e-12)
    exact = np.asfortranarray(np.diag([1.0, 0.25]))  # condition exactly 4 (powers of two)
    np.testing.assert_array_equal(
        inverse_factor(exact, max_cond=4.0), np.diag([1.0, 4.0])
    )  # at the limit: kept
    assert inverse_factor(exact, max_cond=np.nextafter(4.0, 0.0)) is None  # just past it: refused


# -- sparse, heteroscedastic, enhanced ---------------------------------------------------
@pytest.mark.parametrize("queries", [25, 700])
def test_sparse_with_pseudo_inputs_at_training_points_equals_exact(toy, queries: int) -> None:
    """Both outputs have their own length scales, signal and noise variances; 700 queries
    without a Jacobian take the sparse GP's output-by-output batch path."""
    x, y = toy
    x, y = x[:40], y[:40]
    theta = np.array([[0.1, 0.3, 0.0, math.log(0.2)], [-0.2, 0.5, 0.6, math.log(0.1)]])
    xs, ys = identity_scalers(2, 2)
    sparse = SparseGP.from_params(x, y, theta, np.stack([x, x]), xs, ys)
    exact = ExactGP.from_theta(x, y, theta, xs, ys)
    q = np.random.default_rng(7).uniform(-3, 3, (queries, 2))
    jac = queries < 50
    a, b = sparse.predict(q, return_jac=jac), exact.predict(q, return_jac=jac)
    for u, v in ((a.mean, b.mean), (a.var, b.var), *([(a.jac, b.jac)] if jac else [])):
        np.testing.assert_allclose(u, v, rtol=1e-6, atol=1e-8)
    nll_sparse = sparse_nll(np.concatenate([theta[0], x.ravel()]), x, y[:, 0], 40)[0]
    assert nll_sparse == pytest.approx(exact_nll(theta[0], x, y[:, 0])[0], rel=1e-8)
    for arr in (sparse.theta, sparse.pseudo_inputs, sparse.beta, sparse.chol_mm_t, sparse.chol_b_t):
        with pytest.raises(ValueError, match="read-only"):  # a frozen posterior
            arr.flat[0] = 0.0


def test_sparse_fit_is_close_to_exact_on_smooth_data(models, toy) -> None:
    q = np.random.default_rng(8).uniform(-2.5, 2.5, (200, 2))
    truth = np.stack([np.sin(q[:, 0]) + 0.3 * q[:, 1], np.cos(q[:, 1]) * q[:, 0]], axis=1)
    rmse = {k: np.sqrt(np.mean((models[k].predict(q).mean - truth) ** 2)) for k in ("exact", "sparse")}
    assert rmse["sparse"] < 2.0 * rmse["exact"] + 0.02


def test_heteroscedastic_gp_beats_plain_gp_on_input_dependent_noise() -> None:
    rng = np.random.default_rng(9)

    def data(n: int) -> tuple[np.ndarray, np.ndarray]:
        x = rng.uniform(-3, 3, (n, 1))
        std = 0.05 + 0.5 * np.clip(x[:, 0], 0, None) / 3
        return x, np.sin(x[:, 0]) + std * rng.normal(size=n)

    x, y = data(150)
    xt, yt = data(2000)
    het = fit_hetero(x, y, iterations=2, restarts=1, max_iter=80, rng=rng)
    plain = fit_exact(x, y, restarts=2, rng=rng)

    def test_ll(gp) -> float:
        p = gp.predict(xt)
        v, m = p.var[:, 0], p.mean[:, 0]
        return float(np.mean(-0.5 * np.log(2 * np.pi * v) - 0.5 * (yt - m) ** 2 / v))

    assert test_ll(het) > test_ll(plain) + 0.2
    noise = np.sqrt(het.noise_var(np.array([[-2.0], [2.5]])))[:, 0]
    assert noise[1] > 3 * noise[0]  # learned that the right half is noisier


def test_enhanced_gp_falls_back_to_parametric_model_far_from_data() -> None:
    rng = np.random.default_rng(10)
    x = rng.uniform(-2, 2, (60, 1))
    f = lambda q: 2.0 * q  # noqa: E731 - parametric model: slope known
    y = 2.0 * x + 0.3 * np.sin(3 * x)
    egp = fit_enhanced(x, y, f, fit_exact, mean_jacobian=lambda q: np.full((len(q), 1, 1), 2.0))
    plain = fit_exact(x, y)
    far = np.array([[25.0]])
    assert abs(egp.predict(far).mean[0, 0] - 50.0) < 0.5
    assert abs(plain.predict(far).mean[0, 0] - 50.0) > 5.0
    assert egp.predict(far, return_jac=True).jac[0, 0, 0] == pytest.approx(2.0, abs=1e-3)
    # a one-output mean function may return (M,) rather than (M, 1): the same model
    flat = fit_enhanced(x, y, lambda q: 2.0 * q[:, 0], fit_exact, mean_jacobian=egp.mean_jacobian)
    q = np.array([[-1.0], [0.5], [25.0]])
    np.testing.assert_allclose(flat.predict(q).mean, egp.predict(q).mean, rtol=1e-12)


def test_posterior_is_immutable(models) -> None:
    gp = models["exact"]
    with pytest.raises(ValueError):
        gp.alpha[0, 0] = 1.0
    with pytest.raises(AttributeError):
        gp.theta = gp.theta  # frozen dataclass


def test_training_reports_progress_per_output_through_callback(toy) -> None:
    x, y = toy
    seen = []
    fit_exact(x[:30], y[:30, 0], restarts=1, max_iter=5, callback=seen.append)
    assert seen and seen[0].iteration == 1 and np.isfinite(seen[-1].objective)
    assert [s.iteration for s in seen if s.restart == 0][:3] == [1, 2, 3]  # counted per restart
    assert seen[-1].model == "exact"
    seen.clear()
    fit_sparse(x[:30], y[:30], n_pseudo=5, max_iter=3, callback=seen.append)
    assert {s.output for s in seen} == {0, 1} and {s.model for s in seen} == {"sparse"}
    smallest = fit_sparse(x[:3], y[:3], n_pseudo=3, max_iter=2)  # as few points as pseudo-inputs
    assert np.all(np.isfinite(smallest.predict(x[:5]).mean))


def test_exact_and_heteroscedastic_fits_draw_from_the_generator_they_are_given(toy) -> None:
    """Restarts and the hyperparameter subset come from ``rng``: the generator advances, and
    the same seed gives the same fit."""
    x, y = toy
    rng = np.random.default_rng(5)
    before = rng.bit_generator.state
    a = fit_exact(x, y[:, 0], restarts=2, max_iter=5, hyper_points=40, rng=rng)
    assert rng.bit_generator.state != before
    b = fit_exact(x, y[:, 0], restarts=2, max_iter=5, hyper_points=40, rng=np.random.default_rng(5))
    np.testing.assert_array_equal(a.theta, b.theta)
    before = rng.bit_generator.state
    fit_hetero(x[:40], y[:40, 0], iterations=1, restarts=1, max_iter=3, hyper_points=20, rng=rng)
    assert rng.bit_generator.state != before
    # without a generator the fit is seeded, so it is repeatable too
    unseeded = [fit_exact(x, y[:, 0], restarts=2, max_iter=5, hyper_points=40).theta for _ in range(2)]
    np.testing.assert_array_equal(*unseeded)


def test_a_sparse_fit_starts_from_distinct_training_inputs_drawn_by_its_generator(toy, monkeypatch) -> None:
    """Each output's search starts once per restart inside the hyperparameter box (the
    pseudo-inputs unbounded), its pseudo-inputs distinct standardised training inputs drawn
    by ``rng`` (70 of 80: a draw with replacement would repeat one); fewer training points
    than pseudo-inputs is refused by name."""
    import estimator_service.gp.sparse as sparse_module
    from estimator_service.gp.hyper import theta_bounds

    real, calls = sparse_module.optimize_theta, []

    def spy(objective, starts, bounds, *rest):
        calls.append((starts, bounds))
        return real(objective, starts, bounds, *rest)

    monkeypatch.setattr(sparse_module, "optimize_theta", spy)
    x, y = toy
    m, d = 70, 2

    def fit(seed: int, restarts: int = 1) -> SparseGP:
        return fit_sparse(
            x, y[:, 0], n_pseudo=m, restarts=restarts, max_iter=1, rng=np.random.default_rng(seed)
        )

    gp = fit(3)
    (starts, bounds), xs = calls[-1], gp.x_scaler.apply(x)
    assert len(starts) == 1 and bounds == theta_bounds(d) + [(None, None)] * (m * d)
    z0 = starts[0][d + 2 :].reshape(m, d)
    assert len(np.unique(z0, axis=0)) == m
    assert all(np.any(np.all(xs == row, axis=1)) for row in z0)  # each a training input
    fit(4)
    assert not np.array_equal(calls[-1][0][0][d + 2 :], z0.ravel())  # another generator, another draw
    fit(4, restarts=3)
    assert len(calls[-1][0]) == 3
    np.testing.assert_array_equal(fit(3).pseudo_inputs, gp.pseudo_inputs)  # the same seed, the same fit
    with pytest.raises(ValueError, match="need at least 70 training points, got 60"):
        fit_sparse(x[:60], y[:60, 0], n_pseudo=m, max_iter=1)


# -- persistence ----------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["exact", "sparse", "hetero", "enhanced"])
def test_save_load_round_trips_exactly(models, kind: str, tmp_path: Path) -> None:
    gp = models[kind]
    path = save_gp(gp, tmp_path / f"{kind}.npz")
    extra = {"mean_function": gp.mean_function} if kind == "enhanced" else {}
    back = load_gp(path, **extra)
    assert back.kind == kind
    q = np.random.default_rng(11).uniform(-3, 3, (17, 2))
    a, b = gp.predict(q, return_jac=True), back.predict(q, return_jac=True)
    for u, v in ((a.mean, b.mean), (a.var, b.var), (a.jac, b.jac)):
        np.testing.assert_array_equal(u, v)
    assert not list(tmp_path.glob("*.tmp"))


def test_malformed_model_files_are_rejected_naming_the_file_and_field(models, tmp_path: Path) -> None:
    good = save_gp(models["exact"], tmp_path / "good.npz")
    raw = good.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(ModelFileError, match="truncated"):
        load_gp(truncated)
    arrays = dict(np.load(good, allow_pickle=False))
    cases = {
        "version": {**arrays, "__format__": np.array(99)},
        "alpha": {**arrays, "alpha": arrays["alpha"][:, :-1]},
        "chol_t": {**arrays, "chol_t": np.zeros((1, 2, 2))},  # an older file's factors, misshapen
        "kind": {**arrays, "__kind__": np.array("mystery")},
        "x_std": {k: v for k, v in arrays.items() if k != "x_std"},
        "y_mean": {**arrays, "y_mean": np.array(["a", "b"])},
    }
    for needle, content in cases.items():
        path = tmp_path / f"bad_{needle}.npz"
        np.savez(path, **content)
        with pytest.raises(ModelFileError, match=rf"bad_{needle}\.npz.*{needle}"):  # the file, then the field
            load_gp(path)
    egp = save_gp(models["enhanced"], tmp_path / "egp.npz")
    with pytest.raises(ModelFileError, match="mean_function"):
        load_gp(egp)


@pytest.mark.parametrize("kind", ["exact", "sparse", "hetero"])
def test_every_array_of_a_model_file_missing_or_misshapen_is_named_with_the_file(
    models, kind: str, tmp_path: Path
) -> None:
    """Each float array of a saved GP (nested ones by their prefix), removed (but the optional
    noise profile) or one entry short on its last axis, is refused with the file's name first
    and then the array or the shapes that disagree; arrays of another float precision load
    as float64, and what a GP keeps besides its posterior (the heteroscedastic GP's noise
    profile, none for a plain GP) comes back as saved."""
    path = save_gp(models[kind], tmp_path / "good.npz")
    arrays = dict(np.load(path, allow_pickle=False))
    floats = [k for k, v in arrays.items() if v.dtype == np.float64]
    assert len(floats) >= 7
    bad = tmp_path / "bad.npz"
    for key in floats:
        short = arrays[key][..., :-1] if arrays[key].shape[-1] > 1 else arrays[key][..., None]
        cases = [({**arrays, key: short}, "inconsistent shapes: ")]
        if not key.endswith("noise_profile"):  # optional: a plain exact GP has none
            cases.append(({k: v for k, v in arrays.items() if k != key}, f"missing array '{key}'"))
        for content, says in cases:
            np.savez(bad, **content)
            message = load_refused(bad, says)
            assert "None" not in message, message  # the shapes that disagree, named
    np.savez(bad, **{k: v.astype(np.float32) if k in floats else v for k, v in arrays.items()})
    single = load_gp(bad)
    assert single.predict(np.zeros((1, 2))).mean.dtype == np.float64
    parts = (single.main, single.noise) if kind == "hetero" else (single,)
    assert all(part.theta.dtype == np.float64 for part in parts)  # converted on load
    back = load_gp(path)
    inner = (back.main, back.noise) if kind == "hetero" else (back,)
    kept = (models[kind].main, models[kind].noise) if kind == "hetero" else (models[kind],)
    for gp, want in zip(inner, kept, strict=True):
        if isinstance(want, ExactGP) and want.noise_profile is not None:
            np.testing.assert_array_equal(gp.noise_profile, want.noise_profile)
        elif isinstance(want, ExactGP):
            assert gp.noise_profile is None


def test_hostile_gp_files_are_refused_by_name_at_no_cost(models, tmp_path: Path) -> None:
    """A file declaring a terabyte array is refused before anything is read; a pickled array
    (code a load would run) is never unpickled; a ``__format__`` that is not one integer, a
    heteroscedastic GP whose parts are not both exact GPs or differ in outputs: each a
    :class:`ModelFileError` naming the file and the fault."""
    from tests.hostile_files import npz_declaring

    bad = tmp_path / "bad.npz"

    def refused(says: str) -> None:
        load_refused(bad, says)

    npz_declaring(bad, "theta", (10**12,), {"__format__": np.array(1)})
    refused("declares 8000000000000 bytes")
    exact = dict(np.load(save_gp(models["exact"], tmp_path / "exact.npz"), allow_pickle=False))
    npz_declaring(bad, "unused", (1,), {**exact, "__kind__": np.array("exact", dtype=object)})
    refused("unreadable")
    np.savez(bad, **{**exact, "__format__": np.array([1, 2])})
    refused("'__format__' must be one integer")
    hetero = dict(np.load(save_gp(models["hetero"], tmp_path / "hetero.npz"), allow_pickle=False))
    sparse = dict(np.load(save_gp(models["sparse"], tmp_path / "sparse.npz"), allow_pickle=False))
    for part in ("main/", "noise/"):
        swapped = {k: v for k, v in hetero.items() if not k.startswith(part)}
        np.savez(bad, **swapped, **{part + k: v for k, v in sparse.items() if k != "__format__"})
        refused("heteroscedastic parts must be exact GPs")
    one_output = {k: v[:1] if k.split("/")[-1] in ("theta", "alpha", "y_mean", "y_std") else v
                  for k, v in hetero.items()}  # fmt: skip
    np.savez(bad, **{k: v for k, v in hetero.items() if not k.startswith("noise/")},
             **{k: v for k, v in one_output.items() if k.startswith("noise/")})  # fmt: skip
    refused("inconsistent shapes: main and noise GPs differ in outputs")  # the text as written


def test_an_exact_gp_file_keeps_no_factors_and_loads_them_again_bit_for_bit(models, tmp_path: Path) -> None:
    """A saved exact GP holds its data and ``alpha`` but not its ``P n^2`` Cholesky factors;
    loading factors again to the same bits, under any BLAS thread count, so the loaded GP
    predicts exactly as the fitted one. A file of the older layout (with ``chol_t``) loads as
    before; one whose training points would need more than the array limit of factors is
    refused before anything is factored."""
    from threadpoolctl import threadpool_limits

    from estimator_service.gp import ExactGP

    rng = np.random.default_rng(3)  # 300 points: OpenBLAS's threaded potrf rounds otherwise
    x, y = rng.uniform(-2, 2, (300, 2)), rng.normal(size=(300, 2))
    one = Scaler(np.zeros(2), np.ones(2))
    with threadpool_limits(2):
        gp = ExactGP.from_theta(x, y, np.log([[0.7, 0.7, 1.0, 0.01]] * 2), one, one)
    path = save_gp(gp, tmp_path / "exact.npz")
    arrays = dict(np.load(path, allow_pickle=False))
    assert "chol_t" not in arrays and path.stat().st_size < 30_000  # the factors alone: 1.4 MB
    for threads in (1, 2):
        with threadpool_limits(threads):
            back = load_gp(path)
        np.testing.assert_array_equal(back.chol_t, gp.chol_t)
    ints = ExactGP.from_theta(x[:20], y[:20], np.zeros((2, 4), dtype=int), one, one)  # integer theta
    assert (
        ints.theta.dtype == np.float64 and load_gp(save_gp(ints, tmp_path / "ints.npz")).theta.dtype == float
    )
    np.savez(tmp_path / "older.npz", **arrays, chol_t=gp.chol_t)
    older = load_gp(tmp_path / "older.npz")
    assert isinstance(older, ExactGP)
    np.testing.assert_array_equal(older.predict(np.ones((3, 2))).var, gp.predict(np.ones((3, 2))).var)
    n = 2**14 + 1  # 2^31 bytes of factors for one output at 2^14 points
    big = {**arrays, "theta": arrays["theta"][:1], "x_train": np.zeros((n, 2)), "alpha": np.zeros((1, n)),
           "y_mean": arrays["y_mean"][:1], "y_std": arrays["y_std"][:1]}  # fmt: skip
    np.savez(tmp_path / "big.npz", **big)
    load_refused(tmp_path / "big.npz", "bytes of Cholesky factors")
    for value in (-1000.0, 1000.0):  # length scales and variances of 0 or inf: no fit gives them
        np.savez(tmp_path / "nan.npz", **{**arrays, "theta": np.full_like(arrays["theta"], value)})
        load_refused(tmp_path / "nan.npz", "its kernel matrix cannot be factored")
    hetero = dict(np.load(save_gp(models["hetero"], tmp_path / "hetero.npz"), allow_pickle=False))
    np.savez(
        tmp_path / "neg.npz",
        **{**hetero, "main/noise_profile": -1e6 * np.ones_like(hetero["main/noise_profile"])},
    )
    load_refused(tmp_path / "neg.npz", "its kernel matrix cannot be factored: ")  # negative noise


def test_exact_gp_factors_of_the_array_limit_load_and_optional_arrays_are_checked_by_name(
    models, tmp_path: Path, monkeypatch
) -> None:
    """Factors of exactly the array limit are allowed and one byte less of limit refuses them
    (the limit is the largest array a file may hold); a noise profile or stored factors (the
    older layout) holding NaN are refused with the file's name first, like every other array."""
    import estimator_service.gp.io as gp_io

    path = save_gp(models["exact"], tmp_path / "exact.npz")
    exact = dict(np.load(path, allow_pickle=False))
    p, n = exact["alpha"].shape
    factor_bytes = p * n * n * 8
    monkeypatch.setattr(gp_io, "MAX_ARRAY_BYTES", factor_bytes)
    np.testing.assert_array_equal(load_gp(path).chol_t, models["exact"].chol_t)
    monkeypatch.setattr(gp_io, "MAX_ARRAY_BYTES", factor_bytes - 1)
    load_refused(path, f"need {factor_bytes} bytes of Cholesky factors")
    monkeypatch.undo()
    bad = tmp_path / "bad.npz"
    np.savez(bad, **exact, chol_t=np.full_like(models["exact"].chol_t, np.nan))
    load_refused(bad, "array 'chol_t' holds NaN")
    hetero = dict(np.load(save_gp(models["hetero"], tmp_path / "hetero.npz"), allow_pickle=False))
    np.savez(bad, **{**hetero, "main/noise_profile": np.full_like(hetero["main/noise_profile"], np.nan)})
    load_refused(bad, "array 'main/noise_profile' holds NaN")


# -- bad input --------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("x", "y", "match"),
    [
        (np.array([[0.0], [np.nan], [1.0]]), np.zeros(3), "training X contains NaN or Inf .first at row 1"),
        (np.zeros((3, 1)), np.array([0.0, np.inf, 1.0]), "training Y contains NaN or Inf .first at row 1"),
        (np.zeros((4, 1)), np.zeros(3), "rows"),
        (np.zeros((2, 1)), np.zeros(2), "at least"),
        (np.zeros(5), np.zeros(5), "2-D"),
    ],
)
def test_bad_training_data_raises(x, y, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        fit_exact(x, y)


def test_bad_queries_raise(models) -> None:
    gp = models["sparse"]
    with pytest.raises(ValueError, match=r"shape \(M, 2\)"):
        gp.predict(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="NaN"):
        gp.predict(np.array([[0.0, np.nan]]))


@pytest.mark.parametrize("queries", [1, 40, 800])  # 800: output by output over threads
def test_sparse_inverse_factor_variance_matches_the_solve_on_a_near_noiseless_gp(queries: int) -> None:
    """The sparse GP's stacked ``L^-1`` products against its per-output triangular solves,
    noise 4e-7 of the signal, 50 pseudo-inputs at training points and queries at and
    between training points: within rounding of the solve's, each output with its own
    length scales and signal variance, Jacobians included."""
    rng = np.random.default_rng(12)
    x = rng.uniform(-2, 2, (400, 3))
    y = np.stack([np.sin(x @ np.array([1.0, -0.7, 0.4])), np.cos(x[:, 0])], axis=1)
    xs, ys = identity_scalers(3, 2)
    log_sf = np.array([[0.0], [0.4]])
    theta = np.hstack([np.log([[0.9, 1.2, 1.5], [1.3, 0.8, 1.1]]), log_sf, log_sf + 0.5 * math.log(4e-7)])
    fast = SparseGP.from_params(x, y, theta, np.stack([x[:50], x[50:100]]), xs, ys)
    slow = SparseGP(fast.x_scaler, fast.y_scaler, fast.theta, fast.pseudo_inputs, fast.beta,
                    fast.chol_mm_t, fast.chol_b_t, inverse=False)  # fmt: skip
    assert fast.projection() is not None  # well enough conditioned to be used
    q = np.concatenate([x[: queries // 2], rng.uniform(-2, 2, (queries - queries // 2, 3))])
    _same_up_to_rounding(fast, slow, q, mean_rtol=1e-12)  # the same sum, in another order
    jac_fast, jac_slow = (gp.predict(q, return_jac=True).jac for gp in (fast, slow))
    np.testing.assert_allclose(jac_fast, jac_slow, rtol=1e-9, atol=1e-12)


def test_batch_prediction_does_not_depend_on_the_thread_count() -> None:
    """Outputs spread over threads give bit-identical results to one thread."""
    from threadpoolctl import threadpool_limits

    from estimator_service.gp.linalg import blas_threads

    rng = np.random.default_rng(3)
    x = rng.normal(size=(300, 4))
    y = np.stack([np.sin(x[:, 0]), np.cos(x[:, 1]), x[:, 2] * x[:, 3]], axis=1)
    xs, ys = identity_scalers(4, 3)
    theta = np.tile([0.2, 0.3, 0.1, 0.4, 0.0, math.log(0.05)], (3, 1))
    gps = [
        ExactGP.from_theta(x, y, theta, xs, ys),
        SparseGP.from_params(x, y, theta, np.stack([x[:40], x[40:80], x[80:120]]), xs, ys),
    ]
    q = rng.normal(size=(800, 4))  # both GPs' output-by-output paths
    for gp in gps:
        many = gp.predict(q, return_jac=isinstance(gp, ExactGP))
        with threadpool_limits(1):
            assert blas_threads() == 1
            one = gp.predict(q, return_jac=isinstance(gp, ExactGP))
        for field in ("mean", "var", "jac"):
            np.testing.assert_array_equal(getattr(many, field), getattr(one, field))


def test_over_outputs_runs_every_output_once_and_raises_its_errors() -> None:
    from estimator_service.gp.linalg import blas_threads
    from estimator_service.gp.parallel import over_outputs

    before = blas_threads()
    seen: list[int] = []
    over_outputs(seen.append, 7)
    assert sorted(seen) == list(range(7))

    def fail(p: int) -> None:
        if p == 3:
            raise ValueError("output 3")

    with pytest.raises(ValueError, match="output 3"):
        over_outputs(fail, 5)
    assert blas_threads() == before  # the one-thread limit is lifted again


def test_over_outputs_keeps_one_pool_grows_it_and_runs_nested_calls_inline() -> None:
    """With ``w`` BLAS threads allowed the outputs run on ``w`` named pool threads, the same
    threads serve the next call (one pool, kept), a larger ``w`` replaces the pool with a
    larger one, ``w = 1`` runs in the calling thread, and a call made on a pool thread runs
    inline there (it would otherwise wait on the pool it occupies)."""
    import threading

    from threadpoolctl import threadpool_limits

    from estimator_service.gp.linalg import blas_threads
    from estimator_service.gp.parallel import over_outputs

    def threads(outputs: int, inner: bool = False, meet: bool = True) -> dict[int, threading.Thread]:
        """Which thread ran each output; with ``meet`` the first ``w`` outputs meet at a
        barrier, so each of the ``w`` strides is running on its own thread at once."""
        w, seen, lock = min(blas_threads(), outputs), {}, threading.Lock()
        barrier = threading.Barrier(w, timeout=20)

        def fn(p: int) -> None:
            with lock:
                seen[p] = threading.current_thread()
            if meet and p < w and w > 1:
                barrier.wait()
            if inner:  # a nested call: its outputs must run where it was made
                nested = threads(2, meet=False)
                assert set(nested.values()) == {threading.current_thread()}

        over_outputs(fn, outputs)
        return seen

    def run(target) -> object:
        """``target()`` on a helper thread that must finish within 30 s (a nested call that
        waited on its own pool would hang)."""
        out: list = []
        helper = threading.Thread(target=lambda: out.append(target()), daemon=True)
        helper.start()
        helper.join(30)
        assert not helper.is_alive() and out, "over_outputs hung"
        return out[0]

    with threadpool_limits(2):
        first, again = run(lambda: threads(4)), run(lambda: threads(4))
        assert len(set(first.values())) == 2 and set(again.values()) == set(first.values())
        assert all(t.name.startswith("gp-outputs") for t in first.values())
        run(lambda: threads(4, inner=True))
    with threadpool_limits(3):
        grown = run(lambda: threads(6))
        assert len(set(grown.values())) == 3 and not set(grown.values()) & set(first.values())
    with threadpool_limits(1):
        caller = run(lambda: (threading.current_thread(), threads(3)))
        assert set(caller[1].values()) == {caller[0]}


@pytest.mark.parametrize("name", ["exact", "sparse", "hetero"])
def test_conditioned_keeps_the_hyperparameters_and_follows_the_new_data(models, toy, name: str) -> None:
    """Conditioned on its own training data a fitted GP predicts as before; conditioned on
    half of it, it keeps its hyperparameters and scalers and its posterior changes; data of
    the wrong width is refused, naming the array."""
    x, y = toy
    gp = models[name]
    q = np.random.default_rng(2).uniform(-3, 3, (7, 2))
    a, b = gp.predict(q, return_jac=True), gp.conditioned(x, y).predict(q, return_jac=True)
    for u, v in ((a.mean, b.mean), (a.var, b.var), (a.jac, b.jac)):
        np.testing.assert_allclose(v, u, rtol=1e-8, atol=1e-10)
    half = gp.conditioned(x[:40], y[:40])
    inner, inner_half = (g.main if name == "hetero" else g for g in (gp, half))
    np.testing.assert_array_equal(inner_half.theta, inner.theta)
    np.testing.assert_array_equal(inner_half.x_scaler.std, inner.x_scaler.std)
    assert not np.allclose(half.predict(q).mean, a.mean, atol=1e-3)
    with pytest.raises(ValueError, match="X have 1 columns"):
        gp.conditioned(x[:, :1], y)
    with pytest.raises(ValueError, match="Y have 1 columns"):
        gp.conditioned(x, y[:, :1])


def test_central_differences_scale_their_step_with_the_input() -> None:
    """``numeric_jacobian``: step ``1e-6 max(1, |x|)``, so a cubic is differentiated to its
    rounding at ``|x|`` of 1e-3 and of 1e6 alike (one batched call of ``f``)."""
    from estimator_service.gp.enhanced import numeric_jacobian, value_and_jacobian

    calls = []

    def f(x):
        calls.append(len(x))
        return np.stack([x[:, 0] ** 3, x[:, 0] * x[:, 1]], axis=1)

    x = np.array([[1e-3, 2.0], [1e6, -3.0]])
    jac = numeric_jacobian(f, x)
    want = np.array([[[3e-6, 0.0], [2.0, 1e-3]], [[3e12, 0.0], [-3.0, 1e6]]])
    np.testing.assert_allclose(jac, want, rtol=1e-6, atol=1e-9)
    assert calls == [2 * (2 * 2 + 1)]
    at, jac2 = value_and_jacobian(f, x)
    np.testing.assert_array_equal(at, f(x))
    np.testing.assert_array_equal(jac2, jac)
    # a central difference of x^3 is 3 x^2 + h^2 exactly: the step is rel_step max(1, |x|)
    x = np.array([[1e-3, 2.0], [5.0, -3.0]])
    h = 0.01 * np.array([1.0, 5.0])
    cubic = numeric_jacobian(f, x, rel_step=0.01)[:, 0, 0]
    np.testing.assert_allclose(cubic, 3 * x[:, 0] ** 2 + h**2, rtol=1e-9)


def test_starting_points_follow_the_median_distance_heuristic() -> None:
    """``initial_thetas``: three fixed starts around ``log(median |x_i - x_j| sqrt(d))`` (its
    pairs drawn from the generator given), then random ones: log length scales ``N(first,
    1)``, independent per dimension; noise std log-uniform in [0.03, 0.5]; signal std 1."""
    from estimator_service.gp.hyper import initial_thetas

    x = np.random.default_rng(7).normal(size=(50, 3)) * [1.0, 2.0, 0.5]
    starts = np.array(initial_thetas(x, 400, np.random.default_rng(8)))
    idx = np.random.default_rng(8).integers(0, 50, size=(2000, 2))
    base = np.log(np.maximum(np.median(np.abs(x[idx[:, 0]] - x[idx[:, 1]]), axis=0), 1e-3) * np.sqrt(3))
    np.testing.assert_allclose(starts[:3, :3], base + np.log([[1.0], [0.3], [3.0]]), rtol=1e-12)
    np.testing.assert_allclose(starts[:3, 3:], np.log([[1.0, 0.3], [1.0, 0.1], [1.0, 0.5]]), rtol=1e-12)
    z, noise = starts[3:, :3] - base, np.exp(starts[3:, 4])
    assert np.all(starts[3:, 3] == 0.0) and abs(z.mean()) < 0.15 and 0.9 < z.std() < 1.1
    assert np.all(np.abs(np.corrcoef(z.T)[np.triu_indices(3, 1)]) < 0.2)  # a draw per dimension
    assert 0.03 <= noise.min() < 0.035 and 0.45 < noise.max() <= 0.5


def test_the_optimiser_keeps_the_best_start_inside_its_box_and_iteration_budget() -> None:
    """``optimize_theta``: L-BFGS-B from each start inside the bounds, at most ``max_iter``
    iterations each (each reported with its objective value), the best finite result kept;
    a failed factorisation (``LinAlgError``) counts as a huge value, not an error.
    ``random_subset`` takes at least 3 rows."""
    from estimator_service.gp import hyper

    def rosen(t):
        f = (1 - t[0]) ** 2 + 100 * (t[1] - t[0] ** 2) ** 2
        return f, np.array([-2 * (1 - t[0]) - 400 * t[0] * (t[1] - t[0] ** 2), 200 * (t[1] - t[0] ** 2)])

    seen: list = []
    box = [(-2.0, 0.5), (-2.0, 2.0)]  # the optimum (1, 1) lies outside: x stops at 0.5
    theta = hyper.optimize_theta(rosen, [np.zeros(2)], box, 200, "r", 3, seen.append)
    np.testing.assert_allclose(theta, [0.5, 0.25], atol=1e-4)
    seen.clear()
    hyper.optimize_theta(rosen, [np.array([-1.2, 1.0])], None, 3, "r", 3, seen.append)
    assert [s.iteration for s in seen] == [1, 2, 3] and {(s.model, s.output) for s in seen} == {("r", 3)}
    assert all(np.isfinite(s.objective) for s in seen)
    # the best start wins, whichever comes first; a worse finite result never replaces it
    best = hyper.optimize_theta(rosen, [np.ones(2), np.array([-1.2, 1.0])], None, 2, "r", 0, None)
    np.testing.assert_array_equal(best, np.ones(2))

    def brittle(t):
        if t[0] > 0.5:
            raise np.linalg.LinAlgError("not positive definite")
        return rosen(t)

    theta = hyper.optimize_theta(brittle, [np.zeros(2)], None, 50, "r", 0, None)
    assert np.all(np.isfinite(theta)) and theta[0] <= 0.5
    assert len(hyper.random_subset(10, 2, np.random.default_rng(0))) == 3
    # a weak signal under strong noise: the fit's signal std (standardised units) falls well
    # below 1 and its noise std near 1, both inside the box
    rng = np.random.default_rng(4)
    x = rng.uniform(-3, 3, (120, 1))
    gp = fit_exact(x, 0.15 * np.sin(x[:, 0]) + rng.normal(size=120), restarts=1, max_iter=60, rng=rng)
    assert np.exp(gp.theta[0, -2]) < 0.5 and 0.7 < np.exp(gp.theta[0, -1]) < 1.1


@pytest.mark.parametrize("polish", [0, 1, 2])
def test_a_subset_search_is_polished_on_all_rows(toy, monkeypatch, polish: int) -> None:
    """``learn_thetas`` with a subset: the search evaluates the likelihood on the subset's
    rows only, then ``polish_iter`` iterations (none for 0) on all rows, each optimisation
    reporting its output."""
    from estimator_service.gp import hyper

    x, y = toy
    rows: list[int] = []
    real = hyper.exact_nll
    monkeypatch.setattr(hyper, "exact_nll", lambda t, xs, *a: rows.append(len(xs)) or real(t, xs, *a))
    seen: list = []
    subset = hyper.random_subset(len(x), 20, np.random.default_rng(0))
    hyper.learn_thetas(x, y[:, 1:], [[np.zeros(4)]], max_iter=3, name="q", callback=seen.append,
                       subset=subset, polish_iter=polish)  # fmt: skip
    first_all = rows.index(len(x)) if len(x) in rows else len(rows)
    assert set(rows[:first_all]) == {20} and set(rows[first_all:]) <= {len(x)}
    assert (first_all < len(rows)) == (polish > 0) and {s.output for s in seen} == {0}


def test_a_gp_conditions_on_a_single_point() -> None:
    rng = np.random.default_rng(2)
    x = rng.normal(size=(40, 2))
    gp = fit_exact(x, np.sin(x[:, :1]) + 0.01 * rng.normal(size=(40, 1)), restarts=0, max_iter=20, rng=rng)
    one = gp.conditioned(np.array([[0.3, -0.2]]), np.array([[0.5]]))
    p = one.predict(np.array([[0.3, -0.2]]))
    assert (
        p.mean[0, 0] == pytest.approx(0.5, abs=0.1)
        and p.var[0, 0] < gp.predict(np.array([[9.0, 9.0]])).var[0, 0]
    )


def test_heteroscedastic_noise_is_reported_in_the_targets_units() -> None:
    """Targets scaled by 10 (a standardised std far from 1): the learned noise standard
    deviation in original units is the generating one (0.05 + x/6, times 10) within 40 %."""
    rng = np.random.default_rng(9)
    x = rng.uniform(-3, 3, (300, 1))
    std = 0.05 + 0.5 * np.clip(x[:, 0], 0, None) / 3
    y = 10 * (np.sin(x[:, 0]) + std * rng.normal(size=300))
    het = fit_hetero(x, y, iterations=2, restarts=1, max_iter=80, rng=rng)
    noise = np.sqrt(het.noise_var(np.array([[1.5], [2.5]])))[:, 0]
    np.testing.assert_allclose(noise, 10 * (0.05 + np.array([1.5, 2.5]) / 6), rtol=0.4)


def test_an_enhanced_gps_variance_includes_the_noise_by_default() -> None:
    rng = np.random.default_rng(10)
    x = rng.uniform(-2, 2, (60, 1))
    y = np.sin(x) + 0.1 * rng.normal(size=(60, 1))
    egp = fit_enhanced(x, y, lambda q: 0.9 * q, fit_exact, restarts=0, max_iter=30, rng=rng)
    q = np.array([[0.3], [1.1]])
    with_noise, latent = egp.predict(q), egp.predict(q, include_noise=False)
    np.testing.assert_array_equal(with_noise.var, egp.residual.predict(q).var)
    assert np.all(with_noise.var > latent.var + 1e-3)
    mean_only = egp.predict(q, return_var=False)  # no variance asked: none computed
    assert mean_only.var is None and np.array_equal(mean_only.mean, with_noise.mean)


def test_the_kernel_block_never_exceeds_the_signal_variance() -> None:
    """The cross-kernel's expanded distance ``|a|^2 - 2 a.b + |b|^2`` loses digits far from the
    origin and can come out below zero; the block is clamped at ``sf^2`` (both the all-output
    block and one output's), so ``k(x, x) = sf^2`` exactly at the centres, never above (above
    it by 1e-12 here without the clamp)."""
    from estimator_service.gp.kernel import CrossKernel

    rng = np.random.default_rng(0)
    centres = rng.normal(0.0, 30.0, (200, 4))
    theta = np.array([[0.3, -0.2, 0.1, 0.5, 0.4, -2.0], [0.0, 0.2, -0.3, 0.1, -0.3, -2.0]])
    kernel = CrossKernel.build(centres, theta, rng.normal(size=(2, 200)))
    sf2 = np.exp(2.0 * theta[:, -2])
    blocks = kernel.block(centres)
    for p in range(2):
        for k in (blocks[p], kernel.block_one(centres, p)):
            assert k.max() <= sf2[p]
            np.testing.assert_allclose(np.diag(k), sf2[p], rtol=1e-10)


def test_the_kernel_of_a_batch_of_outputs_is_each_outputs_kernel() -> None:
    """``sq_dist`` and ``se_kernel`` on stacked inputs ``(P, M, d)``, ``(P, n, d)`` (one set of
    length scales and signal variance per output, as documented) give each output's 2-D
    block, which is SciPy's squared Euclidean distance; with ``M``, ``n`` and ``d`` all
    different, so no axis can stand in for another."""
    from scipy.spatial.distance import cdist

    from estimator_service.gp.kernel import sq_dist

    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(3, 4, 2)), rng.normal(size=(3, 6, 2))
    ell, sf2 = rng.uniform(0.5, 2.0, (3, 2)), np.array([0.5, 1.0, 2.0])
    d2, k = sq_dist(a, b), se_kernel(a, b, ell, sf2)
    assert d2.shape == k.shape == (3, 4, 6)
    for p in range(3):
        np.testing.assert_allclose(d2[p], cdist(a[p], b[p], "sqeuclidean"), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(k[p], se_kernel(a[p], b[p], ell[p], sf2[p]), rtol=1e-13)


def test_the_inverse_factor_judges_the_lower_triangle_it_inverts() -> None:
    """``inverse_factor`` refuses a factor by the condition of its lower triangle: one with a
    unit diagonal and a large entry below it (condition about 1e12) is refused under 1e4 and
    inverted under 1e13; its strictly upper part, zero, is never read."""
    from estimator_service.gp.linalg import inverse_factor

    l = np.asfortranarray([[1.0, 0.0], [1e6, 1.0]])
    assert inverse_factor(l, max_cond=1e4) is None
    np.testing.assert_allclose(inverse_factor(l, max_cond=1e13), [[1.0, 0.0], [-1e6, 1.0]], rtol=1e-12)
    garbage_above = np.asfortranarray([[1.0, 5.0], [1e6, 1.0]])  # a lower factor ignores it
    assert inverse_factor(garbage_above, max_cond=1e4) is None
    np.testing.assert_array_equal(
        inverse_factor(garbage_above, max_cond=1e13), inverse_factor(l, max_cond=1e13)
    )


def test_a_kernel_with_a_bad_diagonal_is_refused_by_its_diagonal() -> None:
    """A matrix that fails its factorisation with a diagonal negative on average gets no
    jitter ladder (a negative jitter would make it worse): it is refused naming its diagonal."""
    from estimator_service.gp.linalg import NotPositiveDefiniteError, robust_cholesky

    with pytest.raises(NotPositiveDefiniteError, match="non-positive or non-finite diagonal"):
        robust_cholesky(np.array([[-3.0, 0.0], [0.0, 1.0]]))


def test_a_kernel_that_needs_jitter_gets_the_least_that_works() -> None:
    """A kernel with a tiny negative eigenvalue: jitter starts at 1e-10 of the mean
    diagonal and grows tenfold per failure, so the first that works (1e-7) is added and the
    factor reproduces ``K + jitter I``; a zero diagonal is refused."""
    from estimator_service.gp.linalg import NotPositiveDefiniteError, robust_cholesky

    q, _ = np.linalg.qr(np.random.default_rng(4).normal(size=(3, 3)))
    k = q @ np.diag([2.0, 1.0, -5e-8]) @ q.T  # mean diagonal 1; needs jitter above 5e-8
    k = 0.5 * (k + k.T)
    l, jitter = robust_cholesky(k)
    assert jitter == pytest.approx(1e-10 * np.mean(np.diag(k)) * 1e3, rel=1e-12)  # the fourth try
    np.testing.assert_allclose(l @ l.T, k + jitter * np.eye(3), atol=1e-12)
    with pytest.raises(NotPositiveDefiniteError):
        robust_cholesky(np.zeros((3, 3)))
    with pytest.raises(NotPositiveDefiniteError):  # needs more than the last try's 1e-3
        robust_cholesky(q @ np.diag([2.0, 1.0, -5e-3]) @ q.T)


def test_a_hyperparameter_subset_draws_distinct_points() -> None:
    from estimator_service.gp.hyper import random_subset

    sub = random_subset(50, 40, np.random.default_rng(0))
    assert len(sub) == 40 and len(np.unique(sub)) == 40 and np.all(np.diff(sub) > 0)
    assert random_subset(50, 50, np.random.default_rng(0)) is None


def test_a_batch_larger_than_the_memory_chunk_predicts_what_one_block_does(models, monkeypatch) -> None:
    import estimator_service.gp.exact as exact

    gp = models["exact"]
    q = np.random.default_rng(9).uniform(-2, 2, (35, 2))
    whole = gp.predict(q, return_jac=True)
    monkeypatch.setattr(exact, "_CHUNK_BYTES", 8 * gp.output_dim * len(gp.x_train) * 10)  # 10 queries
    parts = gp.predict(q, return_jac=True)
    for a, b in ((parts.mean, whole.mean), (parts.var, whole.var), (parts.jac, whole.jac)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    assert gp.predict(q, return_var=False).var is None


@pytest.mark.parametrize("iterations", [1, 2])
def test_the_heteroscedastic_fit_runs_as_many_noise_rounds_as_asked(toy, iterations: int) -> None:
    """Each round refits the mean GP's hyperparameters under the new noise profile once per
    output: as many fresh ``hetero`` optimisations (iteration 1) as rounds."""
    x, y = toy
    seen = []
    fit_hetero(x[:40], y[:40, 0], iterations=iterations, restarts=1, max_iter=3, callback=seen.append)
    assert sum(s.model == "hetero" and s.iteration == 1 for s in seen) == iterations
    # the mean GP's first fit and each round's noise GP: one start each, as asked, reported
    assert sum(s.model == "exact" and s.iteration == 1 for s in seen) == 1 + iterations
    seen.clear()  # with a hyperparameter subset, each round's refit searches it, then polishes
    fit_hetero(x[:40], y[:40, 0], iterations=iterations, restarts=1, max_iter=3, hyper_points=20,
               polish_iter=2, callback=seen.append)  # fmt: skip
    assert sum(s.model == "hetero" and s.iteration == 1 for s in seen) == 2 * iterations


def test_a_heteroscedastic_fit_normalises_each_outputs_profile_and_needs_three_points(toy) -> None:
    """The mean GP's noise profile has geometric mean 1 per output (the homoscedastic noise
    carries each output's level), the fit without a generator is repeatable, and it needs 3
    points (2 are refused by name)."""
    x, y = toy
    y2 = np.c_[y[:60, 0], 50.0 * y[:60, 1] * (1.0 + np.abs(x[:60, 0]))]  # two noise shapes
    het = fit_hetero(x[:60], y2, iterations=1, restarts=1, max_iter=5, hyper_points=40)
    np.testing.assert_allclose(np.exp(np.log(het.main.noise_profile).mean(axis=1)), 1.0, rtol=1e-9)
    # the noise GP, shifted per output, gives back that profile at the training inputs
    level = np.exp(2 * het.main.theta[:, -1]) * het.main.y_scaler.std**2
    np.testing.assert_allclose(het.noise_var(x[:60]) / level, het.main.noise_profile.T, rtol=1e-9)
    again = fit_hetero(x[:60], y2, iterations=1, restarts=1, max_iter=5, hyper_points=40)
    np.testing.assert_array_equal(again.main.theta, het.main.theta)
    assert fit_hetero(x[:3], y[:3, 0], iterations=1, restarts=1, max_iter=2).main.alpha.shape == (1, 3)
    with pytest.raises(ValueError, match="at least 3"):
        fit_hetero(x[:2], y[:2, 0], iterations=1, restarts=1, max_iter=2)


def test_a_constant_column_is_centred_but_not_scaled() -> None:
    """A column whose spread is below 1e-12 of its magnitude keeps the unit scale (dividing
    by its rounding noise would blow it up); the others get their standard deviation."""
    v = np.c_[np.full(20, 3.0), np.full(20, 1e6) + 1e-9 * np.arange(20), np.arange(20.0)]
    sc = Scaler.fit(v)
    np.testing.assert_array_equal(sc.std[:2], [1.0, 1.0])
    np.testing.assert_allclose(sc.mean, v.mean(axis=0))
    assert sc.std[2] == pytest.approx(np.std(np.arange(20.0)))


def test_the_polish_on_all_points_reports_its_progress(toy) -> None:
    """With a hyperparameter subset, each output's search on the subset and its polish on all
    points both report: two optimisations starting at iteration 1."""
    x, y = toy
    seen = []
    fit_exact(x, y[:, 0], restarts=1, max_iter=3, hyper_points=30, polish_iter=3, callback=seen.append)
    assert sum(s.iteration == 1 for s in seen) == 2


def test_the_polish_on_all_points_searches_inside_the_same_bounds(toy, monkeypatch) -> None:
    """The polish is an L-BFGS-B search in the same box as the subset's search: its result
    stays inside the hyperparameter bounds (each search is given them)."""
    from estimator_service.gp import hyper

    x, y = toy
    real, boxes = hyper.optimize_theta, []

    def spy(objective, starts, bounds, *args):
        boxes.append(bounds)
        return real(objective, starts, bounds, *args)

    monkeypatch.setattr(hyper, "optimize_theta", spy)
    gp = fit_exact(x, y[:, 0], restarts=1, max_iter=3, hyper_points=30, polish_iter=3)
    box = hyper.theta_bounds(x.shape[1])
    assert boxes == [box, box]
    lo, hi = np.array(box).T
    assert np.all((lo <= gp.theta) & (gp.theta <= hi))


# --- the kernel blocks' vectorised exponential ---


def _ulps(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """``|got - want|`` in units of ``want``'s last place (0 where both are equal, inf or NaN)."""
    same = (got == want) | (np.isnan(got) & np.isnan(want))
    with np.errstate(invalid="ignore"):
        return np.where(same, 0.0, np.abs(got - want) / np.maximum(np.spacing(np.abs(want)), 5e-324))


def test_the_vectorised_exp_is_within_one_ulp_of_numpys_over_the_whole_range() -> None:
    """``exp_capped`` against NumPy's ``exp(minimum(a, cap))``: random exponents over the whole
    float64 range, the edges (subnormal results, the overflow threshold, infinities, NaN,
    -0), one cap per leading row; a strided array and a small block take NumPy's path and
    equal it exactly."""
    from estimator_service.gp.fastexp import VECTORISE_MIN, exp_capped, vectorised

    assert vectorised()  # numba is installed with the project's test extras: the compiled loop is tested
    rng = np.random.default_rng(3)
    edges = [-np.inf, -800.0, -745.2, -745.1, -740.0, -708.5, -1e-300, -0.0, 0.0, 1e-300, 1.0,
             709.78, 709.79, 710.0, np.inf, np.nan]  # fmt: skip
    a = np.concatenate([rng.uniform(-746.0, 709.8, 200_000), rng.uniform(-40, 3, 100_000), edges])
    with np.errstate(over="ignore"):
        want = np.exp(a)
        np.testing.assert_array_equal(_ulps(exp_capped(a.copy()), want) <= 1.0, True)
        rows = rng.uniform(-60, 8, (3, 80, 100))
        caps = np.array([-1.0, 0.5, 2.0])
        got = exp_capped(rows.copy(), caps)
        assert _ulps(got, np.exp(np.minimum(rows, caps[:, None, None]))).max() <= 1.0
        assert got[0].max() <= math.exp(-1.0) and got[2].max() > math.exp(0.5)
        fortran = np.asfortranarray(rows)
        assert not fortran.flags.c_contiguous
        np.testing.assert_array_equal(exp_capped(fortran.copy(order="F"), 0.5), np.exp(np.minimum(rows, 0.5)))
        small = rng.uniform(-60, 8, VECTORISE_MIN - 1)
        np.testing.assert_array_equal(exp_capped(small.copy(), 1.0), np.exp(np.minimum(small, 1.0)))
    for bad in (np.zeros(2), np.zeros((3, 1))):  # a cap per leading index, or one: nothing else
        with pytest.raises(ValueError, match="cap must be"):
            exp_capped(rows.copy(), bad)
    with pytest.raises(ValueError, match="cap must be"):  # a single number has no leading index
        exp_capped(np.array(0.5), np.zeros(1))
    assert exp_capped(np.array(2.0), 1.0) == math.e  # a single number, capped
    line = np.array([-1.0, 0.0, 1.0])  # a 1-D array: one cap per element
    np.testing.assert_array_equal(
        exp_capped(line.copy(), np.array([0.0, 0.5, 2.0])), np.exp([-1.0, 0.0, 1.0])
    )


def test_blocks_from_the_size_threshold_on_take_the_compiled_loop(monkeypatch) -> None:
    """The compiled loop gets every C-contiguous float64 block of ``VECTORISE_MIN`` elements or
    more, the threshold itself included, and no smaller one (the values alone cannot tell:
    both paths are within 1 ulp)."""
    from estimator_service.gp import fastexp

    loop, sizes = fastexp._compiled(), []
    assert loop is not None

    def counted(rows: np.ndarray, caps: np.ndarray) -> None:
        sizes.append(rows.size)
        loop(rows, caps)

    monkeypatch.setattr(fastexp, "_loaded", counted)
    for size in (fastexp.VECTORISE_MIN - 1, fastexp.VECTORISE_MIN, fastexp.VECTORISE_MIN + 1):
        a = np.linspace(-5.0, 1.0, size)
        np.testing.assert_allclose(fastexp.exp_capped(a.copy(), 0.5), np.exp(np.minimum(a, 0.5)), rtol=3e-16)
    assert sizes == [fastexp.VECTORISE_MIN, fastexp.VECTORISE_MIN + 1]  # an odd size is one row


def test_a_failed_import_of_the_compiled_loop_leaves_numpys_exp(monkeypatch) -> None:
    """In this process (the subprocess test below covers a real install without numba): where
    the compiled loop cannot be imported, ``vectorised`` says so and large blocks are NumPy's
    ``exp``, exactly."""
    import sys

    from estimator_service.gp import fastexp

    monkeypatch.setitem(sys.modules, "estimator_service.gp.fastexp_kernel", None)  # import fails
    monkeypatch.setattr(fastexp, "_loaded", fastexp._UNLOADED)
    assert fastexp.vectorised() is False
    a = np.random.default_rng(0).uniform(-50.0, 5.0, 2 * fastexp.VECTORISE_MIN)
    np.testing.assert_array_equal(fastexp.exp_capped(a.copy(), 1.0), np.exp(np.minimum(a, 1.0)))


def test_without_numba_the_exp_is_numpys() -> None:
    """Where numba is missing (the estimator alone) ``exp_capped`` is NumPy's ``minimum`` and
    ``exp``, exactly."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['numba'] = None\n"
        "import numpy as np\n"
        "from estimator_service.gp.fastexp import exp_capped, vectorised\n"
        "a = np.random.default_rng(0).uniform(-50, 5, (2, 30000))\n"
        "got = exp_capped(a.copy(), np.array([0.0, 1.0]))\n"
        "want = np.exp(np.minimum(a, np.array([[0.0], [1.0]])))\n"
        "print(vectorised(), np.array_equal(got, want))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.split() == ["False", "True"]
