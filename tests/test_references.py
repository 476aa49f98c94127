"""Equations against outside references: the unscented transform's published weights and
the exact moments of a quadratic, the UKF's observation noise at the mean, the exact GP's
variance output by output with distinct hyperparameters against a dense solve, and the
divergence flag and the service's gate at their chi-square quantiles."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.stats import chi2, norm

from estimator_service.filters import PF, UKF, GaussianBelief, ParticleBelief, systematic_resample
from estimator_service.filters.batched import implausible_many
from estimator_service.filters.common import StepInfo, implausible
from estimator_service.filters.kalman import sigma_weights, unscented_transform
from estimator_service.gp.base import Scaler
from estimator_service.gp.exact import STACKED_MAX_QUERIES, ExactGP
from estimator_service.gp.kernel import split_theta
from estimator_service.models.base import LinearGaussianObservation, LinearGaussianPrediction, ModelOutput
from estimator_service.service.limits import gated


@pytest.mark.parametrize(
    ("n", "alpha", "beta", "kappa", "wm0", "wc0", "wi", "gamma"),
    [
        # Wan & van der Merwe (2000), eq. 15: lambda = alpha^2 (n + kappa) - n,
        # Wm0 = lambda / (n + lambda), Wc0 = Wm0 + 1 - alpha^2 + beta, Wi = 1 / (2 (n + lambda)),
        # worked by hand for these settings
        (2, 1.0, 2.0, 0.0, 0.0, 2.0, 0.25, 2**0.5),
        (3, 0.5, 2.0, 1.0, -2.0, 0.75, 0.5, 1.0),
        (1, 1.0, 0.0, 2.0, 2 / 3, 2 / 3, 1 / 6, 3**0.5),
        (12, 1e-3, 2.0, 0.0, 1 - 1e6, 1 - 1e6 + 3 - 1e-6, 1 / (2 * 12e-6), 12**0.5 * 1e-3),
    ],
)
def test_sigma_weights_are_the_published_ones(n, alpha, beta, kappa, wm0, wc0, wi, gamma) -> None:
    wm, wc, g = sigma_weights(n, alpha, beta, kappa)
    assert wm[0] == pytest.approx(wm0, rel=1e-9, abs=1e-12)
    assert wc[0] == pytest.approx(wc0, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(wm[1:], wi, rtol=1e-9)
    np.testing.assert_allclose(wc[1:], wi, rtol=1e-9)
    assert g == pytest.approx(gamma, rel=1e-9)


@dataclass(frozen=True)
class Square:
    """``x' = x^2`` (a change of ``x^2 - x``), no noise: moments known in closed form."""

    state_dim: int = 1
    control_dim: int = 1

    def predict(self, x, u, *, jac=False, var=True) -> ModelOutput:
        return ModelOutput(x * x - x, np.zeros_like(x), 2 * x[:, :, None] - 1 if jac else None)


@pytest.mark.parametrize(("beta", "kappa"), [(0.0, 2.0), (2.0, 2.0), (2.0, 0.0), (0.0, 0.5)])
def test_the_unscented_prediction_of_a_square_has_its_closed_form_moments(beta, kappa) -> None:
    """For ``y = x^2``, ``x ~ N(m, s^2)``, the transform's mean is exact, ``m^2 + s^2``, for any
    weights, and its variance is ``4 m^2 s^2 + (n + lambda - 1 + beta + 1 - alpha^2) s^4``
    (worked from the sigma points; the true ``4 m^2 s^2 + 2 s^4`` at ``kappa = 2``, ``beta = 0``)."""
    m, s2, alpha, n = 0.7, 0.3, 1.0, 1
    ukf = UKF(Square(), LinearGaussianObservation(np.eye(1), np.ones(1)), alpha=alpha, beta=beta, kappa=kappa)
    prior = ukf.predict(GaussianBelief(np.array([m]), np.array([[s2]])), np.zeros(1), None)
    lam = alpha**2 * (n + kappa) - n
    assert prior.mean[0] == pytest.approx(m * m + s2, rel=1e-12)
    expected = 4 * m * m * s2 + (n + lam - 1 + beta + 1 - alpha**2) * s2 * s2
    assert prior.cov[0, 0] == pytest.approx(expected, rel=1e-10)
    if (beta, kappa) == (0.0, 2.0):
        assert prior.cov[0, 0] == pytest.approx(4 * m * m * s2 + 2 * s2 * s2, rel=1e-10)


