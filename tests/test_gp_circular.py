"""Circular GP inputs and outputs: periodicity, wrapped angle targets, Jacobian, persistence."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from estimator_service.gp import CircularGP, ModelFileError, fit_circular, fit_exact, load_gp, save_gp


def _wrap(a: np.ndarray, period: float) -> np.ndarray:
    return (a + period / 2) % period - period / 2


@pytest.fixture(scope="module")
def data() -> tuple[np.ndarray, np.ndarray]:
    """x = (s, yaw); y = (sin yaw + s, an orientation of period pi that crosses its wrap)."""
    rng = np.random.default_rng(3)
    x = np.c_[rng.uniform(-1, 1, 250), rng.uniform(-math.pi, math.pi, 250)]
    y = np.c_[np.sin(x[:, 1]) + x[:, 0], _wrap(0.5 * x[:, 1] + 0.3 * x[:, 0], math.pi)]
    return x, y + 0.01 * rng.normal(size=y.shape)


@pytest.fixture(scope="module")
def model(data) -> CircularGP:
    x, y = data
    rng = np.random.default_rng(0)
    return fit_circular(
        x,
        y,
        lambda a, b: fit_exact(a, b, rng=rng, max_iter=60),
        angle_inputs=(1,),
        angle_output=1,
        period=math.pi,
    )


def test_prediction_is_periodic_in_the_angle_input(model) -> None:
    eps = 1e-3
    a = model.predict(np.array([[0.2, math.pi - eps]]))
    b = model.predict(np.array([[0.2, -math.pi + eps]]))
    assert np.allclose(a.mean[0, 0], b.mean[0, 0], atol=1e-2)
    assert abs(a.mean[0, 0] - 0.2) < 0.05


def test_angular_output_is_learned_across_its_wrap(model, data) -> None:
    """A raw GP would average +-pi/2 to about 0 near the wrap; the circular one does not."""
    q = np.c_[np.zeros(5), np.linspace(-3.1, 3.1, 5)]
    truth = _wrap(0.5 * q[:, 1], math.pi)
    err = _wrap(model.predict(q).mean[:, 1] - truth, math.pi)
    assert np.max(np.abs(err)) < 0.05
    assert np.all(np.abs(model.predict(q).mean[:, 1]) <= math.pi / 2 + 1e-12)


def test_jacobian_matches_finite_differences(model) -> None:
    q = np.array([[0.2, 3.0], [-0.4, -3.05], [0.1, 0.5]])
    jac = model.predict(q, return_jac=True).jac
    h = 1e-3
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        fd = (model.predict(q + e).mean - model.predict(q - e).mean) / (2 * h)
        assert np.allclose(jac[:, :, j], fd, atol=5e-5)


def test_angle_variance_is_large_where_the_training_angles_disagree() -> None:
    """Random orientations (a round ellipse) give a short mean vector and a large variance."""
    rng = np.random.default_rng(1)
    x = rng.uniform(-1, 1, (200, 1))
    y = np.where(
        x > 0, rng.uniform(-math.pi / 2, math.pi / 2, (200, 1)), 0.3 + 0.01 * rng.normal(size=(200, 1))
    )
    g = fit_circular(x, y, lambda a, b: fit_exact(a, b, rng=rng, max_iter=40), angle_output=0, period=math.pi)
    v = g.predict(np.array([[-0.5], [0.5]])).var[:, 0]
    assert v[1] > 20 * v[0]


def test_round_trip_and_bad_files(model, tmp_path: Path) -> None:
    path = save_gp(model, tmp_path / "c.npz")
    q = np.array([[0.3, -2.0]])
    back = load_gp(path)
    assert isinstance(back, CircularGP)
    assert np.array_equal(back.predict(q, return_jac=True).jac, model.predict(q, return_jac=True).jac)
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["angle_inputs"] = np.array([7.0])
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ModelFileError, match="angle_inputs"):
        load_gp(tmp_path / "bad.npz")


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"angle_inputs": (2,)}, "angle_inputs"),
        ({"angle_inputs": (1, 1)}, "angle_inputs"),
        ({"angle_output": 3}, "angle_output"),
        ({"angle_output": 0, "period": 0.0}, "period"),
    ],
)
def test_bad_arguments_name_the_problem(data, kwargs, match: str) -> None:
    x, y = data
    with pytest.raises(ValueError, match=match):
        fit_circular(x, y, lambda a, b: fit_exact(a, b), **kwargs)
