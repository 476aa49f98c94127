"""Filters vs the closed-form Kalman filter, unscented weights, angles, robustness."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from estimator_service.filters import (
    EKF,
    PF,
    UKF,
    GaussianBelief,
    ParticleBelief,
    Wrapping,
    sigma_weights,
    step_many,
    systematic_resample,
)
from estimator_service.models import (
    LinearGaussianObservation,
    LinearGaussianPrediction,
    ModelOutput,
)

DT = 0.25
A = np.array([[1, 0, DT, 0], [0, 1, 0, DT], [0, 0, 0.95, 0], [0, 0, 0, 0.9]])
B = np.array([[0, 0], [0, 0], [DT, 0], [0, DT]])
Q = np.array([1e-3, 2e-3, 1e-2, 2e-2])
H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [1.0, 1.0, 0, 0]])
R = np.array([0.05, 0.08, 0.1])
PRED = LinearGaussianPrediction(A, B, Q)
OBS = LinearGaussianObservation(H, R)
PRIOR = GaussianBelief(np.array([0.5, -0.2, 0.1, 0.0]), np.diag([0.3, 0.3, 0.1, 0.1]))


def kalman(mean, cov, u, z, valid, noise=R):
    mean, cov = A @ mean + B @ u, A @ cov @ A.T + np.diag(Q)
    idx = np.flatnonzero(valid)
    if idx.size:
        h, r = H[idx], np.diag(noise[idx])
        s = h @ cov @ h.T + r
        k = cov @ h.T @ np.linalg.inv(s)
        mean = mean + k @ (z[idx] - h @ mean)
        cov = (np.eye(4) - k @ h) @ cov
    return mean, cov


def scenario(steps: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = PRIOR.mean.copy()
    for k in range(steps):
        u = rng.normal(size=2)
        x = A @ x + B @ u + rng.normal(size=4) * np.sqrt(Q)
        z = H @ x + rng.normal(size=3) * np.sqrt(R)
        valid = rng.random(3) < 0.6 if k % 5 else np.zeros(3, bool)  # subsets and none
        yield u, z, valid


@pytest.mark.parametrize("make", [lambda: EKF(PRED, OBS), lambda: UKF(PRED, OBS)])
def test_ekf_and_ukf_equal_kalman_filter_on_linear_gaussian_system(make) -> None:
    filt = make()
    belief, mean, cov = PRIOR, PRIOR.mean, PRIOR.cov
    for u, z, valid in scenario(60):
        belief, info = filt.step(belief, u, z, valid)
        mean, cov = kalman(mean, cov, u, z, valid)
        np.testing.assert_allclose(belief.mean, mean, atol=1e-9)
        np.testing.assert_allclose(belief.cov, cov, atol=1e-9)
        assert info.dof == valid.sum() and not info.diverged
        assert math.isnan(info.nis) == (valid.sum() == 0)


def test_particle_filter_matches_kalman_within_monte_carlo_error() -> None:
    pf = PF(PRED, OBS, n_particles=20000, resample_below=0.5)
    rng = np.random.default_rng(3)
    belief = pf.initial(PRIOR, rng)
    mean, cov = PRIOR.mean, PRIOR.cov
    for u, z, valid in scenario(15, seed=1):
        belief, info = pf.step(belief, u, z, valid, rng)
        mean, cov = kalman(mean, cov, u, z, valid)
    g = pf.gaussian(belief)
    se = np.sqrt(np.diag(cov) / info.ess)
    assert np.all(np.abs(g.mean - mean) < 5 * se + 1e-3)
    np.testing.assert_allclose(np.diag(g.cov), np.diag(cov), rtol=0.15)


def test_particle_filter_is_seeded_deterministic() -> None:
    pf = PF(PRED, OBS, n_particles=500)
    runs = []
    for _ in range(2):
        rng = np.random.default_rng(42)
        b = pf.initial(PRIOR, rng)
        for u, z, valid in scenario(10):
            b, _ = pf.step(b, u, z, valid, rng)
        runs.append(b)
    np.testing.assert_array_equal(runs[0].particles, runs[1].particles)
    np.testing.assert_array_equal(runs[0].log_weights, runs[1].log_weights)


@pytest.mark.parametrize("n", [1, 4, 12])
def test_sigma_points_reproduce_mean_and_covariance(n: int) -> None:
    rng = np.random.default_rng(n)
    a = rng.normal(size=(n, n))
    belief = GaussianBelief(rng.normal(size=n), a @ a.T + np.eye(n))
    pred = LinearGaussianPrediction(np.eye(n), np.zeros((n, 1)), np.ones(n))
    ukf = UKF(pred, LinearGaussianObservation(np.eye(n), np.ones(n)))
    wm, wc, _ = sigma_weights(n, ukf.alpha, ukf.beta, ukf.kappa)
    assert wm.sum() == pytest.approx(1.0, abs=1e-9)
    x = ukf.sigma_points(belief)
    np.testing.assert_allclose(wm @ x, belief.mean, atol=1e-8)
    dev = x - belief.mean
    np.testing.assert_allclose((dev * wc[:, None]).T @ dev, belief.cov, rtol=1e-6, atol=1e-8)


@dataclass(frozen=True)
class AngleObs:
    """Observes a state angle directly (first component)."""

    state_dim: int = 2
    obs_dim: int = 1
    r: float = 0.01

    def observe(self, x, *, jac=False, var=True):
        j = np.broadcast_to(np.array([[1.0, 0.0]]), (len(x), 1, 2)) if jac else None
        return ModelOutput(x[:, :1].copy(), np.full((len(x), 1), self.r), j)


@pytest.mark.parametrize("kind", ["ekf", "ukf", "pf"])
@pytest.mark.parametrize("period", [2 * math.pi, math.pi])
def test_angle_wrap_around_gives_small_innovations(kind: str, period: float) -> None:
    """Yaw crossing pi (period 2 pi) and ellipse angle crossing pi/2 (period pi)."""
    edge = period / 2
    pred = LinearGaussianPrediction(np.eye(2), np.zeros((2, 1)), np.array([1e-4, 1e-4]))
    wrap = Wrapping(np.array([period, 0.0]), np.array([period]))
    prior = GaussianBelief(np.array([edge - 0.02, 0.0]), np.diag([0.01, 0.01]))
    z = np.array([-edge + 0.02])  # 0.04 away across the wrap
    if kind == "pf":
        pf, rng = PF(pred, AngleObs(), wrap, n_particles=4000), np.random.default_rng(0)
        post, info = pf.step(pf.initial(prior, rng), np.zeros(1), z, None, rng)
        mean = pf.gaussian(post).mean
    else:
        filt = (EKF if kind == "ekf" else UKF)(pred, AngleObs(), wrap)
        post, info = filt.step(prior, np.zeros(1), z, None)
        mean = post.mean
    assert info.nis < 1.0 and not info.diverged
    err = (mean[0] - edge + period / 2) % period - period / 2  # distance to the wrap point
    assert abs(err) < 0.03


def test_missing_camera_steps_only_predict() -> None:
    for filt in (EKF(PRED, OBS), UKF(PRED, OBS)):
        pred_only = filt.predict(PRIOR, np.ones(2))
        post, info = filt.step(PRIOR, np.ones(2), np.zeros(3), np.zeros(3, bool))
        np.testing.assert_array_equal(post.mean, pred_only.mean)
        assert math.isnan(info.nis) and info.dof == 0


@dataclass(frozen=True)
class Pendulum:
    state_dim: int = 2
    control_dim: int = 1

    def predict(self, x, u, *, jac=False, var=True):
        th, w = x[:, 0], x[:, 1]
        change = np.stack([DT * w, DT * (-9.81 * np.sin(th) - 0.3 * w + u[0])], axis=1)
        j = None
        if jac:
            j = np.zeros((len(x), 2, 2))
            j[:, 0, 1] = DT
            j[:, 1, 0] = -DT * 9.81 * np.cos(th)
            j[:, 1, 1] = -0.3 * DT
        return ModelOutput(change, np.full(change.shape, 1e-4), j)


@dataclass(frozen=True)
class SinObs:
    state_dim: int = 2
    obs_dim: int = 2

    def observe(self, x, *, jac=False, var=True):
        z = np.stack([np.sin(x[:, 0]), x[:, 1] ** 2], axis=1)
        j = None
        if jac:
            j = np.zeros((len(x), 2, 2))
            j[:, 0, 0] = np.cos(x[:, 0])
            j[:, 1, 1] = 2 * x[:, 1]
        return ModelOutput(z, np.full(z.shape, 1e-2), j)


@pytest.mark.parametrize("cls", [EKF, UKF])
@pytest.mark.slow
def test_covariance_stays_positive_definite_over_10000_steps(cls) -> None:
    filt = cls(Pendulum(), SinObs())
    rng = np.random.default_rng(0)
    belief = GaussianBelief(np.array([0.3, 0.0]), np.eye(2) * 0.1)
    x = np.array([0.5, 0.0])
    for k in range(10_000):
        u = np.array([2.0 * math.sin(0.01 * k)])
        x = x + Pendulum().predict(x[None], u).mean[0] + rng.normal(size=2) * 1e-2
        z = SinObs().observe(x[None]).mean[0] + rng.normal(size=2) * 0.1
        belief, _ = filt.step(belief, u, z, np.array([k % 3 == 0, k % 2 == 0]))
        assert np.all(np.isfinite(belief.mean))
        np.testing.assert_array_equal(belief.cov, belief.cov.T)
        assert np.linalg.eigvalsh(belief.cov)[0] > 0


@dataclass(frozen=True)
class BrokenObs:
    state_dim: int = 4
    obs_dim: int = 3

    def observe(self, x, *, jac=False, var=True):
        nan = np.full((len(x), 3), np.nan)
        return ModelOutput(nan, nan, np.full((len(x), 3, 4), np.nan) if jac else None)


@pytest.mark.parametrize("kind", ["ekf", "ukf", "pf"])
def test_divergence_is_flagged_not_returned_as_nan(kind: str) -> None:
    z = np.zeros(3)
    if kind == "pf":
        pf, rng = PF(PRED, BrokenObs(), n_particles=100), np.random.default_rng(0)
        post, info = pf.step(pf.initial(PRIOR, rng), np.zeros(2), z, None, rng)
        assert np.all(np.isfinite(post.particles)) and np.all(np.isfinite(post.log_weights))
    else:
        filt = (EKF if kind == "ekf" else UKF)(PRED, BrokenObs())
        post, info = filt.step(PRIOR, np.zeros(2), z, None)
        assert np.all(np.isfinite(post.mean)) and np.all(np.isfinite(post.cov))
    assert info.diverged


@dataclass(frozen=True)
class BrokenPrediction:
    """A prediction model that overflows (a model queried far outside its data)."""

    state_dim: int = 4
    control_dim: int = 2

    def predict(self, x, u, *, jac=False, var=True):
        inf = np.full(x.shape, np.inf)
        return ModelOutput(inf, np.ones(x.shape), np.full((*x.shape, 4), np.inf) if jac else None)


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_non_finite_prediction_keeps_the_belief_and_flags_divergence(cls) -> None:
    filt = cls(BrokenPrediction(), OBS)
    post, info = filt.step(PRIOR, np.zeros(2), np.zeros(3), None)
    assert info.diverged and post is PRIOR
    again, info2 = filt.step(post, np.zeros(2), np.zeros(3), None)  # and the next step too
    assert info2.diverged and np.all(np.isfinite(again.cov))
    (b, i), (_, i2) = step_many(
        filt, [PRIOR, PRIOR], np.zeros((2, 2)), np.zeros((2, 3)), np.ones((2, 3), bool)
    )
    assert i.diverged and i2.diverged and b is PRIOR


@dataclass(frozen=True)
class NaNRefusing:
    """A model that refuses non-finite queries, as the GPs do (``check_query``)."""

    inner: object

    def __getattr__(self, name: str):
        return getattr(self.inner, name)

    def predict(self, x, u, **kw):
        if not np.isfinite(x).all():
            raise ValueError("query contains NaN or Inf")
        return self.inner.predict(x, u, **kw)

    def observe(self, x, **kw):
        if not np.isfinite(x).all():
            raise ValueError("query contains NaN or Inf")
        return self.inner.observe(x, **kw)


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_a_covariance_that_cannot_be_factored_is_flagged_not_raised(cls) -> None:
    """A belief blown up to huge, indefinite entries (as a diverging calibration run
    produced): the step flags divergence instead of raising ``LinAlgError`` (the UKF's
    sigma points need a factor; the EKF refuses the update), and a batch mate is
    unaffected."""
    cov = np.eye(4)
    cov[:2, :2] = [[1e200, 1e200], [1e200, -1e200]]  # no eigenvalue floor makes it factorable
    blown = GaussianBelief(PRIOR.mean, cov)
    filt = cls(NaNRefusing(PRED), NaNRefusing(OBS))  # no model is asked about NaN
    post, info = filt.step(blown, np.zeros(2), np.zeros(3), None)
    assert info.diverged and np.isfinite(post.mean).all()  # the belief or its prediction
    post, info = filt.update(blown, np.zeros(3))  # an update alone is refused the same way
    assert info.diverged and post is blown
    (b, i), (good, i2) = step_many(
        filt, [blown, PRIOR], np.zeros((2, 2)), np.zeros((2, 3)), np.ones((2, 3), bool)
    )
    assert i.diverged and np.isfinite(b.mean).all() and not i2.diverged
    ref, _ = filt.step(PRIOR, np.zeros(2), np.zeros(3), None)
    np.testing.assert_allclose(good.mean, ref.mean, rtol=1e-12, atol=1e-12)


@dataclass(frozen=True)
class BrokenWhere:
    """A prediction model that overflows where the control's first entry exceeds 1 (one
    blimp of a batch flown far outside the model's data)."""

    inner: object

    def __getattr__(self, name: str):
        return getattr(self.inner, name)

    def predict(self, x, u, *, jac=False, var=True):
        out = self.inner.predict(x, u, jac=jac, var=var)
        bad = np.broadcast_to(np.atleast_2d(u)[:, :1] > 1, out.mean.shape)
        return ModelOutput(np.where(bad, np.inf, out.mean), out.var, out.jac)


