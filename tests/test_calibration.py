"""Process-noise calibration: the scaled model, its file, and the NEES-matching choice."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.recorder import collect_flight
from agents.training import TrainSettings, calibrate_noise, train_models
from estimator_service.factory import load_models
from estimator_service.models import LinearGaussianPrediction
from estimator_service.models.calibration import (
    CALIBRATION_FILE,
    NoiseScaledPrediction,
    read_noise_scales,
    write_noise_scales,
)


def test_scaled_model_scales_only_the_variance() -> None:
    base = LinearGaussianPrediction(np.eye(2), np.ones((2, 1)), np.array([0.1, 0.2]))
    scaled = NoiseScaledPrediction(base, 3.0)
    x, u = np.array([[1.0, 2.0], [0.0, -1.0]]), np.array([0.5])
    a, b = base.predict(x, u, jac=True), scaled.predict(x, u, jac=True)
    np.testing.assert_array_equal(b.mean, a.mean)
    np.testing.assert_array_equal(b.jac, a.jac)
    np.testing.assert_allclose(b.var, 3.0 * a.var)
    assert scaled.state_dim == 2 and scaled.control_dim == 1
    with pytest.raises(ValueError, match="noise scale"):
        NoiseScaledPrediction(base, 0.0)


def test_scales_file_round_trip_merge_and_errors(tmp_path: Path) -> None:
    assert read_noise_scales(tmp_path) == {}
    write_noise_scales(tmp_path, {"gp": 2.0})
    write_noise_scales(tmp_path, {"param": 4.5}, note="x")
    assert read_noise_scales(tmp_path) == {"gp": 2.0, "param": 4.5}
    assert not list(tmp_path.glob("*.tmp"))  # written, then renamed
    (tmp_path / CALIBRATION_FILE).write_text('{"noise_scale": {"gp": -1}}')
    with pytest.raises(ValueError, match="finite and > 0"):
        read_noise_scales(tmp_path)
    (tmp_path / CALIBRATION_FILE).write_text("[1, 2]")
    with pytest.raises(ValueError, match="noise_scale"):
        read_noise_scales(tmp_path)


def test_calibration_picks_the_scale_whose_nees_is_nearest_the_state_dimension(tmp_path: Path) -> None:
    flight = collect_flight(90, seed=3)
    s = TrainSettings(n_points=60, restarts=1, max_iter=5, calibration_seconds=0)
    train_models([flight], tmp_path, kinds=["param"], settings=s, seed=0)
    assert read_noise_scales(tmp_path) == {}  # calibration_seconds = 0 skips it
    chosen = calibrate_noise(flight, tmp_path, ["param"], seconds=30, scales=(0.01, 1.0, 100.0))
    nees = json.loads((tmp_path / CALIBRATION_FILE).read_text())["details"]["ekf_nees_by_scale"]["param"]
    best = min(nees, key=lambda k: abs(np.log(nees[k] / 12)))
    assert chosen == {"param": float(best)} and nees["0.01"] > nees["1.0"] > nees["100.0"]
    pred, _ = load_models(tmp_path, "param")
    assert (chosen["param"] == 1.0) != isinstance(pred, NoiseScaledPrediction)
