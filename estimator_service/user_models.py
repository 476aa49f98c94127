"""Parametric models a user brings: Python callables named in the system description.

A robot's description (:class:`~estimator_service.system.System`) may name a prediction
model and, per sensor type, a sensor model (:class:`~estimator_service.system.ModelSpec`).
This module loads them (:func:`resolve`), fits their parameters to the training log by
least squares on one-step predictions and on readings, as the paper fits the blimp's
(:func:`fit_user_models`), stores the fitted values in ``parametric.json``
(:func:`save_user_models`, :func:`load_user_models`) and evaluates them as the filters'
:class:`~estimator_service.models.base.PredictionModel` and
:class:`~estimator_service.models.base.ObservationModel` (:class:`UserPrediction`,
:class:`UserSensorModel`). With them a robot has every model kind the blimp has:
``param`` is the fitted models, ``egp`` and ``hetgp`` a GP on their residual.

Contracts (``M`` rows, every array float64):

- prediction ``f(x (M, n), u (M, k), p, dt) -> (M, n)``: the next state;
- sensor ``h(x (M, n), c, p) -> (M, size)``: the readings, with ``c`` a mapping from the
  type's constant names to ``(M,)`` arrays (each row's sensor's values);
- optional Jacobians of the same arguments: ``(M, n, n)`` and ``(M, size, n)`` with
  respect to ``x``; central differences otherwise (angle outputs' differences wrapped).

``p`` maps each parameter name (fitted and fixed) to a float. The noise variance of each
output is the mean squared residual on the training log, never below the description's
noise floor. A prediction model may also name a noise shape ``g(x, u, p, dt) -> (M, n)``
(standard deviations up to one factor per state component, > 0): its noise variance is then
``factor**2 * g**2``, the factor fitted by maximum likelihood (``mean(residual**2 / g**2)``).
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from estimator_service.files import atomic_write_text
from estimator_service.models.base import ModelOutput, controls_for, sensor_rows, side_by_side
from estimator_service.reprs import short_repr
from estimator_service.system import ModelSpec, System, wrap_columns

__all__ = [
    "ENTRY_POINT_GROUP",
    "USER_MODELS_FILE",
    "FittedModel",
    "UserModelError",
    "UserPrediction",
    "UserSensorModel",
    "fit_user_models",
    "load_user_models",
    "resolve",
    "save_user_models",
    "user_models",
]

FloatArray = NDArray[np.float64]
ENTRY_POINT_GROUP = "gpbf.models"
USER_MODELS_FILE = "parametric.json"
USER_MODELS_FORMAT = "gpbf-user-models"
_REL_STEP = 1e-6  # central differences: step relative to max(1, |x|)
_FIT_EVALS = 200  # least-squares function evaluations per model
_MIN_VAR = 1e-12  # the least fitted noise variance (or noise-shape factor squared): never 0


class UserModelError(ValueError):
    """A user's model cannot be loaded, fitted or evaluated; the message names it."""


def resolve(ref: str) -> Callable[..., Any]:
    """The callable ``"package.module:attribute"`` names, or the entry point ``ref`` in the
    group :data:`ENTRY_POINT_GROUP`."""
    module, _, attr = ref.partition(":")
    try:
        if not attr:
            found = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP, name=ref)
            if not found:
                raise UserModelError(
                    f"model {ref!r}: no entry point of that name in group {ENTRY_POINT_GROUP!r}"
                )
            obj = next(iter(found)).load()
        else:
            obj = importlib.import_module(module)
            for part in attr.split("."):
                obj = getattr(obj, part)
    except UserModelError:
        raise
    except Exception as exc:  # an import runs the user's code: any error is theirs
        hint = " (is its folder on PYTHONPATH?)" if isinstance(exc, ModuleNotFoundError) else ""
        raise UserModelError(f"model {ref!r} cannot be loaded: {type(exc).__name__}: {exc}{hint}") from None
    if not callable(obj):
        raise UserModelError(f"model {ref!r} is not callable")
    return obj