@pytest.mark.parametrize(("alpha", "beta", "kappa"), [(1.0, 2.0, 0.0), (1e-2, 2.0, 1.0), (0.5, 0.0, 3.0)])
def test_the_unscented_transform_of_an_affine_map_is_exact(alpha, beta, kappa) -> None:
    """``y = A x + b``, ``x ~ N(m, P)``: mean ``A m + b`` and covariance ``A P A^T`` for any
    weights, and with an angle component the same moments across its cut at +-pi."""
    rng = np.random.default_rng(3)
    n, d = 3, 2
    m, g = rng.normal(size=n), rng.normal(size=(n, n))
    p, a, b = g @ g.T + 0.1 * np.eye(n), rng.normal(size=(d, n)), rng.normal(size=d)
    wm, wc, gamma = sigma_weights(n, alpha, beta, kappa)
    l = np.linalg.cholesky(p)
    xs = np.concatenate([m[None], m + gamma * l.T, m - gamma * l.T])
    mean, dev, cov = unscented_transform(xs @ a.T + b, wm, wc, np.zeros(d))
    np.testing.assert_allclose(mean, a @ m + b, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(cov, a @ p @ a.T, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(dev, xs @ a.T + b - mean, rtol=1e-9, atol=1e-9)
    shift = np.array([np.pi - (a @ m + b)[0] + 0.01, 0.0])  # the mean sits 0.01 past +pi
    ys = np.array([1.0, 0.0]) * np.angle(np.exp(1j * (xs @ a.T + b + shift)[:, :1])) + [0, 1] * (xs @ a.T + b)
    mean2, _, cov2 = unscented_transform(ys, wm, wc, np.array([2 * np.pi, 0.0]))
    assert mean2[0] == pytest.approx(-np.pi + 0.01, abs=1e-9) and mean2[1] == pytest.approx((a @ m + b)[1])
    np.testing.assert_allclose(cov2, cov, rtol=1e-7, atol=1e-9)


@dataclass(frozen=True)
class StateDependentNoise:
    """``z = x_0`` with noise variance ``0.01 + x_0^2``."""

    state_dim: int = 2
    obs_dim: int = 1

    def observe(self, x, *, jac=False, var=True) -> ModelOutput:
        j = np.broadcast_to(np.array([[1.0, 0.0]]), (len(x), 1, 2)) if jac else None
        return ModelOutput(x[:, :1].copy(), 0.01 + x[:, :1] ** 2, j)


def test_the_ukf_takes_the_observation_noise_at_the_mean() -> None:
    """``noise="mean"`` (the paper's): a linear observation's update is the Kalman update with
    ``R`` at the prior mean, not at any other sigma point."""
    ukf = UKF(Square(state_dim=2), StateDependentNoise(), noise="mean")
    prior = GaussianBelief(np.array([0.8, -0.3]), np.array([[0.5, 0.1], [0.1, 0.4]]))
    post, _ = ukf.update(prior, np.array([1.1]), np.array([True]), None)
    s = prior.cov[0, 0] + 0.01 + 0.8**2
    gain = prior.cov[:, 0] / s
    np.testing.assert_allclose(post.mean, prior.mean + gain * (1.1 - 0.8), rtol=1e-10)
    np.testing.assert_allclose(post.cov, prior.cov - np.outer(gain, gain) * s, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("queries", [5, STACKED_MAX_QUERIES + 9])
def test_exact_gp_variances_per_output_against_a_dense_solve(queries: int) -> None:
    """Three outputs with distinct length scales, signal and noise variances, on both
    prediction paths (all outputs stacked, and output by output beyond
    ``STACKED_MAX_QUERIES``), against ``sf2 - k^T (K + sn2 I)^-1 k + sn2`` by ``numpy.linalg``."""
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-2, 2, size=(40, 2)), rng.normal(size=(40, 3))
    theta = np.log([[0.7, 1.5, 1.0, 0.1], [1.9, 0.4, 2.5, 0.3], [1.1, 1.1, 0.4, 0.02]])
    xsc, ysc = (
        Scaler(np.array([0.1, -0.2]), np.array([1.3, 0.8])),
        Scaler(np.zeros(3), np.array([1.0, 2.0, 0.5])),
    )
    gp = ExactGP.from_theta(xsc.apply(x), ysc.apply(y), theta, xsc, ysc)
    q = rng.uniform(-2, 2, size=(queries, 2))
    out = gp.predict(q, return_var=True)
    xs, qs = xsc.apply(x), xsc.apply(q)
    for p in range(3):
        ell, sf2, sn2 = split_theta(theta[p])

        def k(a, b, ell=ell, sf2=sf2):
            return sf2 * np.exp(-0.5 * (((a[:, None, :] - b[None, :, :]) / ell) ** 2).sum(-1))

        kxx = k(xs, xs) + sn2 * np.eye(len(xs))
        kq = k(xs, qs)
        var = sf2 - np.einsum("ij,ij->j", kq, np.linalg.solve(kxx, kq)) + sn2
        np.testing.assert_allclose(out.var[:, p], var * ysc.std[p] ** 2, rtol=1e-8)
        mean = kq.T @ np.linalg.solve(kxx, ysc.apply(y)[:, p])
        np.testing.assert_allclose(out.mean[:, p], mean * ysc.std[p] + ysc.mean[p], rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("dof", [1, 3, 10])
def test_divergence_flag_sits_at_its_chi_square_quantile(dof: int) -> None:
    """A NIS flags divergence exactly where its chi-square tail probability falls below
    ``DIVERGENCE_P`` (1e-9): just below the quantile not, just above yes, on the single and
    the batched path."""
    edge = chi2.isf(1e-9, dof)
    nis = np.array([edge * (1 - 1e-6), edge * (1 + 1e-6)])
    assert [implausible(float(v), dof) for v in nis] == [False, True]
    np.testing.assert_array_equal(implausible_many(nis, dof), [False, True])


@pytest.mark.parametrize(("gate_p", "dof"), [(1e-3, 1), (1e-6, 4), (0.05, 10)])
def test_the_service_gate_sits_at_its_chi_square_quantile(gate_p: float, dof: int) -> None:
    edge = chi2.isf(gate_p, dof)
    assert not gated(StepInfo(edge * (1 - 1e-9), dof), gate_p)
    assert gated(StepInfo(edge * (1 + 1e-9), dof), gate_p)
    assert not gated(StepInfo(1e300, dof), 0.0)  # a gate of 0 is off


def test_one_angle_rule_in_the_estimator_the_filters_and_the_simulator() -> None:
    """Every angle is wrapped into [-p/2, p/2): the estimator's rule, the filters' wrapping
    (state values, state and observation differences) and the simulator's compiled kernel give
    the same numbers, the edges included (+p/2 maps to -p/2)."""
    from estimator_service.angles import wrap_angle
    from estimator_service.filters import Wrapping
    from gpbf_env.dynamics import wrap_angle as sim_wrap

    pi = np.pi
    a = np.array([pi, -pi, 3 * pi, -3 * pi, 0.0, -0.0, 1e-17, -1e-17, pi - 1e-15, 7.5, -7.5, 1e6, -1e6])
    ours = wrap_angle(a)
    assert np.all((ours >= -pi) & (ours < pi))
    assert ours[0] == -pi and ours[1] == -pi and ours[2] == -pi and ours[3] == -pi
    np.testing.assert_array_equal(ours, sim_wrap(a))  # the kernel on an array
    np.testing.assert_array_equal(ours, [sim_wrap(float(v)) for v in a])  # and one float at a time
    w = Wrapping(np.array([0.0, 2 * pi, pi]), np.array([2 * pi]))
    x = np.stack([a, a, a], axis=1)
    expect = np.stack([a, ours, wrap_angle(a, pi)], axis=1)
    np.testing.assert_array_equal(w.state_value(x), expect)
    np.testing.assert_array_equal(w.state_diff(x), expect)
    np.testing.assert_array_equal(w.obs_diff(a[:, None]), ours[:, None])
    half = wrap_angle(np.array([pi / 2, -pi / 2]), pi)  # period pi: [-pi/2, pi/2)
    np.testing.assert_array_equal(half, [-pi / 2, -pi / 2])
    z = wrap_angle(np.array([3 * pi + 1e-20j]))  # complex step: the derivative passes through
    assert z[0].imag == 1e-20 and z[0].real == -pi


@dataclass(frozen=True)
class BlindBeyond:
    """``z = x_0`` with noise variance ``0.01 + x_0^2``; a sensor that cannot see past
    ``x_0 = 5`` (infinite variance there)."""

    state_dim: int = 1
    obs_dim: int = 1

    def observe(self, x, *, jac=False, var=True) -> ModelOutput:
        v = np.where(x[:, :1] > 5.0, np.inf, 0.01 + x[:, :1] ** 2)
        return ModelOutput(x[:, :1].copy(), v, None)


def _pf(**options) -> PF:
    pred = LinearGaussianPrediction(np.eye(1), np.zeros((1, 1)), np.array([0.04]))
    return PF(pred, BlindBeyond(), **{"n_particles": 5, "resample_below": 0.0, **options})


def test_particle_weights_are_the_exact_gaussian_likelihoods() -> None:
    """Steps 5-7 of Table 1 with state-dependent noise: each log-weight gains the normal
    log-density of the reading (its normalising constant differs per particle), a particle
    the sensor cannot see gets weight 0; the NIS is that of the weighted predicted readings
    (``S = sum w (z_m - zhat)^2 + sum w var_m``), the ESS ``1 / sum w^2``."""
    x = np.array([[-0.4], [0.1], [0.3], [0.9], [6.0]])
    logw0 = np.log(np.array([0.1, 0.3, 0.2, 0.15, 0.25]))
    prior, z = ParticleBelief(x, logw0), np.array([0.25])
    post, info = _pf().update(prior, z, np.array([True]), np.random.default_rng(0))
    v = 0.01 + x[:, 0] ** 2
    expected = logw0 + norm.logpdf(z[0], x[:, 0], np.sqrt(v))
    expected[4] = -np.inf
    expected -= np.logaddexp.reduce(expected)
    np.testing.assert_allclose(post.log_weights, expected, rtol=1e-12)
    assert info.diverged is not None and not info.diverged and info.resampled is False
    assert info.ess == pytest.approx(1.0 / np.sum(np.exp(expected) ** 2), rel=1e-12)
    seen = ParticleBelief(x[:4], logw0[:4] - np.logaddexp.reduce(logw0[:4]))  # all visible: finite S
    info_seen = _pf().update(seen, z, np.array([True]), np.random.default_rng(0))[1]
    w0 = seen.weights
    zhat = w0 @ x[:4, 0]
    s = w0 @ (x[:4, 0] - zhat) ** 2 + w0 @ v[:4]
    assert info_seen.nis == pytest.approx((z[0] - zhat) ** 2 / s, rel=1e-12) and info_seen.dof == 1
    again, info2 = _pf().update(prior, z, None, np.random.default_rng(0))  # valid None: every entry
    np.testing.assert_array_equal(again.log_weights, post.log_weights)
    assert info2.nis == info.nis and info2.ess == info.ess
    same, info3 = _pf().update(prior, z, np.array([False]), np.random.default_rng(0))
    assert same is prior and info3.dof == 0 and info3.ess == pytest.approx(prior.ess)


def test_a_reading_no_particle_can_explain_leaves_the_prior_and_says_so() -> None:
    prior = ParticleBelief(np.array([[6.0], [7.0], [8.0]]), np.log(np.array([0.5, 0.3, 0.2])))
    post, info = _pf(n_particles=3).update(prior, np.array([0.2]), np.array([True]), np.random.default_rng(0))
    assert post is prior and info.diverged is True and info.dof == 1 and info.resampled is False
    assert info.ess == pytest.approx(prior.ess) and info.nis == pytest.approx(0.0)  # S is infinite


def test_process_noise_and_roughening_are_the_generators_draws_scaled_as_documented() -> None:
    """Step 4 (``x + mu + sqrt(var) e``) and the regularised resampling (``x + h L e`` with
    Silverman's ``h = roughen (4 / (M (n + 2)))^(1 / (n + 4))``, ``L L^T`` the weighted
    covariance), against the same generator's draws made by hand."""
    m = 64
    x = np.linspace(-1.0, 1.0, m)[:, None]
    prior = ParticleBelief(x, np.full(m, -np.log(m)))
    pf = PF(
        LinearGaussianPrediction(np.eye(1), np.ones((1, 1)), np.array([0.04])),
        LinearGaussianObservation(np.zeros((1, 1)), np.ones(1)),  # reads nothing of the state
        n_particles=m, resample_below=2.0, roughen=0.7,
    )  # fmt: skip
    moved = pf.predict(prior, np.array([0.5]), np.random.default_rng(1))
    e = np.random.default_rng(1).standard_normal((m, 1))
    np.testing.assert_allclose(moved.particles, x + 0.5 + 0.2 * e, rtol=1e-12)
    post, info = pf.update(prior, np.array([0.0]), np.array([True]), np.random.default_rng(2))
    assert info.resampled is True and info.ess == pytest.approx(m)
    gen = np.random.default_rng(2)
    gen.random()  # the systematic resampling's one draw: equal weights keep every particle once
    h = 0.7 * (4.0 / (m * 3)) ** (1.0 / 5)
    sd = np.sqrt(np.mean((x - x.mean()) ** 2))
    np.testing.assert_allclose(post.particles, x + h * sd * gen.standard_normal((m, 1)), rtol=1e-10)


@pytest.mark.parametrize("seed", range(5))
def test_systematic_resampling_keeps_each_particle_floor_or_ceil_of_m_w_times(seed: int) -> None:
    """Low-variance resampling (Thrun et al. 2005, Table 4.4): particle ``i`` is drawn
    ``floor(M w_i)`` or ``ceil(M w_i)`` times, the counts sum to ``M``."""
    rng = np.random.default_rng(seed)
    w = rng.dirichlet(np.full(7, 0.5))
    counts = np.bincount(systematic_resample(w, rng), minlength=7)
    assert counts.sum() == 7
    assert np.all(counts >= np.floor(7 * w) - 1e-9) and np.all(counts <= np.ceil(7 * w) + 1e-9)


@pytest.mark.parametrize("method", ["initial", "predict", "update", "step"])
def test_every_particle_filter_method_names_itself_when_its_generator_is_missing(method: str) -> None:
    pf, belief = _pf(n_particles=3), ParticleBelief(np.zeros((3, 1)), np.full(3, -np.log(3)))
    call = {
        "initial": lambda: pf.initial(GaussianBelief(np.zeros(1), np.eye(1))),
        "predict": lambda: pf.predict(belief, np.zeros(1)),
        "update": lambda: pf.update(belief, np.zeros(1)),
        "step": lambda: pf.step(belief, np.zeros(1)),
    }[method]
    with pytest.raises(
        TypeError, match=rf"^PF\.{method}: 'rng' must be a numpy.random.Generator, got NoneType"
    ):
        call()