@pytest.mark.parametrize("kind", ["ekf", "ukf", "pf"])
def test_step_policy_does_not_depend_on_the_batch(kind: str) -> None:
    """One policy: each belief's step (a non-finite prediction kept and flagged, a gated
    update refused, a plain update, a prediction without readings) is the same alone and in a
    batch with the others, for the batched Kalman filters and the per-belief particle filter."""
    pred = BrokenWhere(PRED)
    filt = {"ekf": EKF(pred, OBS), "ukf": UKF(pred, OBS), "pf": PF(pred, OBS, n_particles=200)}[kind]
    start = filt.initial(PRIOR, np.random.default_rng(0))
    u = np.array([[5.0, 0.0], [0.1, 0.0], [0.1, 0.0], [0.1, 0.0]])  # row 0: non-finite prediction
    z = np.array([[0.0, 0.0, 0.0], [50.0, -50.0, 0.0], [0.1, 0.2, 0.0], [0.0, 0.0, 0.0]])  # row 1: gated
    valid = np.array([[True] * 3, [True] * 3, [True] * 3, [False] * 3])  # row 3: nothing read

    def gate(info):
        return info.nis > 100.0

    together = step_many(filt, [start] * 4, u, z, valid, gate, [np.random.default_rng(i) for i in range(4)])
    alone = [step_many(filt, [start], u[i : i + 1], z[i : i + 1], valid[i : i + 1], gate,
                       np.random.default_rng(i))[0] for i in range(4)]  # fmt: skip
    for (b1, i1), (b2, i2) in zip(together, alone, strict=True):
        g1, g2 = filt.gaussian(b1), filt.gaussian(b2)
        np.testing.assert_allclose(g1.mean, g2.mean, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(g1.cov, g2.cov, rtol=1e-10, atol=1e-12)
        assert (i1.diverged, i1.gated, i1.dof) == (i2.diverged, i2.gated, i2.dof)
    infos = [i for _, i in together]
    assert together[0][0] is start and infos[0].diverged and infos[0].dof == 0
    assert infos[1].gated and infos[1].dof == 0 and infos[1].nis > 100.0
    assert infos[2].dof == 3 and not infos[2].gated and infos[3].dof == 0 and not infos[3].diverged


def test_implausible_innovation_is_flagged() -> None:
    _, info = EKF(PRED, OBS).step(PRIOR, np.zeros(2), np.array([100.0, -100.0, 0.0]), None)
    assert info.diverged and info.nis > 1e3


def test_systematic_resampling_counts_follow_weights() -> None:
    rng = np.random.default_rng(1)
    w = rng.random(1000) * (rng.random(1000) > 0.3)
    w /= w.sum()
    counts = np.bincount(systematic_resample(w, rng), minlength=w.size)
    assert counts.sum() == w.size
    assert np.all(np.abs(counts - w.size * w) < 1.0)  # low variance: floor or ceil of M w
    assert np.all(counts[w == 0] == 0)


def test_particle_belief_ess() -> None:
    b = ParticleBelief(np.zeros((4, 1)), np.log(np.array([0.25, 0.25, 0.25, 0.25])))
    assert b.ess == pytest.approx(4.0)


def _sharp_run(rule: str, noise: np.ndarray, steps: int = 12):
    """A PF with ``update_rule`` against the closed-form Kalman filter on readings of noise
    variance ``noise``: the last belief as a Gaussian, the Kalman mean and covariance, the
    last step's report and the mean NEES of the truth over the run."""
    pf = PF(PRED, LinearGaussianObservation(H, noise), n_particles=2000, roughen=1.0,
            roughen_cov="kalman", update_rule=rule)  # fmt: skip
    rng, truth = np.random.default_rng(7), np.random.default_rng(8)
    belief, mean, cov, x, nees = pf.initial(PRIOR, rng), PRIOR.mean, PRIOR.cov, PRIOR.mean.copy(), []
    for _ in range(steps):
        u = truth.normal(size=2)
        x = A @ x + B @ u + truth.normal(size=4) * np.sqrt(Q)
        z, valid = H @ x + truth.normal(size=3) * np.sqrt(noise), np.ones(3, bool)
        belief, info = pf.step(belief, u, z, valid, rng)
        mean, cov = kalman(mean, cov, u, z, valid, noise)
        g = pf.gaussian(belief)
        nees.append((g.mean - x) @ np.linalg.solve(g.cov, g.mean - x))
    return pf.gaussian(belief), mean, cov, info, float(np.mean(nees))


def test_the_bridged_update_follows_the_kalman_filter_where_the_likelihood_is_too_sharp() -> None:
    """Readings 300 times sharper than the test's (sd 1 mm against a 0.55 m prior): the
    likelihood's update (Table 1) leaves about one particle and loses the state; the
    ensemble Kalman particle update (Frei & Kuensch 2013) keeps half the sample and the
    closed-form posterior, consistent (mean NEES near n = 4)."""
    sharp = np.full(3, 1e-6)
    g, mean, cov, info, nees = _sharp_run("bridge", sharp)
    assert info.ess >= 0.5 * 2000 and info.resampled
    assert info.dof == 3 and math.isfinite(info.nis) and info.diverged is not None and not info.diverged
    se = np.sqrt(np.diag(cov) / info.ess)
    assert np.all(np.abs(g.mean - mean) < 5 * se)
    np.testing.assert_allclose(np.diag(g.cov), np.diag(cov), rtol=0.3)
    assert 2.0 < nees < 8.0
    plain = _sharp_run("table1", sharp)
    assert plain[3].ess < 5 and plain[4] > 100  # what the bridge mends


def _reference_bridge(x, logw, noise, z, gamma, rng):
    """Frei & Kuensch's (2013) update written with the linear model's ``H`` and the cloud's
    covariance ``P``, as the paper states it: ``K1 = P H^T (H P H^T + R / gamma)^-1``,
    ``nu = x + K1 (z - H x)``, ``Q = K1 R K1^T / gamma``, weights ``w N(z; H nu, H Q H^T +
    R / (1 - gamma))``, ``K2 = Q H^T (H Q H^T + R / (1 - gamma))^-1``; the draws in the
    implementation's order. The moved particles and the weights' effective sample size."""
    w = np.exp(logw)
    dx = x - w @ x
    p, r = (dx * w[:, None]).T @ dx, np.diag(noise)
    k1 = p @ H.T @ np.linalg.inv(H @ p @ H.T + r / gamma)
    nu = x + (z - x @ H.T) @ k1.T
    q = k1 @ r @ k1.T / gamma
    alpha, k2 = w, None
    if gamma < 1:
        s2 = H @ q @ H.T + r / (1 - gamma)
        innov = z - nu @ H.T
        alpha = w * np.exp(-0.5 * np.einsum("mi,ij,mj->m", innov, np.linalg.inv(s2), innov))
        k2 = q @ H.T @ np.linalg.inv(s2)
    alpha = alpha / alpha.sum()
    keep = systematic_resample(alpha, rng)
    xi = rng.standard_normal((x.shape[0], 3)) * np.sqrt(noise / gamma)
    moved = nu[keep] + xi @ k1.T
    if k2 is not None:
        zeta = rng.standard_normal((x.shape[0], 3)) * np.sqrt(noise / (1 - gamma))
        moved = moved + (z - nu[keep] @ H.T - xi @ (H @ k1).T - zeta) @ k2.T
    return moved, 1.0 / np.sum(alpha**2)


@pytest.mark.parametrize(("spread", "expected"), [(0.0, 0.1), (0.8, 0.2), (1.5, 1.0)])
def test_the_bridged_update_is_frei_and_kuenschs_with_the_least_gamma_keeping_half(spread, expected) -> None:
    """A two-mode cloud (3,000 particles near the reading, 1,000 a metre away) and a 3 cm
    reading: the implementation's algebra (``A = (C + R / gamma)^-1``, ``d = (R / gamma) A
    r``) gives the paper's update to rounding, with the smallest gamma of the grid whose
    weights keep half the sample: 0.1 with equal prior weights; 0.2 with prior weights
    (log-normal, ``spread``) that keep 2,090 of 4,000, where gamma 0.1's keep 1,985; and
    gamma 1, the ensemble Kalman move alone resampled by the prior weights, when they keep
    456 and no gamma can."""
    from estimator_service.filters.particle import BRIDGE_ESS, BRIDGE_GAMMAS

    m, noise, rng = 4000, np.full(3, 1e-3), np.random.default_rng(11)
    sd = np.array([0.1, 0.1, 0.05, 0.05])
    far = [1.0, 0, 0, 0] + rng.standard_normal((1000, 4)) * sd
    x = np.concatenate([rng.standard_normal((3000, 4)) * sd, far])
    logw = np.full(m, -np.log(m)) + rng.normal(size=m) * spread
    logw -= np.logaddexp.reduce(logw)
    prior, z = ParticleBelief(x, logw), np.array([0.02, -0.01, 0.01])
    pf = PF(PRED, LinearGaussianObservation(H, noise), n_particles=m, update_rule="bridge")
    zs = x @ H.T
    w = np.exp(logw)
    moved, ess, gamma = pf._bridge(prior, z - zs, zs - w @ zs, noise, np.random.default_rng(3))
    refs = {g: _reference_bridge(x, logw, noise, z, g, np.random.default_rng(3)) for g in BRIDGE_GAMMAS}
    kept = [g for g in BRIDGE_GAMMAS if refs[g][1] >= BRIDGE_ESS * m]
    assert gamma == pytest.approx(expected) and gamma == (kept[0] if kept else 1.0)
    np.testing.assert_allclose(moved, refs[gamma][0], atol=1e-9)
    assert ess == pytest.approx(refs[gamma][1], rel=1e-9) and ess <= m


@dataclass(frozen=True)
class InfiniteWhereFar:
    """The linear reading, sharp, with an infinite mean (or variance: ``field``) for
    particles with ``x_0 > 1`` (a model evaluated far outside its data)."""

    field: str = "mean"
    state_dim: int = 4
    obs_dim: int = 3

    def observe(self, x, *, jac=False, var=True) -> ModelOutput:
        out = LinearGaussianObservation(H, np.full(3, 1e-4)).observe(x, jac=jac, var=var)
        far = np.broadcast_to(x[:, :1] > 1.0, out.mean.shape)
        if self.field == "mean":
            return ModelOutput(np.where(far, np.inf, out.mean), out.var, out.jac)
        return ModelOutput(out.mean, np.where(far, np.inf, out.var), out.jac)


@pytest.mark.parametrize("field", ["mean", "var"])
def test_a_non_finite_reading_of_some_particles_keeps_table1s_update(field: str) -> None:
    """Table 1 gives particles whose predicted reading or its variance is infinite no weight;
    the bridge, whose moments would not be finite, is not tried: the same particles, draw for
    draw."""
    prior = GaussianBelief(np.array([0.5, -0.2, 0.1, 0.0]), np.diag([0.3, 0.3, 0.1, 0.1]))
    posts = []
    for rule in ("table1", "bridge"):
        model = InfiniteWhereFar(field)
        pf, rng = PF(PRED, model, n_particles=500, update_rule=rule), np.random.default_rng(4)
        b = pf.initial(prior, rng)
        assert np.any(b.particles[:, 0] > 1.0) and np.any(b.particles[:, 0] < 1.0)
        post, info = pf.update(b, np.array([0.4, -0.1, 0.3]), None, rng)
        assert np.all(np.isfinite(post.particles)) and info.ess < 0.5 * 500
        posts.append(post)
    np.testing.assert_array_equal(posts[0].particles, posts[1].particles)


def test_the_bridged_update_is_table1_while_the_weights_keep_half_the_sample() -> None:
    """Readings the cloud can absorb (the test's own noise) never call the bridge: the same
    particles, draw for draw, as the likelihood's update."""
    runs = [_sharp_run(rule, R * 1e3, steps=5) for rule in ("table1", "bridge")]
    assert runs[0][3].ess > 0.5 * 2000 and not runs[0][3].resampled
    np.testing.assert_array_equal(runs[0][0].mean, runs[1][0].mean)
    np.testing.assert_array_equal(runs[0][0].cov, runs[1][0].cov)
    with pytest.raises(ValueError, match="update_rule"):
        PF(PRED, OBS, update_rule="enkf")


def test_the_factory_picks_the_pf_update_by_model_kind_unless_told() -> None:
    from estimator_service.factory import MODEL_KINDS, PF_UPDATE_RULES, make_filter

    assert set(PF_UPDATE_RULES) == set(MODEL_KINDS)
    rules = {k: make_filter("pf", PRED, OBS, model_kind=k).update_rule for k in MODEL_KINDS}
    assert rules == {"param": "table1", **dict.fromkeys(("gp", "egp", "hetgp", "sparse"), "bridge")}
    assert make_filter("pf", PRED, OBS).update_rule == "table1"  # models of no kind: the paper's
    assert make_filter("pf", PRED, OBS, model_kind="gp", update_rule="table1").update_rule == "table1"
    pf = make_filter("pf", PRED, OBS, model_kind="gp")
    assert (pf.roughen, pf.roughen_cov) == (1.0, "kalman")
    with pytest.raises(ValueError, match="model_kind"):
        make_filter("pf", PRED, OBS, model_kind="gpr")


def test_regularised_resampling_keeps_the_cloud_diverse_and_consistent() -> None:
    rng = np.random.default_rng(0)
    plain, rough = (
        PF(PRED, OBS, n_particles=2000, resample_below=1.0),
        PF(PRED, OBS, n_particles=2000, resample_below=1.0, roughen=1.0),
    )
    beliefs = {"plain": plain.initial(PRIOR, rng), "rough": rough.initial(PRIOR, rng)}
    mean, cov = PRIOR.mean, PRIOR.cov
    for u, z, valid in scenario(8, seed=2):
        beliefs["plain"], _ = plain.step(beliefs["plain"], u, z, valid, rng)
        beliefs["rough"], _ = rough.step(beliefs["rough"], u, z, valid, rng)
        mean, cov = kalman(mean, cov, u, z, valid)
    unique = {k: len(np.unique(b.particles[:, 0])) for k, b in beliefs.items()}
    assert unique["rough"] == 2000 and unique["rough"] > unique["plain"]
    g = rough.gaussian(beliefs["rough"])
    assert np.all(np.abs(g.mean - mean) < 5 * np.sqrt(np.diag(cov)))
    np.testing.assert_allclose(np.diag(g.cov), np.diag(cov), rtol=0.5)


def test_kalman_roughening_keeps_the_gaussian_posterior_spread_under_a_sharp_likelihood() -> None:
    """A likelihood far sharper than the cloud leaves one particle with all the weight: the
    posterior-covariance kernel then collapses the cloud, the Kalman kernel keeps the
    spread the closed-form filter has (times Silverman's bandwidth) in the unobserved
    velocities, their correlation included."""
    sharp = LinearGaussianObservation(H[:2], np.array([1e-10, 1e-10]))
    cov = PRIOR.cov.copy()
    cov[2, 3] = cov[3, 2] = 0.07  # correlated velocities (r = 0.7)
    prior = GaussianBelief(PRIOR.mean, cov)
    u, z, valid = np.zeros(2), np.array([0.4, -0.1]), np.ones(2, bool)
    m = 4000
    spread, clouds = {}, {}
    for cov_kind in ("posterior", "kalman"):
        pf = PF(PRED, sharp, n_particles=m, resample_below=1.0, roughen=1.0, roughen_cov=cov_kind)
        rng = np.random.default_rng(5)
        belief, info = pf.step(pf.initial(prior, rng), u, z, valid, rng)
        assert info.ess < 2.0
        spread[cov_kind] = belief.particles[:, 2:].std(axis=0)
        clouds[cov_kind] = np.cov(belief.particles.T)
    prior_cov = A @ prior.cov @ A.T + np.diag(Q)
    hs = H[:2]
    k = np.linalg.solve(hs @ prior_cov @ hs.T, hs @ prior_cov).T  # gain P H^T S^-1 (S symmetric)
    post = prior_cov - k @ hs @ prior_cov
    h = (4.0 / (m * 6)) ** (1.0 / 8)
    np.testing.assert_allclose(spread["kalman"], h * np.sqrt(np.diag(post)[2:]), rtol=0.1)
    # the observed positions are pinned by the update (posterior sd ~0): the whole roughened
    # cloud has the Kalman covariance; the prior's would spread the positions by h * 0.55
    np.testing.assert_allclose(clouds["kalman"], h**2 * post, atol=0.05 * h**2 * post.diagonal().max())
    assert np.all(spread["posterior"] < 0.01 * spread["kalman"])
    with pytest.raises(ValueError, match="roughen_cov"):
        PF(PRED, OBS, roughen_cov="prior")


@pytest.mark.parametrize(("cls", "noise"), [(EKF, None), (UKF, "mean"), (UKF, "sigma")])
def test_batched_kalman_step_equals_one_blimp_at_a_time(cls, noise) -> None:
    """The service and the batched belief env step many blimps' EKFs or UKFs with one GP
    call: same beliefs, any camera subset per blimp (none, one camera, both), up to rounding."""
    from estimator_service.gp import ExactGP, Scaler
    from estimator_service.models import GPObservationModel, GPPredictionModel

    rng = np.random.default_rng(3)
    nx, nu, nz, n = 4, 2, 6, 200
    x = rng.normal(size=(n, nx + nu))
    xo = rng.normal(size=(n, nx))
    theta_p = np.column_stack([np.full((nx, nx + nu), 0.4), np.full(nx, -1.0), np.full(nx, -3.0)])
    theta_o = np.column_stack([np.full((nz, nx), 0.3), np.zeros(nz), np.full(nz, -2.5)])
    one = lambda d: Scaler(np.zeros(d), np.ones(d))  # noqa: E731
    gp_p = ExactGP.from_theta(x, 0.1 * np.tanh(x[:, :nx]), theta_p, one(nx + nu), one(nx))
    gp_o = ExactGP.from_theta(xo, np.tanh(xo @ rng.normal(size=(nx, nz))), theta_o, one(nx), one(nz))
    kw = {} if noise is None else {"noise": noise}
    ekf = cls(GPPredictionModel(gp_p, nx), GPObservationModel(gp_o), **kw)
    b = 9
    beliefs = [
        GaussianBelief(rng.normal(size=nx) * 0.5, np.diag(rng.uniform(0.01, 0.1, nx))) for _ in range(b)
    ]
    u, z = rng.normal(size=(b, nu)), rng.normal(size=(b, nz))
    valid = np.zeros((b, nz), bool)
    for i in range(b):
        valid[i, : 3 * (i % 3)] = True  # 0, 1 or 2 "cameras" of 3 values
    batched = step_many(ekf, beliefs, u, z, valid)
    for i in range(b):
        one_belief, info = ekf.step(beliefs[i], u[i], z[i], valid[i])
        np.testing.assert_allclose(batched[i][0].mean, one_belief.mean, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched[i][0].cov, one_belief.cov, rtol=1e-10, atol=1e-12)
        assert batched[i][1].dof == info.dof == int(valid[i].sum())
        assert not np.array_equal(batched[i][0].mean, beliefs[i].mean)


def test_batched_joseph_update_equals_the_single_rule_and_isolates_a_bad_row() -> None:
    """The stacked update against the one-belief rule (``kalman_update``, cho_solve), and a
    row whose innovation covariance is indefinite: it alone is skipped, the others are not."""
    from estimator_service.filters.batched import joseph_update_many
    from estimator_service.filters.kalman import kalman_update

    rng = np.random.default_rng(5)
    b, n, q = 6, 5, 3
    mean = rng.normal(size=(b, n))
    a = rng.normal(size=(b, n, n))
    cov = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(n)
    h, r = rng.normal(size=(b, q, n)), rng.normal(size=(b, q))
    noise = rng.uniform(0.05, 0.2, (b, q))
    wrap = Wrapping(np.array([0.0, 2 * math.pi, 0, 0, 0]), np.zeros(q))

    def single(i: int):
        s = h[i] @ cov[i] @ h[i].T + np.diag(noise[i])
        return kalman_update(GaussianBelief(mean[i], cov[i]), r[i], s, cov[i] @ h[i].T, wrap, h[i], noise[i])

    for bad in (None, 2):
        if bad is not None:
            noise[bad] = -1e6  # S indefinite: the single rule skips the update
        out = joseph_update_many(mean, cov, r, h, noise, wrap, single)
        for i in range(b):
            ref, info = single(i)
            np.testing.assert_allclose(out[i][0].mean, ref.mean, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(out[i][0].cov, ref.cov, rtol=1e-9, atol=1e-12)
            assert out[i][1].diverged == info.diverged and out[i][1].dof == info.dof
            assert out[i][1].nis == pytest.approx(info.nis, rel=1e-9, nan_ok=True)
        if bad is not None:
            assert out[bad][1].diverged and np.array_equal(out[bad][0].mean, mean[bad])
            assert not any(out[i][1].diverged for i in range(b) if i != bad)


def _nees_and_inflation(filt, q_true: np.ndarray, steps: int = 400) -> tuple[float, float]:
    """Average NEES of ``filt`` on the linear system with true process noise ``q_true``,
    and the belief's process-noise factor at the end."""
    rng = np.random.default_rng(4)
    x, belief, nees = PRIOR.mean.copy(), PRIOR, []
    for _ in range(steps):
        u = rng.normal(size=2)
        x = A @ x + B @ u + rng.normal(size=4) * np.sqrt(q_true)
        z = H @ x + rng.normal(size=3) * np.sqrt(R)
        belief, _ = filt.step(belief, u, z, np.ones(3, bool))
        e = x - belief.mean
        nees.append(e @ np.linalg.solve(belief.cov, e))
    return float(np.mean(nees[50:])), belief.inflation


@pytest.mark.parametrize("cls", [EKF, UKF])
@pytest.mark.slow
def test_adaptive_process_noise_stays_put_when_consistent_and_inflates_when_not(cls) -> None:
    """With the model's own noise the factor stays near its floor and the filter is the
    Kalman filter's within a few percent of NEES; with 10x the process noise it rises and
    brings NEES (4 when consistent) most of the way back."""
    plain, adaptive = cls(PRED, OBS), cls(PRED, OBS, adapt_rate=0.5)
    nees_plain, f_plain = _nees_and_inflation(plain, Q)
    nees_adapt, f_adapt = _nees_and_inflation(adaptive, Q)
    assert f_plain == 1.0 and f_adapt < 1.5
    assert abs(nees_adapt - nees_plain) < 0.15 * nees_plain
    hard_plain, _ = _nees_and_inflation(plain, 10 * Q)
    hard_adapt, f_hard = _nees_and_inflation(adaptive, 10 * Q)
    assert f_hard > 2.0 and hard_adapt - 4.0 < 0.5 * (hard_plain - 4.0)  # measured 21.2 -> 9.5


def _nis_level(filt, steps: int = 400) -> float:
    """Mean NIS/dof of ``filt`` on the linear system in its own conditions."""
    rng, x, belief, ratios = np.random.default_rng(5), PRIOR.mean.copy(), PRIOR, []
    for _ in range(steps):
        u = rng.normal(size=2)
        x = A @ x + B @ u + rng.normal(size=4) * np.sqrt(Q)
        belief, info = filt.step(belief, u, H @ x + rng.normal(size=3) * np.sqrt(R), np.ones(3, bool))
        ratios.append(info.nis / info.dof)
    return float(np.mean(ratios))


@pytest.mark.parametrize("cls", [EKF, UKF])
@pytest.mark.slow
def test_adaptation_referenced_to_the_calibrated_nis_level_catches_what_nis_one_misses(cls) -> None:
    """A filter whose noise was widened 2.5x (as a calibration's coverage factor does) has
    innovations well below consistent (mean NIS/dof 0.4): referred to 1, the adaptation
    starts only once the innovations are too large *by themselves*, and with 10x the
    velocities' process noise it hardly moves (NEES 6.9, 4 when consistent; 7.8 without
    adaptation); referred to the filter's own level it stays at its floor in its own
    conditions and brings NEES back below 4 (measured 3.7)."""
    wide = LinearGaussianPrediction(A, B, 2.5 * Q), LinearGaussianObservation(H, 2.5 * R)
    level = _nis_level(cls(*wide))
    assert level < 0.5
    plain, by_one = cls(*wide), cls(*wide, adapt_rate=0.5)
    by_level = cls(*wide, adapt_rate=0.5, adapt_reference=level)
    nees_plain, _ = _nees_and_inflation(plain, Q)
    nees_own, f_own = _nees_and_inflation(by_level, Q)
    assert f_own < 1.5 and abs(nees_own - nees_plain) < 0.2 * nees_plain
    hard = Q * np.array([1, 1, 10, 10])
    nees_one, _ = _nees_and_inflation(by_one, hard)
    nees_level, f_level = _nees_and_inflation(by_level, hard)
    assert f_level > 2.0 and nees_level < 4.0 < nees_one - 2.0


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_adaptive_inflation_scales_only_the_disturbed_states(cls) -> None:
    """The factor multiplies the process variance of ``adapt_states`` only."""
    belief = GaussianBelief(PRIOR.mean, PRIOR.cov, 4.0)
    u = np.array([0.3, -0.2])
    base = cls(PRED, OBS).predict(GaussianBelief(PRIOR.mean, PRIOR.cov), u)
    only_v = cls(PRED, OBS, adapt_rate=0.5, adapt_states=(2, 3)).predict(belief, u)
    every = cls(PRED, OBS, adapt_rate=0.5).predict(belief, u)
    want = np.array([0, 0, 3 * Q[2], 3 * Q[3]])
    np.testing.assert_allclose(np.diag(only_v.cov) - np.diag(base.cov), want, atol=1e-12)
    np.testing.assert_allclose(np.diag(every.cov) - np.diag(base.cov), 3 * Q, atol=1e-12)
    for bad, field in (({"adapt_states": (4,)}, "adapt_states"), ({"adapt_states": (1, 1)}, "adapt_states"),
                       ({"adapt_states": ()}, "adapt_states"), ({"adapt_reference": 0.0}, "adapt_reference"),
                       ({"adapt_reference": math.inf}, "adapt_reference")):  # fmt: skip
        with pytest.raises(ValueError, match=field):
            cls(PRED, OBS, adapt_rate=0.5, **bad)


def test_adaptive_ekf_batched_equals_one_at_a_time_and_the_pf_refuses_the_option() -> None:
    from estimator_service.factory import make_filter

    ekf = EKF(PRED, OBS, adapt_rate=0.5)
    beliefs = [GaussianBelief(PRIOR.mean + 0.1 * i, PRIOR.cov, 1.0 + i) for i in range(3)]
    u, z = np.ones((3, 2)), np.full((3, 3), 4.0)  # large innovations: the factor moves
    batched = step_many(ekf, beliefs, u, z, np.ones((3, 3), bool))
    for b, (post, _) in zip(beliefs, batched, strict=True):
        one, _ = ekf.step(b, u[0], z[0], np.ones(3, bool))
        np.testing.assert_allclose(post.mean, one.mean, rtol=1e-12)
        assert post.inflation == one.inflation > b.inflation
    with pytest.raises(ValueError, match="adapt_rate"):
        make_filter("pf", PRED, OBS, adapt_rate=0.5)
    with pytest.raises(ValueError, match="inflation"):
        GaussianBelief(PRIOR.mean, PRIOR.cov, 0.0)
    with pytest.raises(ValueError, match="adapt_rate"):
        EKF(PRED, OBS, adapt_rate=math.nan)
    with pytest.raises(ValueError, match="max_inflation"):
        UKF(PRED, OBS, adapt_rate=0.5, max_inflation=0.5)


# --- the filters' contracts, field by field (each check below failed a mutant of the code) ---


@dataclass(frozen=True)
class NoisyWhereFar:
    """Identity dynamics with process variance ``0.01 + x^2`` per component."""

    state_dim: int = 2
    control_dim: int = 1

    def predict(self, x, u, *, jac=False, var=True) -> ModelOutput:  # no variance unless asked, as a GP
        j = np.zeros((len(x), 2, 2)) if jac else None
        return ModelOutput(np.zeros_like(x), 0.01 + x**2 if var else np.zeros_like(x), j)


@dataclass(frozen=True)
class FirstWithNoise:
    """``z = x_0 + 0.3 x_0^2`` with noise variance ``0.01 + x_0^2``."""

    state_dim: int = 2
    obs_dim: int = 1

    def observe(self, x, *, jac=False, var=True) -> ModelOutput:
        j = np.concatenate([1 + 0.6 * x[:, :1], np.zeros((len(x), 1))], axis=1)[:, None, :] if jac else None
        v = 0.01 + x[:, :1] ** 2 if var else np.zeros((len(x), 1))
        return ModelOutput(x[:, :1] + 0.3 * x[:, :1] ** 2, v, j)


def test_the_ukf_takes_noise_at_the_mean_or_averaged_over_the_sigma_points_as_asked() -> None:
    """``noise="mean"``: ``Q`` and ``R`` at the mean (the paper); ``noise="sigma"``: their plain
    average over the ``2n + 1`` sigma points. Worked by hand from the sigma points."""
    prior = GaussianBelief(np.array([0.4, -0.3]), np.array([[0.2, 0.05], [0.05, 0.1]]), inflation=1.0)
    for noise in ("mean", "sigma"):
        ukf = UKF(NoisyWhereFar(), FirstWithNoise(), noise=noise)
        pts = ukf.sigma_points(prior)
        wm, wc, _ = sigma_weights(2, ukf.alpha, ukf.beta, ukf.kappa)
        dev = pts - wm @ pts
        q = 0.01 + (prior.mean**2 if noise == "mean" else np.mean(pts**2, axis=0))
        pred = ukf.predict(prior, np.zeros(1))
        np.testing.assert_allclose(pred.cov, (dev * wc[:, None]).T @ dev + np.diag(q), rtol=1e-12)
        post, info = ukf.update(prior, np.array([0.9]), np.array([True]))
        zs = pts[:, 0] + 0.3 * pts[:, 0] ** 2
        r = 0.01 + (prior.mean[0] ** 2 if noise == "mean" else np.mean(pts[:, 0] ** 2))
        zhat = wm @ zs
        s = wc @ (zs - zhat) ** 2 + r
        assert info.nis == pytest.approx((0.9 - zhat) ** 2 / s, rel=1e-12) and info.dof == 1
        pxz = (wc * (zs - zhat)) @ (pts - prior.mean)  # the state's deviations from the prior mean
        np.testing.assert_allclose(post.mean, prior.mean + pxz / s * (0.9 - zhat), rtol=1e-12)
        np.testing.assert_allclose(post.cov, prior.cov - np.outer(pxz, pxz) / s, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_a_beliefs_inflation_survives_its_steps_and_failed_sigma_points(cls) -> None:
    f = cls(PRED, OBS)
    inflated = GaussianBelief(PRIOR.mean, PRIOR.cov, inflation=2.5)
    assert f.predict(inflated, np.zeros(2)).inflation == 2.5
    broken = GaussianBelief(PRIOR.mean, np.full((4, 4), np.nan), inflation=2.5)
    out = f.predict_many([broken, inflated], np.zeros((2, 2)))
    assert np.isnan(out[0].cov).all() and out[0].inflation == 2.5
    assert np.isnan(out[0].mean).all() == (cls is UKF)  # the EKF moves the mean without the covariance
    assert out[1].inflation == 2.5 and np.isfinite(out[1].cov).all()


def test_an_unusable_belief_in_a_ukf_batch_refuses_only_its_own_update() -> None:
    ukf = UKF(PRED, OBS)
    broken = GaussianBelief(PRIOR.mean, np.full((4, 4), np.nan))
    z, valid = np.array([[0.4, -0.1, 0.3]] * 3), np.array([[True, True, False]] * 3)
    out = ukf.update_many([PRIOR, broken, PRIOR], z, valid)
    assert out[1][0] is broken and out[1][1].diverged and out[1][1].dof == 2
    assert math.isnan(out[1][1].nis)
    alone = ukf.update(PRIOR, z[2], valid[2])
    for post, info in (out[0], out[2]):  # the beliefs after the broken one are still updated
        np.testing.assert_allclose(post.mean, alone[0].mean, rtol=1e-12)
        assert info.dof == 2 and not info.diverged
    assert np.isnan(ukf.sigma_points(broken)).all() and ukf.sigma_points(broken).shape == (9, 4)


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_an_update_reads_only_the_valid_entries(cls) -> None:
    f = cls(PRED, OBS)
    z = np.array([0.4, 99.0, 99.0])  # the invalid entries would pull the belief far away
    post, info = f.update(PRIOR, z, np.array([True, False, False]))
    only = cls(PRED, LinearGaussianObservation(H[:1], R[:1])).update(PRIOR, z[:1])
    np.testing.assert_allclose(post.mean, only[0].mean, rtol=1e-12)
    assert info.dof == 1 and info.nis == pytest.approx(only[1].nis, rel=1e-12)


def test_an_implausible_innovation_is_flagged_by_the_ukf_update() -> None:
    info = UKF(PRED, OBS).update(PRIOR, np.array([40.0, 0.0, 0.0]), np.ones(3, bool))[1]
    assert info.diverged and info.nis > 1e3 and info.dof == 3


def test_a_refused_update_reports_its_nis_and_no_degrees_of_freedom() -> None:
    from estimator_service.filters.common import StepInfo

    info = StepInfo(7.5, 3, True, 12.0, True).refused()
    assert (info.nis, info.dof, info.gated) == (7.5, 0, True)
    assert info.diverged is False and info.resampled is False and info.ess is None


def test_the_ukf_refuses_weights_that_do_not_exist_by_name() -> None:
    with pytest.raises(ValueError, match=r"alpha > 0 and n \+ kappa > 0 \(n = 4\), got 1.0, -4"):
        UKF(PRED, OBS, kappa=-4)
    with pytest.raises(ValueError, match="alpha > 0"):
        UKF(PRED, OBS, alpha=0.0)


def test_the_particle_mean_of_angles_uses_each_components_own_period() -> None:
    """An ellipse orientation (period pi) and a heading (2 pi) averaged on their circles, a
    position linearly: three particles straddling each cut."""
    wrap = Wrapping(np.array([0.0, math.pi, 2 * math.pi]), np.zeros(1))
    x = np.array([[1.0, 1.5, 3.0], [2.0, -1.5, -3.0], [4.0, 1.5, 3.1]])
    w = np.array([0.5, 0.25, 0.25])
    mean = wrap.circular_mean(x, w)
    assert mean[0] == pytest.approx(w @ x[:, 0])
    for k, p in ((1, math.pi), (2, 2 * math.pi)):
        a = 2 * math.pi * x[:, k] / p
        assert mean[k] == pytest.approx(p / (2 * math.pi) * math.atan2(w @ np.sin(a), w @ np.cos(a)))
    assert abs(mean[1]) > 1.3 and abs(mean[2]) > 2.9  # near the cut, not near 0


def test_a_gaussian_belief_prints_its_mean_and_standard_deviations() -> None:
    b = GaussianBelief(np.array([1.23456, 2e-5]), np.diag([4.0, 9.0]))
    assert repr(b) == "GaussianBelief(mean=[1.235 0.   ], std=[2. 3.])"
    long = repr(GaussianBelief(np.arange(25.0), np.eye(25)))
    assert "..." in long and "..." not in repr(GaussianBelief(np.arange(24.0), np.eye(24)))


def test_the_adaptive_factor_and_its_defaults_follow_the_documented_rule() -> None:
    """``lambda' = clip(lambda * clip(NIS / (dof c), 1/10, 10)^rate, 1, cap)``; unchanged when
    off, nothing was read, the gate refused the update, or the NIS is not finite."""
    from estimator_service.filters.adaptive import RATIO_CLIP, check_adaptation, next_inflation
    from estimator_service.filters.common import StepInfo

    info = StepInfo(nis=6.0, dof=2)
    assert next_inflation(2.0, info, 0.5) == pytest.approx(2.0 * 3.0**0.5)  # reference 1 by default
    assert next_inflation(2.0, info, 0.5, reference=1.5) == pytest.approx(2.0 * 2.0**0.5)
    assert next_inflation(2.0, info, 1.0, cap=5.0) == 5.0
    assert next_inflation(2.0, StepInfo(nis=1e6, dof=1), 1.0, cap=100.0) == pytest.approx(2.0 * RATIO_CLIP)
    assert next_inflation(8.0, StepInfo(nis=1e-6, dof=1), 1.0) == 1.0  # never below 1
    assert next_inflation(30.0, StepInfo(nis=1e-6, dof=1), 0.5) == pytest.approx(30.0 / RATIO_CLIP**0.5)
    for same in (
        StepInfo(nis=6.0, dof=0),
        StepInfo(nis=6.0, dof=2, gated=True),
        StepInfo(nis=math.nan, dof=2),
    ):
        assert next_inflation(2.0, same, 0.5) == 2.0
    assert next_inflation(2.0, StepInfo(nis=2.0, dof=1), 0.5) == pytest.approx(2.0 * 2.0**0.5)  # one value
    assert next_inflation(2.0, info, 0.0) == 2.0 and next_inflation(2.0, info, 1e-9) > 2.0
    from estimator_service.filters.adaptive import adapted

    moved = adapted(PRIOR, GaussianBelief(PRIOR.mean, PRIOR.cov, 2.0), info, 0.5)  # reference 1, cap 30
    assert moved.inflation == pytest.approx(2.0 * 3.0**0.5)
    check_adaptation(0.0, 1.0)  # the edges are allowed
    check_adaptation(1.0, 1.0, 0.5)
    for rate, cap in (
        (1.0 + 1e-9, 10.0),
        (-1e-9, 10.0),
        (math.nan, 10.0),
        (0.5, 1.0 - 1e-9),
        (0.5, math.inf),
    ):
        with pytest.raises(ValueError, match=r"adapt_rate|max_inflation"):
            check_adaptation(rate, cap)


def test_a_batch_of_ekf_updates_is_the_joseph_form_computed_once_for_all() -> None:
    """The batched EKF update equals the single-belief rule row by row without falling back
    to it (the fallback raises here), and its covariances are exactly symmetric."""
    from estimator_service.filters.batched import implausible_many, joseph, joseph_update_many
    from estimator_service.filters.kalman import kalman_update

    rng = np.random.default_rng(4)
    b, n, q = 3, 4, 2
    g = rng.normal(size=(b, n, n))
    cov, mean = g @ g.transpose(0, 2, 1) + 0.1 * np.eye(n), rng.normal(size=(b, n))
    h, r_noise, r = rng.normal(size=(b, q, n)), rng.uniform(0.1, 0.5, size=(b, q)), rng.normal(size=(b, q))
    wrap = Wrapping.none(n, q)

    def no_fallback(i: int):
        raise AssertionError("the batched update fell back to the single rule")

    out = joseph_update_many(mean, cov, r, h, r_noise, wrap, no_fallback)
    for i, (post, info) in enumerate(out):
        s = h[i] @ cov[i] @ h[i].T + np.diag(r_noise[i])
        want, want_info = kalman_update(
            GaussianBelief(mean[i], cov[i]), r[i], s, cov[i] @ h[i].T, wrap, h[i], r_noise[i]
        )
        np.testing.assert_allclose(post.mean, want.mean, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(post.cov, want.cov, rtol=1e-9, atol=1e-12)
        assert info.nis == pytest.approx(want_info.nis, rel=1e-10) and info.dof == q and not info.diverged
        assert np.array_equal(post.cov, post.cov.T)
    k = rng.normal(size=(b, n, q))
    post = joseph(cov, k, h, r_noise)
    assert np.array_equal(post, post.transpose(0, 2, 1)) and np.array_equal(
        joseph(cov[0], k[0], h[0], r_noise[0]), post[0]
    )
    assert implausible_many(np.array([math.nan, 1e9]), 0).tolist() == [False, False]  # nothing read
    assert implausible_many(np.array([math.nan, 1e9, 1.0]), 2).tolist() == [True, True, False]


def test_the_step_policys_edges_named_and_reported() -> None:
    """Which filters batch; a step without readings is the prediction; bad batch shapes are
    refused naming the argument; a particle belief's ESS is reported where it is kept."""
    from estimator_service.filters import update_many
    from estimator_service.filters.policy import batchable, step_one

    assert batchable(EKF(PRED, OBS)) and batchable(UKF(PRED, OBS)) and not batchable(PF(PRED, OBS))
    for f in (EKF(PRED, OBS), UKF(PRED, OBS)):
        post, info = f.step(PRIOR, np.array([0.3, -0.1]))
        want = f.predict(PRIOR, np.array([0.3, -0.1]))
        np.testing.assert_array_equal(post.mean, want.mean)
        assert info.dof == 0 and math.isnan(info.nis) and not info.diverged
    two = [PRIOR, PRIOR]
    for name, args in (
        ("u", (np.zeros((3, 2)), np.zeros((2, 3)), np.ones((2, 3), bool))),
        ("z", (np.zeros((2, 2)), np.zeros((1, 3)), np.ones((2, 3), bool))),
        ("valid", (np.zeros((2, 2)), np.zeros((2, 3)), np.ones(3, bool))),
    ):
        with pytest.raises(ValueError, match=rf"^step_many: '{name}' must have one row per belief \(2\)"):
            step_many(EKF(PRED, OBS), two, *args)
    pf = PF(PRED, OBS, n_particles=50)
    cloud = pf.initial(PRIOR, np.random.default_rng(0))
    weighted = ParticleBelief(cloud.particles, cloud.log_weights - np.log(np.exp(cloud.log_weights).sum()))
    broken = ParticleBelief(np.full((50, 4), np.nan), cloud.log_weights)
    out = step_many(
        pf, [broken], np.zeros((1, 2)), np.zeros((1, 3)), np.ones((1, 3), bool), rng=np.random.default_rng(0)
    )
    assert out[0][0] is broken and out[0][1].diverged and out[0][1].ess == pytest.approx(broken.ess)
    kept = update_many(pf, [weighted], np.zeros((1, 3)), np.zeros((1, 3), bool), rng=np.random.default_rng(0))
    assert kept[0][0] is weighted and kept[0][1].ess == pytest.approx(weighted.ess)
    alone = step_one(pf, weighted, np.zeros(2), rng=np.random.default_rng(0))[1]
    assert alone.ess == pytest.approx(weighted.ess) and alone.dof == 0


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_the_factor_moves_relative_to_the_filters_reference_on_its_states(cls) -> None:
    f = cls(PRED, OBS, adapt_rate=1.0, adapt_reference=0.5)
    post, info = f.update(PRIOR, np.array([1.4, -0.9, 0.2]), np.ones(3, bool))
    assert post.inflation == pytest.approx(min(max(info.nis / (3 * 0.5), 1.0), 10.0), rel=1e-12)
    assert post.inflation > 1.0
    with pytest.raises(
        ValueError, match=r"adapt_states must be distinct state indices in \[0, 4\), got \(1, 1\)"
    ):
        cls(PRED, OBS, adapt_states=(1, 1))


def test_the_covariance_helpers_at_their_edges() -> None:
    """``make_pd``: a positive-definite matrix is returned as given with its exact factor; a
    singular one has its eigenvalues raised to ``floor * trace / n``. Index rules, the
    chi-square flag without readings, one wrapping rule per component, a belief's shapes."""
    from estimator_service.filters.common import (
        distinct_indices,
        implausible,
        make_pd,
        weighted_mean,
        wrap_periodic,
    )

    good = np.array([[2.0, 0.3], [0.3, 1.0]])
    c, l = make_pd(good)
    assert np.array_equal(c, good) and np.array_equal(l, np.linalg.cholesky(good))
    c, l = make_pd(np.diag([400.0, 0.0, 0.0, 0.0]))  # floor 1e-12 x trace 400 / 4
    np.testing.assert_allclose(np.diag(c), [400.0, 1e-10, 1e-10, 1e-10], rtol=1e-6)
    assert np.allclose(c, np.diag(np.diag(c)), rtol=0, atol=1e-15)
    assert distinct_indices((0, 2), 3) == (0, 2) and distinct_indices((3,), 3) is None
    assert distinct_indices((2, 2), 3) is None and distinct_indices((), 3) is None
    assert implausible(math.nan, 0) is False and implausible(math.nan, 2) is True
    np.testing.assert_allclose(
        wrap_periodic(np.array([5.0, 4.0]), np.array([0.0, 2 * math.pi])), [5.0, 4.0 - 2 * math.pi]
    )
    values = np.array([[math.pi - 0.01], [-math.pi + 0.03]])  # 0.04 apart across the cut
    assert weighted_mean(values, np.array([0.5, 0.5]), np.array([2 * math.pi]))[0] == pytest.approx(
        -math.pi + 0.01
    )
    b = GaussianBelief(np.array([1, 2]), np.eye(2, dtype=int))
    assert b.mean.dtype == np.float64 and b.cov.dtype == np.float64
    listed = GaussianBelief([1.0, 2.0], [[1.0, 0.0], [0.0, 1.0]])
    assert isinstance(listed.mean, np.ndarray) and isinstance(listed.cov, np.ndarray)
    with pytest.raises(
        ValueError, match=r"belief mean \(n,\) and cov \(n, n\) expected, got \(2,\), \(3, 3\)"
    ):
        GaussianBelief(np.zeros(2), np.eye(3))
    assert "\n" not in repr(GaussianBelief(np.arange(12.0) * 1000.5, np.eye(12)))


def test_a_periodic_component_of_any_period_is_averaged_on_its_circle() -> None:
    wrap = Wrapping(np.array([0.5]), np.zeros(1))
    x = np.array([[0.24], [-0.24]])  # 0.02 apart across the cut at +-0.25
    assert abs(wrap.circular_mean(x, np.array([0.5, 0.5]))[0]) == pytest.approx(0.25, abs=1e-9)


@pytest.mark.parametrize("cls", [EKF, UKF])
def test_an_update_whose_innovation_covariance_is_not_positive_definite_is_refused(cls) -> None:
    obs = LinearGaussianObservation(H[:1], np.array([-10.0]))  # a negative noise variance: S < 0
    post, info = cls(PRED, obs).update(PRIOR, np.array([0.3]))
    assert post is PRIOR and info.diverged and info.dof == 1 and math.isnan(info.nis)


def test_a_batch_with_one_unusable_row_falls_back_to_the_single_rule_for_every_row() -> None:
    obs = LinearGaussianObservation(H, R)
    ekf = EKF(PRED, obs)
    broken = GaussianBelief(PRIOR.mean, -np.eye(4))  # S not positive definite: the batch fails
    z, valid = np.array([[0.4, -0.1, 0.3]] * 3), np.ones((3, 3), bool)
    out = ekf.update_many([PRIOR, broken, PRIOR], z, valid)
    alone = ekf.update(PRIOR, z[0])
    for post, info in (out[0], out[2]):
        np.testing.assert_allclose(post.mean, alone[0].mean, rtol=1e-12)
        np.testing.assert_allclose(post.cov, alone[0].cov, rtol=1e-10, atol=1e-14)
        assert info.nis == pytest.approx(alone[1].nis, rel=1e-12)
    assert out[1][0] is broken and out[1][1].diverged


def test_angles_are_averaged_across_the_cut_by_the_ukf() -> None:
    """A heading near +pi with a spread that crosses the cut: the predicted mean and the
    innovation of a reading just past -pi stay near the cut (not near 0)."""
    from estimator_service.angles import wrap_angle

    @dataclass(frozen=True)
    class Heading:  # a model that reports its angles wrapped, as the GP models do
        state_dim: int = 1
        control_dim: int = 1
        obs_dim: int = 1

        def predict(self, x, u, *, jac=False, var=True) -> ModelOutput:
            change = wrap_angle(x + 0.0, 2 * math.pi) - x
            return ModelOutput(change, np.full_like(x, 1e-4), np.zeros((len(x), 1, 1)) if jac else None)

        def observe(self, x, *, jac=False, var=True) -> ModelOutput:
            return ModelOutput(
                wrap_angle(x, 2 * math.pi), np.full_like(x, 1e-3), np.ones((len(x), 1, 1)) if jac else None
            )

    wrap = Wrapping(np.array([2 * math.pi]), np.array([2 * math.pi]))
    ukf = UKF(Heading(), Heading(), wrapping=wrap)
    prior = GaussianBelief(np.array([math.pi - 0.05]), np.array([[0.01]]))
    p = ukf.predict(prior, np.zeros(1))
    assert p.mean[0] == pytest.approx(math.pi - 0.05, abs=1e-9) and p.cov[0, 0] == pytest.approx(0.0101)
    post, info = ukf.update(p, np.array([-math.pi + 0.02]))
    assert abs(post.mean[0]) > 3.1 and info.nis < 1.0  # 0.07 rad away, not 2 pi - 0.07
    away = ukf.update(GaussianBelief(p.mean - math.pi, p.cov), np.array([0.02]))  # the same, far from the cut
    assert wrap_angle(post.mean[0] - math.pi - away[0].mean[0], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)
    assert info.nis == pytest.approx(away[1].nis, rel=1e-9) and post.cov[0, 0] == pytest.approx(
        away[0].cov[0, 0]
    )


def test_a_prediction_with_a_finite_mean_but_no_covariance_keeps_the_belief() -> None:
    from estimator_service.filters.policy import batchable

    class HalfBatched:
        def predict_many(self, beliefs, u):  # an update_many is missing: not a batching filter
            raise AssertionError

    assert not batchable(HalfBatched())
    ekf = EKF(PRED, OBS)
    nan_cov = GaussianBelief(PRIOR.mean, np.full((4, 4), np.nan))
    post, info = ekf.step(nan_cov, np.zeros(2), np.array([0.4, -0.1, 0.3]), np.ones(3, bool))
    assert post is nan_cov and info.diverged


def test_an_update_whose_posterior_overflows_or_cannot_be_factored_is_skipped() -> None:
    """With a positive-definite ``S`` the update is still skipped (the prior kept, divergence
    flagged, the NIS and its degrees of freedom reported) when the posterior mean overflows,
    when the covariance overflows, or when no factor of it exists; the batched update hands
    such a batch to the single rule row by row."""
    from estimator_service.filters.batched import joseph_update_many
    from estimator_service.filters.common import StepInfo
    from estimator_service.filters.kalman import kalman_update

    one = np.array([[1.0]])
    wrap = Wrapping.none(1, 1)
    cases = {  # prior, innovation, S, cross-covariance, Joseph H and R (None: P - K S K^T)
        "mean overflows": (GaussianBelief(np.array([1.797e308]), np.array([[1e305]])), [1e306], 1e305 + 1.0,
                           [[1e305]], one, [1.0]),
        "covariance overflows": (GaussianBelief(np.zeros(1), one), [0.0], 1.0, [[1e200]], one, [1.0]),
        "no factor": (GaussianBelief(np.zeros(2), np.full((2, 2), 1.7e308)), [0.5], 1.0, [[0.0], [0.0]],
                      None, None),
    }  # fmt: skip
    for name, (prior, r, s, pxz, h, noise) in cases.items():
        r, s = np.array(r), np.array([[s]])
        nis = float(np.sum((r / math.sqrt(s[0, 0])) ** 2))
        post, info = kalman_update(prior, r, s, np.array(pxz), wrap if h is not None else Wrapping.none(2, 1),
                                   h, None if noise is None else np.array(noise))  # fmt: skip
        assert post is prior, name
        assert info.diverged and info.dof == 1 and info.nis == pytest.approx(nis, rel=1e-12), name
    prior, r, s, pxz, h, noise = cases["mean overflows"]
    calls = []

    def single(i: int):
        calls.append(i)
        return prior, StepInfo(1.0, 1, True)

    mean = np.array([[0.0], prior.mean])
    cov = np.stack([one, prior.cov])
    out = joseph_update_many(
        mean, cov, np.array([[0.1], r]), np.stack([one, one]), np.ones((2, 1)), wrap, single
    )
    assert calls == [0, 1] and all(o[1].diverged for o in out)  # the overflowing row spoils none


def test_an_update_that_leaves_an_indefinite_covariance_is_refused() -> None:
    """A UKF-form update ``P - K S K^T`` whose cross-covariance claims more than the prior
    knew leaves a clearly negative eigenvalue: the update is refused (the prior kept,
    divergence flagged) instead of flooring it into a belief certain in that direction
    (before: variance 1e-12 of the trace, the truth's NEES 2.3e11 on a lab flight). A
    negative eigenvalue at rounding level is still repaired."""
    from estimator_service.filters.common import ROUNDING, sound_posterior
    from estimator_service.filters.kalman import kalman_update

    prior = GaussianBelief(np.zeros(2), np.eye(2))
    wrap = Wrapping.none(2, 1)
    post, info = kalman_update(prior, np.array([0.5]), np.array([[1.0]]), np.array([[2.0], [0.0]]), wrap)
    assert post is prior and info.diverged and info.dof == 1  # P - K S K^T = diag(-3, 1)
    tiny = np.diag([1.0, -0.1 * ROUNDING])
    c, l = sound_posterior(tiny)
    np.testing.assert_allclose(l @ l.T, c, atol=1e-11)
    np.testing.assert_allclose(c, np.diag([1.0, 0.0]), atol=1e-9)
    assert sound_posterior(np.diag([1.0, -1e-3])) is None
    assert sound_posterior(np.diag([1e-6, -1e-12])) is None  # relative to the trace: scale-free
