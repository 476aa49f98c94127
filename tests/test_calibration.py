"""Noise calibration: the scaled models, their file, the NEES-matching process-noise choice
and the held-out observation-noise scales."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from agents.sim import collect_flight
from estimator_service.calibrate import (
    calibrate_noise,
    calibrate_observation,
    calibrate_process,
    calibration_rows,
    without_frames,
)
from estimator_service.factory import load_models
from estimator_service.models import LinearGaussianObservation, LinearGaussianPrediction
from estimator_service.models.calibration import (
    CALIBRATION_FILE,
    NoiseScaledObservation,
    NoiseScaledPrediction,
    read_noise_scales,
    read_observation_scales,
    write_noise_scales,
)
from estimator_service.training import TrainSettings, train_models


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
    with pytest.raises(ValueError, match="JSON object"):
        read_noise_scales(tmp_path)


def test_process_calibration_matches_each_output_to_the_held_out_errors(tmp_path: Path) -> None:
    """One-step scales are each output's mean squared standardised residual on the held-out
    transitions; the matching rounds then bring every output's ``e^2 / P`` on those rows
    nearer 1, and the stored scales are what the models load with."""
    flight = collect_flight(120, seed=3)
    rows = calibration_rows(flight, 30.0)
    s = TrainSettings(n_points=60, restarts=1, max_iter=5, calibration_seconds=0)
    train_models([flight.select(np.arange(rows.stop, len(flight)))], tmp_path, kinds=["param"], settings=s)
    assert read_noise_scales(tmp_path) == {}  # calibration_seconds = 0 skips it
    one_step = calibrate_process(flight, tmp_path, ["param"], rows=rows)["param"]
    pred, _ = load_models(tmp_path, "param", calibrated=False)
    x, u, x1 = flight.select(np.arange(rows.stop)).transitions()
    out = pred.predict(x, u)
    r = flight.system.wrapping().state_diff(flight.system.state_error(x1, x) - out.mean)
    np.testing.assert_allclose(one_step, np.clip(np.mean(r * r / out.var, axis=0), 0.1, 1e4), rtol=1e-9)
    chosen = calibrate_noise(flight, tmp_path, ["param"], rows=rows)["param"]
    rounds = json.loads((tmp_path / CALIBRATION_FILE).read_text())["details"]["matching"]["param"]
    first, last = (np.abs(np.log(rounds[k]["e2_over_var"])) for k in (0, -1))
    assert np.median(last) < np.median(first)  # each output's spread nearer its errors
    scaled, _ = load_models(tmp_path, "param")
    assert isinstance(scaled, NoiseScaledPrediction)
    np.testing.assert_allclose(scaled.scale, chosen, rtol=1e-12)


def test_cross_fitted_calibration_keeps_the_truth_inside_3_sigma_on_a_new_flight(tmp_path: Path) -> None:
    """GP models trained on an 8-minute flight and calibrated by cross-fitting (two 2-minute
    blocks, each scored with models that never saw it), tracked on a new flight by the
    factory's filters: the truth lies within 3 sigma on every dimension on at least 90% of
    the steps (Gaussian expectation 0.968 for 12 dimensions) and the average NEES is near
    12. (The in-sample calibration before cross-fitting reached 0.901 and 0.920 here too,
    on this long flight; its failure shows on short ones: 4-minute flight, 1 minute held
    out, 0.695 and 0.720, NEES 263. The leakage itself is tested below.) Measured in the
    clean world, where this was established; the lab world's figure is in issue 19's note."""
    from estimator_service.factory import build_filter
    from estimator_service.tracking import track_flight

    clean = {"reality": "clean"}
    train = collect_flight(480, seed=21, env_kwargs=clean)
    test = collect_flight(120, seed=22, env_kwargs=clean)
    s = TrainSettings(n_points=200, restarts=1, max_iter=40, hyper_points=None, calibration_seconds=120)
    train_models([train], tmp_path, kinds=["gp"], settings=s)
    for kind in ("ekf", "ukf"):
        filt = build_filter(kind, "gp", tmp_path)
        runs = [
            track_flight(filt, test, rows=slice(a, a + 120)).scores() for a in range(0, len(test) - 119, 120)
        ]
        assert np.mean([r["within3"] for r in runs]) >= 0.9, kind
        assert 0.5 * 12 <= np.mean([r["nees"] for r in runs]) <= 1.5 * 12, kind


def test_no_calibration_block_is_in_the_data_of_the_models_it_scores(tmp_path: Path, monkeypatch) -> None:
    """Cross-fitting: the saved models see the whole flight; each calibration block is
    scored only with models fitted without any of its rows."""
    import estimator_service.crossfit as crossfit
    import estimator_service.training as training

    fits, scored = [], []
    real_fit, real_calibrate = training._fit_models, crossfit.calibrate_all

    def fit(out, flights, *args, **kwargs):
        fits.append((out, set(np.concatenate([f.t for f in flights]).tolist())))
        return real_fit(out, flights, *args, **kwargs)

    def calibrate(flight, folder, kinds, *, rows):
        scored.append((folder, set(flight.t[rows].tolist())))
        return real_calibrate(flight, folder, kinds, rows=rows)

    monkeypatch.setattr(training, "_fit_models", fit)
    monkeypatch.setattr(crossfit, "calibrate_all", calibrate)
    flight = collect_flight(120, seed=5)
    s = TrainSettings(n_points=40, restarts=1, max_iter=3, calibration_seconds=20)
    train_models([flight], tmp_path, kinds=["param"], settings=s)
    assert fits[0][1] == set(flight.t.tolist()) and len(fits) == 3 and len(scored) == 2
    for (fold, seen), (folder, block) in zip(fits[1:], scored, strict=True):
        assert fold == folder and len(block) == 80 and not seen & block
    assert "process_noise_scale" in json.loads((tmp_path / CALIBRATION_FILE).read_text())


def test_scaled_observation_scales_each_output_variance() -> None:
    base = LinearGaussianObservation(np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([0.1, 0.2]))
    scaled = NoiseScaledObservation(base, np.array([2.0, 5.0]))
    x = np.array([[1.0, 2.0], [0.0, -1.0]])
    a, b = base.observe(x, jac=True), scaled.observe(x, jac=True)
    np.testing.assert_array_equal(b.mean, a.mean)
    np.testing.assert_array_equal(b.jac, a.jac)
    np.testing.assert_allclose(b.var, a.var * [2.0, 5.0])
    assert scaled.obs_dim == 2 and scaled.state_dim == 2
    for bad in (np.array([1.0]), np.array([1.0, -1.0]), np.array([1.0, np.nan])):
        with pytest.raises(ValueError, match="observation noise scale"):
            NoiseScaledObservation(base, bad)


def test_observation_calibration_is_the_held_out_standardised_residual(tmp_path: Path) -> None:
    flight = collect_flight(120, seed=4)
    rows = calibration_rows(flight, 20.0)
    assert rows == slice(0, 80) and calibration_rows(flight, 1e4) == slice(0, len(flight) // 4)
    held = without_frames(flight, rows)
    assert not held.valid[rows].any() and (held.valid[80:] == flight.valid[80:]).all()
    s = TrainSettings(n_points=60, restarts=1, max_iter=5, calibration_seconds=0)
    train_models([held], tmp_path, kinds=["param"], settings=s, seed=0)
    chosen = calibrate_observation(flight, tmp_path, ["param"], rows=rows, floor=1e-6)["param"]
    _, cam = load_models(tmp_path, "param", calibrated=False)
    fl = flight.select(np.arange(80))
    for j in range(10):  # independently: camera j // 5, ellipse field j % 5
        v = fl.valid[:, j // 5]
        out = cam.observe(fl.state[v])
        r = fl.z[v, j] - out.mean[:, j]
        if j % 5 == 4:
            r = (r + np.pi / 2) % np.pi - np.pi / 2
        assert chosen[j] == pytest.approx(min(np.mean(r * r / out.var[:, j]), 100.0), rel=1e-9)  # cap 100
    calibrate_observation(flight, tmp_path, ["param"], rows=rows)  # the default floor 1 never narrows
    _, obs = load_models(tmp_path, "param")
    assert isinstance(obs, NoiseScaledObservation)
    np.testing.assert_allclose(obs.scale, np.maximum(chosen, 1.0))
    assert read_observation_scales(tmp_path)["param"].shape == (10,)
    assert read_noise_scales(tmp_path) == {}  # process scales untouched
