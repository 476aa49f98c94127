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
