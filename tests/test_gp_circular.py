"""Circular GP inputs and outputs: periodicity, wrapped angle targets, Jacobian, persistence."""

from __future__ import annotations

import dataclasses
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
    degrees = dataclasses.replace(model, period=360)  # an integer period (angles in degrees)
    back = load_gp(save_gp(degrees, tmp_path / "degrees.npz"))  # saved as floats, as a file's arrays must be
    assert back.period == 360 and np.array_equal(back.predict(q).mean, degrees.predict(q).mean)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"angle_inputs": (2,)}, "angle_inputs"),
        ({"angle_inputs": (1, 1)}, "angle_inputs"),
        ({"angle_output": 3}, "angle_output"),
        ({"angle_output": 2}, "angle_output"),  # y has columns 0 and 1
        ({"angle_inputs": (-1,)}, "angle_inputs"),
        ({"angle_output": 0, "period": 0.0}, "period"),
    ],
)
def test_bad_arguments_name_the_problem(data, kwargs, match: str) -> None:
    x, y = data
    with pytest.raises(ValueError, match=match):
        fit_circular(x, y, lambda a, b: fit_exact(a, b), **kwargs)


def test_the_first_columns_and_a_short_period_are_accepted(data) -> None:
    """The bounds of the checks above: column 0 is an input or output angle like any other,
    and any positive period is one (an angle of period 0.5 wraps at +-0.25)."""
    x, y = data
    g = fit_circular(x[:30], y[:30], lambda a, b: fit_exact(a, b, max_iter=2), angle_inputs=(0,),
                     angle_output=0, period=0.5)  # fmt: skip
    assert g.angle_inputs == (0,) and g.angle_output == 0 and g.period == 0.5
    assert np.all(np.abs(g.predict(x[:5]).mean[:, 0]) <= 0.25 + 1e-12)


class _Linear:
    """A stand-in inner GP on 2 inputs with 4 outputs (cos, other, other, sin): linear means
    ``a x + b``, distinct constant variances (plus 0.5 with noise), and their Jacobian."""

    kind = "exact"
    input_dim, output_dim = 2, 4
    a = np.array([[0.3, -0.2], [1.0, 0.0], [0.0, 1.0], [0.1, 0.4]])
    b = np.array([0.6, 0.0, 0.0, 0.5])
    v = np.array([0.01, 0.2, 0.3, 0.04])

    def __init__(self) -> None:
        self.noise_asked: list[bool] = []

    def predict(self, x, *, return_var=True, return_jac=False, include_noise=True):
        from estimator_service.gp import GPPrediction

        self.noise_asked.append(include_noise)
        var = np.tile(self.v + (0.5 if include_noise else 0.0), (len(x), 1)) if return_var else None
        jac = np.broadcast_to(self.a, (len(x), 4, 2)).copy() if return_jac else None
        return GPPrediction(x @ self.a.T + self.b, var, jac)