def _checked(out: object, shape: tuple[int, ...], ref: str) -> FloatArray:
    """``out`` as a float64 array of ``shape``, finite, or a UserModelError naming ``ref``."""
    try:
        a = np.asarray(out, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise UserModelError(f"model {ref!r} returned something that is not numbers ({exc})") from None
    if a.shape != shape:
        raise UserModelError(f"model {ref!r} returned shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise UserModelError(f"model {ref!r} returned NaN or Inf")
    return a


def _call(fn: Callable[..., Any], ref: str, shape: tuple[int, ...], *args: object) -> FloatArray:
    try:
        out = fn(*args)
    except UserModelError:
        raise
    except Exception as exc:
        raise UserModelError(f"model {ref!r} raised {type(exc).__name__}: {exc}") from None
    return _checked(out, shape, ref)


def wrapped_jacobian(
    f: Callable[[FloatArray, NDArray[np.intp]], FloatArray], x: FloatArray, periods: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """``f`` at ``x (M, d)`` and its central-difference Jacobian ``(M, P, d)`` from one call.

    ``f(points (N, d), rows (N,))`` gets each point with the row of ``x`` it belongs to (so
    per-row arguments such as controls line up); differences of outputs with a period > 0
    (``periods (P,)``) are wrapped, so an angle output crossing its cut does not jump.
    """
    m, d = x.shape
    h = _REL_STEP * np.maximum(1.0, np.abs(x))  # (M, d)
    steps = h[:, :, None] * np.eye(d)  # (M, d, d)
    pts = np.concatenate([x[:, None, :], x[:, None, :] + steps, x[:, None, :] - steps], axis=1)
    rows = np.repeat(np.arange(m), 2 * d + 1)
    vals = f(pts.reshape(-1, d), rows).reshape(m, 2 * d + 1, -1)
    diff = wrap_columns(vals[:, 1 : d + 1] - vals[:, d + 1 :], periods)
    return vals[:, 0], (diff / (2.0 * h[:, :, None])).transpose(0, 2, 1)


@dataclass(frozen=True)
class FittedModel:
    """A :class:`~estimator_service.system.ModelSpec` with its fitted values.

    Attributes
    ----------
    spec
        What the description says.
    values
        Every parameter (fitted and fixed) by name.
    noise_var: (P,)
        Per output, the mean squared residual on the training log, at least the floor; with
        a noise shape (:attr:`ModelSpec.noise`), the factor squared that multiplies the
        shape's square (the floor is then applied to the product, when filtering).
    """

    spec: ModelSpec
    values: Mapping[str, float]
    noise_var: FloatArray

    def to_dict(self) -> dict[str, Any]:
        out = {
            "function": self.spec.function,
            "values": dict(self.values),
            "noise_var": self.noise_var.tolist(),
        }
        return out if self.spec.noise is None else out | {"noise": self.spec.noise}

    @classmethod
    def from_dict(cls, spec: ModelSpec, d: object, size: int, where: str) -> FittedModel:
        if not isinstance(d, Mapping) or d.get("function") != spec.function:
            raise UserModelError(f"{where}: fitted for another function than {spec.function!r}: retrain")
        if d.get("noise") != spec.noise:
            raise UserModelError(
                f"{where}: fitted with noise shape {d.get('noise')!r}, the description names "
                f"{spec.noise!r}: retrain"
            )
        values = d.get("values")
        names = {k for k, _ in spec.params} | {k for k, _ in spec.fixed}
        if not isinstance(values, Mapping) or set(values) != names:
            raise UserModelError(f"{where}: 'values' must name exactly {sorted(names)}")
        vals, var = {str(k): v for k, v in values.items()}, d.get("noise_var")
        ok = all(map(_is_finite_number, vals.values())) and isinstance(var, list) and len(var) == size
        if not (ok and all(_is_finite_number(v) and v > 0 for v in var)):
            raise UserModelError(
                f"{where}: values must be finite numbers and 'noise_var' {size} finite numbers > 0"
            )
        return cls(spec, {k: float(v) for k, v in vals.items()}, np.array(var, dtype=np.float64))


def _is_finite_number(v: object) -> bool:
    """A JSON number (not a bool) that is finite."""
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


@dataclass(frozen=True, eq=False)
class _FittedFunctions:
    """A fitted model with its function and optional Jacobian resolved once."""

    __repr__ = short_repr

    fitted: FittedModel

    def __post_init__(self) -> None:
        _ = self.function, self.jacobian, self.noise  # an unresolvable reference fails here, by name

    @functools.cached_property
    def function(self) -> Callable[..., Any]:
        return resolve(self.fitted.spec.function)

    @functools.cached_property
    def jacobian(self) -> Callable[..., Any] | None:
        ref = self.fitted.spec.jacobian
        return None if ref is None else resolve(ref)

    @functools.cached_property
    def noise(self) -> Callable[..., Any] | None:
        ref = self.fitted.spec.noise
        return None if ref is None else resolve(ref)


@dataclass(frozen=True, eq=False)
class UserPrediction(_FittedFunctions):
    """The user's prediction model as a :class:`~estimator_service.models.base.PredictionModel`:
    the mean state change ``f(x, u) - x`` (angles wrapped), the fitted noise variance (times
    the noise shape's square where the model names one)."""

    system: System

    @property
    def state_dim(self) -> int:
        return self.system.state_dim

    @property
    def control_dim(self) -> int:
        return self.system.control_dim

    def next_state(self, x: FloatArray, u: FloatArray) -> FloatArray:
        """``f(x (M, n), u (M, k))``: the next states ``(M, n)``."""
        args = (x, u, self.fitted.values, self.system.dt)
        return _call(self.function, self.fitted.spec.function, x.shape, *args)

    def noise_shape(self, x: FloatArray, u: FloatArray) -> FloatArray | None:
        """The noise shape ``g(x (M, n), u (M, k))`` ``(M, n)``, None without one."""
        if self.noise is None:
            return None
        return _noise_shape(self.noise, str(self.fitted.spec.noise), x, u, self.fitted.values, self.system.dt)

    def change(self, x: FloatArray, u: FloatArray) -> FloatArray:
        """Mean change ``(M, n)``, angles wrapped."""
        return self.system.state_error(self.next_state(x, controls_for(u, len(x))), x)

    def predict(self, x: FloatArray, u: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        x = np.asarray(x, dtype=np.float64)
        uu, n = controls_for(u, x.shape[0]), self.state_dim
        if not jac:
            mean, j = self.change(x, uu), None
        elif self.jacobian is not None:
            args = (x, uu, self.fitted.values, self.system.dt)
            mean = self.change(x, uu)
            j = _call(self.jacobian, self.fitted.spec.jacobian or "", (len(x), n, n), *args) - np.eye(n)
        else:
            periods = np.asarray(self.system.state_periods)
            nxt, jn = wrapped_jacobian(lambda q, rows: self.next_state(q, uu[rows]), x, periods)
            mean, j = self.system.state_error(nxt, x), jn - np.eye(n)
        shape = self.noise_shape(x, uu)
        noise = self.fitted.noise_var if shape is None else self.fitted.noise_var * shape * shape
        return ModelOutput(mean, np.broadcast_to(noise, mean.shape), j)


def _noise_shape(fn: Callable[..., Any], ref: str, x: FloatArray, u: FloatArray,
                 values: Mapping[str, float], dt: float) -> FloatArray:  # fmt: skip
    """A noise shape's values ``(M, n)`` at states ``x`` and controls ``u``: all > 0."""
    g = _call(fn, ref, x.shape, x, u, values, dt)
    if not np.all(g > 0):
        raise UserModelError(f"model {ref!r} returned a noise standard deviation <= 0")
    return g


@dataclass(frozen=True, eq=False)
class UserSensorModel(_FittedFunctions):
    """One sensor type's model over its sensors ``S`` (readings side by side, sensor by
    sensor: ``obs_dim = S * size``), as an
    :class:`~estimator_service.models.base.ObservationModel`.

    Attributes
    ----------
    fitted
        The type's fitted model.
    constant_names
        The type's constants.
    constants: (S, c)
        Each sensor's constants.
    periods: (size,)
        The type's output periods.
    state_dim
        ``n``.
    """

    constant_names: tuple[str, ...]
    constants: FloatArray
    periods: FloatArray
    state_dim: int

    @property
    def size(self) -> int:
        return len(self.periods)

    @property
    def obs_dim(self) -> int:
        return self.size * len(self.constants)

    def readings(self, x: FloatArray, c: FloatArray) -> FloatArray:
        """``h(x (N, n), c (N, c))``: readings ``(N, size)``."""
        args = (x, _named_columns(self.constant_names, c), self.fitted.values)
        return _call(self.function, self.fitted.spec.function, (len(x), self.size), *args)

    def readings_and_jacobian(self, x: FloatArray, c: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Readings ``(N, size)`` and ``d h / d x`` ``(N, size, n)``."""
        if self.jacobian is None:
            return wrapped_jacobian(lambda q, rows: self.readings(q, c[rows]), x, self.periods)
        args = (x, _named_columns(self.constant_names, c), self.fitted.values)
        jac = _call(self.jacobian, self.fitted.spec.jacobian or "", (len(x), self.size, x.shape[1]), *args)
        return self.readings(x, c), jac

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        s = len(self.constants)
        xs, cs = sensor_rows(np.asarray(x, dtype=np.float64), self.constants)
        mean, j = self.readings_and_jacobian(xs, cs) if jac else (self.readings(xs, cs), None)
        mean = side_by_side(mean, s)
        j = None if j is None else side_by_side(j, s)
        return ModelOutput(mean, np.broadcast_to(np.tile(self.fitted.noise_var, s), mean.shape), j)


def _named_columns(names: Sequence[str], c: FloatArray) -> dict[str, FloatArray]:
    """The constants ``c (N, c)`` as the mapping a sensor model receives: name -> ``(N,)``."""
    return {name: c[:, i] for i, name in enumerate(names)}


# -- fitting ------------------------------------------------------------------------------------


def _least_squares(
    spec: ModelSpec, residual: Callable[[Mapping[str, float]], FloatArray]
) -> dict[str, float]:
    """The spec's parameters minimising ``|residual(values)|^2`` (fixed ones held)."""
    fixed = dict(spec.fixed)
    names = [k for k, _ in spec.params]
    if not names:
        return fixed

    def values(z: FloatArray) -> dict[str, float]:
        return {**fixed, **{k: float(v) for k, v in zip(names, z, strict=True)}}

    start = np.array([v for _, v in spec.params])
    res = least_squares(lambda z: residual(values(z)).ravel(), start, method="trf", max_nfev=_FIT_EVALS)
    return values(res.x)


def _noise_var(err: FloatArray, floor: Sequence[float]) -> FloatArray:
    """Mean squared residual per output ``(P,)``, at least ``floor**2`` (and > 0)."""
    return np.maximum(np.mean(err * err, axis=0), np.maximum(np.square(floor), _MIN_VAR))


def fit_prediction(system: System, x: FloatArray, u: FloatArray, x_next: FloatArray) -> FittedModel:
    """The prediction model's parameters fitted to transitions ``x (T, n), u (T, k) ->
    x_next (T, n)``: residuals per state scaled by the state change's spread."""
    spec = system.prediction_model
    if spec is None:
        raise UserModelError(f"system {system.name!r} names no 'prediction_model'")
    fn = resolve(spec.function)
    scale = np.maximum(system.state_error(x_next, x).std(axis=0), 1e-9)

    def error(vals: Mapping[str, float]) -> FloatArray:
        return system.state_error(_call(fn, spec.function, x.shape, x, u, vals, system.dt), x_next)

    values = _least_squares(spec, lambda vals: error(vals) / scale)
    err = error(values)
    if spec.noise is None:
        return FittedModel(spec, values, _noise_var(err, system.process_noise_floor))
    g = _noise_shape(resolve(spec.noise), spec.noise, x, u, values, system.dt)
    factor2 = np.maximum(np.mean((err / g) ** 2, axis=0), _MIN_VAR)
    return FittedModel(spec, values, factor2)


def fit_sensor_type(
    system: System, type_name: str, x: FloatArray, c: FloatArray, z: FloatArray
) -> FittedModel:
    """A sensor type's model fitted to states ``x (T, n)``, constants ``c (T, c)`` and
    readings ``z (T, size)`` of all its sensors; the floor is the largest of its sensors'."""
    stype = system.sensor_type(type_name)
    spec = stype.model
    if spec is None:
        raise UserModelError(f"sensor type {type_name!r} has no 'model'")
    ks = system.sensors_of_type()[type_name]
    periods = np.asarray(system.sensors[ks[0]].periods)
    floor = np.max([system.sensors[k].noise_floor for k in ks], axis=0)
    fn = resolve(spec.function)
    scale = np.maximum(z.std(axis=0), 1e-9)

    consts = _named_columns(stype.constants, c)

    def error(vals: Mapping[str, float]) -> FloatArray:
        return wrap_columns(_call(fn, spec.function, z.shape, x, consts, vals) - z, periods)

    values = _least_squares(spec, lambda vals: error(vals) / scale)
    return FittedModel(spec, values, _noise_var(error(values), floor))


@dataclass(frozen=True)
class UserModels:
    """A system's fitted parametric models: the prediction and one per sensor type."""

    prediction: FittedModel
    sensor_types: Mapping[str, FittedModel]


def fit_user_models(
    system: System,
    transitions: tuple[FloatArray, FloatArray, FloatArray],
    readings: Mapping[str, tuple[FloatArray, FloatArray, FloatArray]],
) -> UserModels:
    """Every parametric model of ``system``: the prediction on ``transitions (x, u,
    x_next)`` and each type on ``readings[type] (x, c, z)``."""
    types = {t: fit_sensor_type(system, t, *readings[t]) for t in system.sensors_of_type()}
    return UserModels(fit_prediction(system, *transitions), types)


def save_user_models(models: UserModels, path: str | os.PathLike[str]) -> Path:
    """Write the fitted values and noise variances as JSON (atomically)."""
    doc = {
        "format": USER_MODELS_FORMAT, "version": 1, "prediction": models.prediction.to_dict(),
        "sensor_types": {t: m.to_dict() for t, m in models.sensor_types.items()},
    }  # fmt: skip
    return atomic_write_text(path, json.dumps(doc, indent=1))


def load_user_models(path: str | os.PathLike[str], system: System) -> UserModels:
    """Read :func:`save_user_models`' file for ``system`` (checked against its description)."""
    where = f"parametric model file {os.fspath(path)!r}"
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise UserModelError(f"{where}: cannot be read ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != USER_MODELS_FORMAT:
        raise UserModelError(f"{where}: not a {USER_MODELS_FORMAT} file")
    assert system.prediction_model is not None  # has_parametric was checked by the caller
    pred = FittedModel.from_dict(system.prediction_model, doc.get("prediction"), system.state_dim, where)
    types = doc.get("sensor_types")
    if not isinstance(types, dict) or set(types) != set(system.sensors_of_type()):
        raise UserModelError(f"{where}: 'sensor_types' must hold {sorted(system.sensors_of_type())}")
    fitted = {}
    for name, ks in system.sensors_of_type().items():
        spec = system.sensor_type(name).model
        assert spec is not None
        fitted[name] = FittedModel.from_dict(
            spec, types[name], system.sensors[ks[0]].size, f"{where}, type {name!r}"
        )
    return UserModels(pred, fitted)


def user_models(models: UserModels, system: System) -> tuple[UserPrediction, dict[str, UserSensorModel]]:
    """The filters' models of ``models``: the prediction and one observation model per type
    (its sensors side by side, in the system's sensor order)."""
    sensors = {}
    for name, ks in system.sensors_of_type().items():
        sensors[name] = UserSensorModel(
            models.sensor_types[name], system.sensor_type(name).constants,
            np.array([system.sensors[k].constants for k in ks], dtype=np.float64).reshape(len(ks), -1),
            np.asarray(system.sensors[ks[0]].periods), system.state_dim,
        )  # fmt: skip
    return UserPrediction(models.prediction, system), sensors
