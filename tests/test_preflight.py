"""Training fails fast, before any fit, with an error naming the sensor, fold or row and the fix."""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from estimator_service.flight import make_flight
from estimator_service.preflight import PreflightError, PreflightWarning
from estimator_service.system import System
from estimator_service.training import TrainSettings, train_models
from tests.robot_log import SYSTEM, simulate

LANDMARKS = {
    **SYSTEM,
    "sensors": [*SYSTEM["sensors"], {"name": "beacon", "outputs": ["range"], "rate_hz": 10.0}],
}


def _flight(rows: int = 3000, beacon_rows: slice = slice(None), **changes):
    d = simulate(rows, np.random.default_rng(0))
    system = System.from_dict({**LANDMARKS, **changes})
    beacon = np.full((rows, 1), np.nan)
    beacon[beacon_rows] = np.hypot(d["x"][beacon_rows, 0] - 3.0, d["x"][beacon_rows, 1])[:, None]
    z = np.concatenate([d["gps"], d["compass"], beacon], axis=1)
    valid = np.stack([np.isfinite(d["gps"][:, 0]), np.ones(rows, bool), np.isfinite(beacon[:, 0])], axis=1)
    return make_flight(system, d["t"], d["x"], d["u"], np.nan_to_num(z), valid)


def _train(flight, tmp_path: Path, **settings):
    settings = TrainSettings(**{"n_points": 50, "restarts": 1, "max_iter": 5, **settings})
    return train_models([flight], tmp_path / "models", kinds=["gp"], settings=settings)


def test_a_sensor_whose_readings_all_fall_in_a_calibration_fold_is_named_within_seconds(tmp_path) -> None:
    flight = _flight(beacon_rows=slice(0, 600))  # the beacon is seen in the first minute only
    t0 = time.perf_counter()
    with pytest.raises(PreflightError) as err:
        _train(flight, tmp_path, calibration_seconds=60.0, calibration_folds=4)
    assert time.perf_counter() - t0 < 5.0
    message = str(err.value)
    assert "calibration fold 1 of 4 (rows 0-599 of log 0)" in message
    assert "sensor 'beacon'" in message and "600 fall in the fold" in message
    assert "--calibration-seconds" in message
    assert not (tmp_path / "models").exists()  # nothing written


def test_too_few_readings_wrong_steps_and_degrees_are_named(tmp_path) -> None:
    with pytest.raises(PreflightError, match=r"sensor 'beacon' has 3 reading\(s\) in the logs"):
        _train(_flight(beacon_rows=slice(0, 3)), tmp_path, calibration_seconds=0)
    flight = _flight()
    t = flight.t.copy()
    t[1500:] += 0.5  # half a second missing, same episode
    with pytest.raises(PreflightError, match=r"log 0: rows 1499 and 1500 .* are 0.6 s apart"):
        _train(make_flight(flight.system, t, flight.state, flight.control, flight.z, flight.valid),
               tmp_path, calibration_seconds=0)  # fmt: skip
    state = flight.state.copy()
    state[:, 2] = np.degrees(state[:, 2])
    with pytest.raises(
        PreflightError, match=r"state 'heading' reaches 1[0-9]{2}\.?[0-9]*, beyond half its period"
    ):
        _train(make_flight(flight.system, flight.t, state, flight.control, flight.z, flight.valid),
               tmp_path, calibration_seconds=0)  # fmt: skip


def test_a_sensor_far_from_its_declared_rate_is_a_warning_not_an_error(tmp_path) -> None:
    flight = _flight(beacon_rows=slice(None, None, 20))  # 0.5 Hz where the description says 10
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _train(flight, tmp_path, calibration_seconds=0)
    rates = [str(w.message) for w in caught if issubclass(w.category, PreflightWarning)]
    assert rates == ["log 0: sensor 'beacon' delivered 0.5 readings/s, its description says 10"]