def test_the_angle_output_follows_the_delta_method_of_atan2() -> None:
    """The angle from a ``(cos, sin)`` pair with distinct variances: its mean is
    ``atan2(s, c) / k``, its variance ``g_c^2 v_c + g_s^2 v_s`` and its Jacobian
    ``g_c dc/dx + g_s ds/dx``, with the gradient ``g`` of ``atan2(s, c) / k`` taken by central
    differences; the other outputs pass through; noise is included by default."""
    inner = _Linear()
    gp = CircularGP(inner, (), angle_output=0, period=math.pi)
    x = np.array([[0.2, -0.4], [1.0, 0.7]])
    out = gp.predict(x, return_jac=True)
    k, h = 2.0, 1e-6
    c, s = (x @ inner.a.T + inner.b)[:, 0], (x @ inner.a.T + inner.b)[:, 3]
    g_c = (np.arctan2(s, c + h) - np.arctan2(s, c - h)) / (2 * h * k)
    g_s = (np.arctan2(s + h, c) - np.arctan2(s - h, c)) / (2 * h * k)
    np.testing.assert_allclose(out.mean[:, 0], np.arctan2(s, c) / k, rtol=1e-12)
    np.testing.assert_allclose(out.var[:, 0], g_c**2 * 0.51 + g_s**2 * 0.54, rtol=1e-6)
    np.testing.assert_allclose(
        out.jac[:, 0], g_c[:, None] * inner.a[0] + g_s[:, None] * inner.a[3], rtol=1e-6
    )
    np.testing.assert_allclose(out.var[:, 1:], np.tile(inner.v[1:3] + 0.5, (2, 1)))
    assert inner.noise_asked == [True]
    plain = gp.predict(x, return_var=False)
    assert plain.var is None and plain.jac is None and np.array_equal(plain.mean, out.mean)
    assert gp.predict(x, include_noise=False).var[0, 0] < out.var[0, 0]
    assert CircularGP(inner, ()).predict(x, return_var=False).var is None  # no angle output


@pytest.mark.parametrize(
    ("angle_inputs", "meta", "ok"),
    [
        ([0], [1, math.pi], True),  # the first input
        ([2], [1, math.pi], False),  # one past the last input (d = 2)
        ([-1], [1, math.pi], False),
        ([0, 0], [1, math.pi], False),  # twice
        ([1], [0, math.pi], True),  # the first output
        ([1], [-1, math.pi], True),  # no angular output
        ([1], [2, math.pi], False),  # one past the last output (P = 2)
        ([1], [-2, math.pi], False),
        ([1], [1, 0.5], True),  # any positive period
        ([1], [1, 0.0], False),
    ],
)
def test_circular_files_are_checked_at_each_bound(model, tmp_path: Path, angle_inputs, meta, ok) -> None:
    """A circular model file's angle inputs must be distinct inputs in ``[0, d)`` and its
    angle output in ``[-1, P)`` with a positive period; the error names the file and field."""
    path = save_gp(model, tmp_path / "c.npz")
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["angle_inputs"], arrays["angle_output"] = np.array(angle_inputs, float), np.array(meta, float)
    np.savez(tmp_path / "edit.npz", **arrays)
    if ok:
        back = load_gp(tmp_path / "edit.npz")
        assert back.angle_inputs == tuple(angle_inputs) and back.angle_output == meta[0]
        return
    field = "angle_inputs" if angle_inputs != [1] else "angle_output"
    with pytest.raises(ModelFileError, match=rf"edit\.npz.*{field}"):
        load_gp(tmp_path / "edit.npz")


def test_a_circular_files_angle_arrays_missing_or_misshapen_are_named_with_the_file(tmp_path: Path) -> None:
    """A circular GP file without its angle inputs or angle output, or with an angle output
    that is not ``(column, period)``, is refused with the file's name first."""
    rng = np.random.default_rng(4)
    x = rng.uniform(-1, 1, (30, 2))
    gp = fit_circular(x, np.c_[x[:, 0]], lambda a, b: fit_exact(a, b, max_iter=5), angle_inputs=(1,))
    with np.load(save_gp(gp, tmp_path / "good.npz")) as f:
        arrays = {k: f[k] for k in f.files}
    bad = tmp_path / "bad.npz"
    cases = [({k: v for k, v in arrays.items() if k != key}, f"missing array '{key}'")
             for key in ("angle_inputs", "angle_output")]  # fmt: skip
    cases.append(
        ({**arrays, "angle_output": np.array([-1.0, 1.0, 2.0])}, "angle_output must hold (column, period)")
    )
    from tests.hostile_files import load_refused

    for content, says in cases:
        np.savez(bad, **content)
        load_refused(bad, says)


