"""Scoring of tracking runs: the consistency bands of the averaged NEES and NIS/dof."""

from __future__ import annotations

import numpy as np
import pytest

from estimator_service.tracking import consistency_band, consistent_variances


def test_consistency_bands_match_simulated_consistent_filters() -> None:
    rng = np.random.default_rng(0)
    steps, reps = 200, 4000
    dof = rng.choice([0, 5, 10], size=steps)
    nees_var, nis_var = consistent_variances(steps, dof)
    nees = rng.chisquare(12, size=(reps, steps)).mean(axis=1)  # a consistent filter's averages
    has = dof > 0
    nis = (rng.chisquare(np.where(has, dof, 1), size=(reps, steps))[:, has] / dof[has]).mean(axis=1)
    assert nees.var() == pytest.approx(nees_var, rel=0.1) and nis.var() == pytest.approx(nis_var, rel=0.1)
    lo, hi = consistency_band(12.0, nees_var)
    assert np.mean((nees >= lo) & (nees <= hi)) == pytest.approx(0.95, abs=0.015)
    assert np.isnan(consistent_variances(10, np.zeros(10, np.int64))[1])


def test_consistency_band_is_the_chi_square_law_not_a_normal_one() -> None:
    # a short run: the average of 3 NEES values is skewed, chi2(36) / 3
    rng = np.random.default_rng(1)
    nees = rng.chisquare(12, size=(200_000, 3)).mean(axis=1)
    lo, hi = consistency_band(12.0, consistent_variances(3, np.zeros(3, np.int64))[0])
    assert np.mean(nees < lo) == pytest.approx(0.025, abs=0.002)
    assert np.mean(nees > hi) == pytest.approx(0.025, abs=0.002)
    assert np.isnan(consistency_band(1.0, float("nan"))[0])


def test_reliability_is_the_diagonal_for_a_calibrated_belief_and_below_it_when_overconfident() -> None:
    """Errors drawn from the belief itself cover each nominal central interval as often as it
    says (within 4 binomial standard errors); errors twice as large fall below the diagonal
    at every level, by the closed-form amount ``2 Phi(k / 2) - 1``."""
    from scipy.stats import norm

    from estimator_service.system import Group
    from estimator_service.tracking import RELIABILITY_LEVELS, reliability

    rng = np.random.default_rng(3)
    t, sd = 20_000, np.array([0.5, 2.0, 3.0])
    cov = np.broadcast_to(np.diag(sd**2), (t, 3, 3))
    err = rng.normal(size=(t, 3)) * sd
    groups = (Group("a", (0,), 1.0), Group("bc", (1, 2), 1.0))
    levels = np.array(RELIABILITY_LEVELS)
    calibrated = reliability(err, cov, groups)
    for name, count in (("a", t), ("bc", 2 * t)):
        se = np.sqrt(levels * (1 - levels) / count)
        assert np.all(np.abs(calibrated[name] - levels) <= 4 * se + 1e-12), name
    wide = reliability(2 * err, cov, groups)["bc"]
    expected = 2 * norm.cdf(norm.ppf((1 + levels) / 2) / 2) - 1
    np.testing.assert_allclose(wide, expected, atol=4 * np.sqrt(0.25 / (2 * t)))
    assert np.all(wide < levels)


def test_a_run_whose_belief_has_lost_the_yaw_fails_though_the_truth_stays_inside() -> None:
    """A run fails when the truth leaves 3 sigma on more than 10 % of its steps, or when
    its belief has lost an angle (standard deviation above half a uniform belief's: 52 deg
    for a full turn) on more than 10 % of them: such a belief holds any truth within 3 sigma
    and has lost track all the same."""
    import math

    from estimator_service.tracking import TrackResult, lost_angle_sd, score

    rng = np.random.default_rng(4)
    t, n = 200, 12
    sd = np.full(n, 0.01)
    truth = rng.normal(size=(t, n)) * 0.1
    truth[:, 3:6] = 0.0
    mean = truth + rng.normal(size=(t, n)) * sd

    def run(yaw_sd: np.ndarray) -> dict[str, float]:
        cov = np.broadcast_to(np.diag(sd**2), (t, n, n)).copy()
        cov[:, 5, 5] = yaw_sd**2
        none = np.zeros(t, np.int64)
        return score(TrackResult(mean, cov, truth, np.zeros(t), none, none.astype(bool), 0.0))

    assert math.degrees(lost_angle_sd(2 * math.pi)) == pytest.approx(51.96, abs=0.01)
    sharp = run(np.full(t, 0.01))
    assert sharp["failed"] == 0.0 and sharp["lost_steps"] == 0.0
    lost = np.full(t, 0.01)
    lost[:30] = math.radians(60)  # 15 % of the steps: the yaw's belief is nearly uniform
    wide = run(lost)
    assert wide["outside_3sigma"] < 0.1 and wide["lost_steps"] == pytest.approx(0.15)
    assert wide["failed"] == 1.0
    lost[:30] = math.radians(50)  # sharp enough: not lost
    assert run(lost)["failed"] == 0.0
