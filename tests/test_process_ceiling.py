"""The process-variance ceiling: a calibrated process noise never exceeds ten times what the
state did in training, so a runaway matched scale cannot make the EKF diverge."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.sim import collect_flight
from estimator_service.factory import build_filter, load_models
from estimator_service.models import LinearGaussianPrediction
from estimator_service.models.calibration import (
    CALIBRATION_FILE,
    CEILING_FACTOR,
    PROCESS_CEILING,
    NoiseScaledPrediction,
    read_process_ceiling,
    write_noise_scales,
    write_process_ceiling,
)
from estimator_service.store import seal
from estimator_service.tracking import track_flight
from estimator_service.training import TrainSettings, train_models

ROLL_RATE = 9


def test_scaled_variance_is_capped_per_output() -> None:
    base = LinearGaussianPrediction(np.eye(2), np.ones((2, 1)), np.array([0.1, 0.2]))
    capped = NoiseScaledPrediction(base, 3.0, np.array([0.2, 10.0]))
    x, u = np.array([[1.0, 2.0], [0.0, -1.0]]), np.array([0.5])
    a, b = base.predict(x, u, jac=True), capped.predict(x, u, jac=True)
    np.testing.assert_array_equal(b.mean, a.mean)
    np.testing.assert_array_equal(b.jac, a.jac)
    np.testing.assert_allclose(b.var, np.minimum(3.0 * a.var, [0.2, 10.0]))
    assert b.var[0, 0] == 0.2 and b.var[0, 1] == 3.0 * a.var[0, 1]
    for bad in ([0.2], [0.2, 0.0], [0.2, np.nan], [[0.2, 1.0]], [0.2, "x"], [0.2, [1.0]]):
        with pytest.raises(ValueError, match=PROCESS_CEILING):
            NoiseScaledPrediction(base, 3.0, bad)
    uncapped = NoiseScaledPrediction(base, 3.0, np.array([0.2, np.inf])).predict(x, u)
    assert uncapped.var[0, 1] == 3.0 * a.var[0, 1]  # inf: that output has no ceiling


def test_ceiling_file_round_trip_survives_scale_writes_and_refuses_bad_values(tmp_path: Path) -> None:
    assert read_process_ceiling(tmp_path, 2) is None
    states = np.array([[0.0, 1.0], [2.0, 1.5], [4.0, 2.0]])
    write_process_ceiling(tmp_path, states)
    write_noise_scales(tmp_path, {"gp": 2.0}, process={"gp": np.array([1.0, 3.0])})
    np.testing.assert_allclose(read_process_ceiling(tmp_path, 2), CEILING_FACTOR * states.var(axis=0))
    body = json.loads((tmp_path / CALIBRATION_FILE).read_text())
    states[:, 1] = 1.5  # an output that never varied in training gets no ceiling
    write_process_ceiling(tmp_path, states)
    assert json.loads((tmp_path / CALIBRATION_FILE).read_text())[PROCESS_CEILING][1] is None
    np.testing.assert_array_equal(
        read_process_ceiling(tmp_path, 2), [CEILING_FACTOR * states[:, 0].var(), np.inf]
    )
    body = json.loads((tmp_path / CALIBRATION_FILE).read_text())
    body[PROCESS_CEILING] = [1.0, -1.0]
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(body))
    with pytest.raises(ValueError, match=f"{CALIBRATION_FILE}.*{PROCESS_CEILING}"):
        read_process_ceiling(tmp_path, 2)


def test_a_runaway_process_scale_is_capped_and_the_ekf_stays_on_track(tmp_path: Path) -> None:
    """A roll-rate process scale of 1e4 (the matching reached 875 on one paper-size hetGP
    fold) makes the plain EKF diverge (position error 1e27 m, measured) unless the ceiling
    stored by training caps it; with it the belief stays within half a metre."""
    train, test = collect_flight(120, seed=3), collect_flight(60, seed=4)
    s = TrainSettings(n_points=60, restarts=1, max_iter=5, calibration_seconds=0)
    train_models([train], tmp_path, kinds=["param"], settings=s)
    ceiling = read_process_ceiling(tmp_path, 12)
    np.testing.assert_allclose(ceiling, CEILING_FACTOR * train.state.var(axis=0), rtol=1e-12)
    runaway = np.ones(12)
    runaway[ROLL_RATE] = 1e4
    write_noise_scales(tmp_path, {"param": 1.0}, process={"param": runaway})
    seal(tmp_path, train.system)
    pred, _ = load_models(tmp_path, "param")
    assert isinstance(pred, NoiseScaledPrediction)
    np.testing.assert_array_equal(pred.ceiling, ceiling)

    def worst_position_error() -> float:
        filt = build_filter("ekf", "param", tmp_path, adapt_rate=0.0)
        with np.errstate(all="ignore"):
            r = track_flight(filt, test, rows=slice(0, 120))
        return float(np.nanmax(np.linalg.norm(r.mean[:, :3] - r.truth[:, :3], axis=1)))

    assert worst_position_error() < 0.5
    body = json.loads((tmp_path / CALIBRATION_FILE).read_text())
    del body[PROCESS_CEILING]  # a folder trained before the ceiling: the scale as stored
    (tmp_path / CALIBRATION_FILE).write_text(json.dumps(body))
    seal(tmp_path, train.system)
    assert not worst_position_error() < 1e3