def test_an_angle_output_needs_two_inner_outputs(tmp_path: Path) -> None:
    """An angular output is a ``(cos, sin)`` pair: a file whose inner GP has one output and
    declares an angular output is refused."""
    rng = np.random.default_rng(4)
    x = rng.uniform(-1, 1, (30, 1))
    gp = fit_circular(x, np.c_[x[:, 0]], lambda a, b: fit_exact(a, b, max_iter=5))
    path = save_gp(gp, tmp_path / "one.npz")
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["angle_output"] = np.array([0.0, math.pi])
    np.savez(tmp_path / "one.npz", **arrays)
    with pytest.raises(ModelFileError, match="angle_output"):
        load_gp(tmp_path / "one.npz")


def test_a_circular_enhanced_gp_round_trips_with_its_parametric_mean(tmp_path: Path) -> None:
    """The parametric mean and its Jacobian given to :func:`load_gp` reach the enhanced GP
    inside a circular one: the loaded model predicts what the fitted one did."""
    from estimator_service.gp import fit_enhanced

    rng = np.random.default_rng(5)
    x = np.c_[rng.uniform(-1, 1, 60), rng.uniform(-math.pi, math.pi, 60)]
    y = np.c_[3.0 * x[:, 0] + np.sin(x[:, 1])]

    def mean_fn(f):  # on the features [s, cos, sin]
        return 3.0 * f[:, :1]

    def mean_jac(f):
        return np.broadcast_to(np.array([[3.0, 0.0, 0.0]]), (len(f), 1, 3)).copy()

    gp = fit_circular(
        x,
        y,
        lambda a, b: fit_enhanced(a, b, mean_fn, fit_exact, mean_jacobian=mean_jac, max_iter=10),
        angle_inputs=(1,),
    )
    back = load_gp(save_gp(gp, tmp_path / "e.npz"), mean_function=mean_fn, mean_jacobian=mean_jac)
    q = np.array([[2.5, 0.3], [-3.0, -2.0]])  # far from the data: the parametric mean dominates
    a, b = gp.predict(q, return_jac=True), back.predict(q, return_jac=True)
    np.testing.assert_allclose(b.mean, a.mean, rtol=1e-12)
    np.testing.assert_allclose(b.jac, a.jac, rtol=1e-12)
    assert abs(b.jac[0, 0, 0] - 3.0) < 0.5


def test_the_innermost_gp_of_a_saved_model_loads_without_its_code(model, data, tmp_path: Path) -> None:
    """An EGP whose residual is a circular GP, as training saves it, then the circular GP and
    a plain exact GP: ``load_innermost_gp`` gives the exact GP inside (what a calibration
    fold refits on its own data), without the parametric mean the whole model needs; a
    damaged array inside is named with the file, by both loaders."""
    from estimator_service.gp import ExactGP, fit_enhanced, load_innermost_gp

    x, y = data
    rng = np.random.default_rng(1)
    base = lambda a, b: fit_exact(a, b, rng=rng, max_iter=5)  # noqa: E731
    egp = fit_enhanced(x, y, lambda q: 0.5 * q, lambda a, b: fit_circular(a, b, base, angle_inputs=(1,)))
    for whole, inner in ((egp, egp.residual.inner), (model, model.inner), (model.inner, model.inner)):
        back = load_innermost_gp(save_gp(whole, tmp_path / "m.npz"))
        assert isinstance(back, ExactGP)
        np.testing.assert_array_equal(back.alpha, inner.alpha)
        np.testing.assert_array_equal(back.theta, inner.theta)
    arrays = dict(np.load(save_gp(egp, tmp_path / "egp.npz"), allow_pickle=False))
    arrays["residual/inner/alpha"] = arrays["residual/inner/alpha"][:, :-1]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ModelFileError, match=r"bad\.npz.*alpha"):
        load_innermost_gp(tmp_path / "bad.npz")
    with pytest.raises(ModelFileError, match=r"bad\.npz.*alpha"):
        load_gp(tmp_path / "bad.npz", mean_function=lambda q: 0.5 * q)
