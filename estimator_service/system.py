"""What the estimator knows of a robot: its state, controls, sensors and step.

A :class:`System` replaces every robot constant in the estimator: the state dimension
and which components are angles, the control dimension, each sensor's observation layout
(with its angle outputs and rate), the filter step ``dt``, the groups a tracking run is
scored by and the prior a new service session starts from. It travels as JSON: inside
every flight file (``metadata["system"]``) and in every model folder (``system.json``),
so training, tracking, calibration and the service read it from the data instead of
assuming a blimp.

The paper's blimp is one description (:func:`estimator_service.models.blimp.blimp_system`);
``docs/your-robot.md`` writes another.

Observations of all sensors are concatenated into one vector ``z (m,)`` in sensor order;
a sensor delivers all its outputs or none at a step, so validity is kept per sensor
``(S,)`` in logs and expanded to per output ``(m,)`` for the filters
(:meth:`System.expand_valid`).
"""

from __future__ import annotations

import functools
import itertools
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimator_service.angles import wrap_angle, wrap_columns
from estimator_service.filters.common import Wrapping, distinct_indices
from estimator_service.frozen import normalise

__all__ = [
    "DescriptionError",
    "Group",
    "ModelSpec",
    "Sensor",
    "SensorType",
    "System",
    "wrap_angle",
    "wrap_columns",
]

FloatArray = NDArray[np.float64]
SYSTEM_FORMAT = "gpbf-system"
SYSTEM_VERSION = 1

MAX_CONTROL_DELAY = 60.0  # seconds: the longest command-to-effect delay a description may declare


class DescriptionError(ValueError):
    """A system description is malformed, or data does not fit it."""


def _is_name(text: object) -> bool:
    """Letters, digits, ``_`` and ``-`` (a sensor's, type's or parameter's name)."""
    return (
        isinstance(text, str) and bool(text) and all(c.isascii() and (c.isalnum() or c in "_-") for c in text)
    )


def _floats(values: object, n: int, field_name: str, where: str) -> tuple[float, ...]:
    """``n`` finite numbers >= 0 (empty: ``n`` zeros), or a DescriptionError naming the field."""
    try:
        vals = tuple(float(v) for v in values) or (0.0,) * n  # type: ignore[union-attr]
    except (TypeError, ValueError):
        vals = ()
    if len(vals) != n or not all(math.isfinite(v) and v >= 0 for v in vals):
        raise DescriptionError(f"{where}: '{field_name}' needs {n} finite numbers >= 0, got {values!r}")
    return vals


def _named_values(values: object, field_name: str, where: str) -> tuple[tuple[str, float], ...]:
    """A JSON object ``{name: number}`` as sorted pairs; a DescriptionError names the field."""
    if isinstance(values, Mapping):
        values = tuple(values.items())
    try:
        pairs = tuple((str(k), float(v)) for k, v in values)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise DescriptionError(f"{where}: '{field_name}' must map names to numbers, got {values!r}") from None
    bad = [k for k, v in pairs if not _is_name(k) or not math.isfinite(v)]
    if bad or len({k for k, _ in pairs}) != len(pairs):
        want = "distinct names and finite numbers"
        raise DescriptionError(f"{where}: '{field_name}' needs {want} (bad: {bad})")
    return tuple(sorted(pairs))


@dataclass(frozen=True)
class ModelSpec:
    """A parametric model the user brings: a Python callable named by import path.

    The system description names the code; :mod:`estimator_service.user_models` loads it,
    fits ``params`` to the training log and evaluates it. Naming code in a description
    means loading that description runs the code: load only descriptions you trust.

    Attributes
    ----------
    function
        ``"package.module:attribute"`` or the name of an entry point in the group
        ``gpbf.models``. A prediction model is called ``f(x, u, p, dt)`` with states
        ``x (M, n)``, controls ``u (M, k)``, parameters ``p`` (a mapping name -> float) and
        the step ``dt``, and returns the next states ``(M, n)``; a sensor model is called
        ``h(x, c, p)`` with the sensors' constants ``c`` (a mapping name -> ``(M,)``) and
        returns the readings ``(M, size)``.
    params
        ``(name, initial value)`` pairs, fitted by least squares on the training log.
    fixed
        ``(name, value)`` pairs passed to the function and never fitted.
    jacobian
        Optional callable of the same arguments returning ``d f / d x`` ``(M, n, n)`` (or
        ``d h / d x`` ``(M, size, n)``); central differences otherwise.
    noise
        Prediction models only, optional: a callable of the same arguments returning the
        *shape* of the process noise's standard deviation per step ``(M, n)`` (> 0), such as
        a term growing with the commanded speed plus a constant. Training fits one factor
        per state component by maximum likelihood; the ``param`` kind's noise is then
        ``factor**2 * shape**2`` at each state and control (without one it is constant). The
        GP kinds learn their noise from the residuals, as without a shape (the ``hetgp``
        kind's depends on the state and controls).
    """

    function: str
    params: tuple[tuple[str, float], ...] = ()
    fixed: tuple[tuple[str, float], ...] = ()
    jacobian: str | None = None
    noise: str | None = None

    def __post_init__(self) -> None:
        where = f"model {self.function!r}"
        for ref in (self.function, self.jacobian, self.noise):
            if ref is not None and not _is_reference(ref):
                raise DescriptionError(
                    f"{where}: {ref!r} is not 'package.module:attribute' or an entry-point name"
                )
        normalise(
            self,
            params=_named_values(self.params, "params", where),
            fixed=_named_values(self.fixed, "fixed", where),
        )
        clash = {k for k, _ in self.params} & {k for k, _ in self.fixed}
        if clash:
            raise DescriptionError(f"{where}: {sorted(clash)} both in 'params' and in 'fixed'")

    def to_dict(self) -> dict[str, Any]:
        out = {
            "function": self.function, "params": dict(self.params), "fixed": dict(self.fixed),
            "jacobian": self.jacobian,
        }  # fmt: skip
        return out if self.noise is None else out | {"noise": self.noise}

    @classmethod
    def from_dict(cls, d: object, where: str) -> ModelSpec:
        if not isinstance(d, Mapping) or "function" not in d:
            raise DescriptionError(f"{where}: a model needs a JSON object with 'function'")
        unknown = set(d) - {"function", "params", "fixed", "jacobian", "noise"}
        if unknown:
            raise DescriptionError(f"{where}: unknown model field(s) {sorted(unknown)}")
        return cls(
            str(d["function"]), d.get("params") or (), d.get("fixed") or (), d.get("jacobian"), d.get("noise")
        )


def _is_reference(ref: object) -> bool:
    """``module.path:attr.path`` or an entry-point name."""
    if not isinstance(ref, str):
        return False
    module, _, attr = ref.partition(":")
    parts = module.split(".") + (attr.split(".") if attr else [])
    return all(p.isidentifier() for p in parts) and (bool(attr) or ":" not in ref)


@dataclass(frozen=True)
class SensorType:
    """Sensors that share one model: the landmarks of a range-bearing camera, the cameras of
    one make. Each sensor of the type gives values for the type's ``constants`` (a
    landmark's surveyed position, a camera's pose); the type's model (a parametric
    ``model``, and the GP kinds' one GP) takes them as inputs beside the state, so every
    sensor's readings train it.

    Attributes
    ----------
    name
        Unique among the system's types.
    constants
        Names of the per-sensor constants (may be empty).
    model
        The parametric sensor model, or None (the GP kinds still share one GP).
    """

    name: str
    constants: tuple[str, ...] = ()
    model: ModelSpec | None = None

    def __post_init__(self) -> None:
        normalise(self, constants=tuple(str(c) for c in self.constants))
        if not _is_name(self.name):
            raise DescriptionError(f"sensor type name {self.name!r}: use letters, digits, '_' and '-'")
        if not all(map(_is_name, self.constants)) or len(set(self.constants)) != len(self.constants):
            raise DescriptionError(f"sensor type {self.name!r}: 'constants' must be distinct names")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> SensorType:
        model, where = d.get("model"), f"sensor type {d['name']!r}"
        spec = None if model is None else ModelSpec.from_dict(model, where)
        return cls(d["name"], tuple(d.get("constants") or ()), spec)

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "constants": list(self.constants),
            "model": None if self.model is None else self.model.to_dict(),
        }  # fmt: skip


@dataclass(frozen=True)
class Sensor:
    """One sensor's observation layout.

    Attributes
    ----------
    name
        Unique among the system's sensors (letters, digits, ``_`` and ``-``).
    outputs
        Names of the values it reports at once, e.g. ``("cx", "cy", "w", "h", "angle")``.
    periods
        Per output, the period of an angle output (e.g. ``pi`` for an ellipse orientation)
        or 0; empty means no angles.
    rate_hz
        Nominal frame rate (informational; frames arrive whenever they arrive).
    type
        The :class:`SensorType` whose model this sensor shares, or None (a model of its own).
    constants
        The values of the type's constants for this sensor, in the type's order.
    noise_floor
        Per output, the least noise standard deviation any model may claim (the sensor's
        datasheet or a measurement; output units); empty: no floor.
    """

    name: str
    outputs: tuple[str, ...]
    periods: tuple[float, ...] = ()
    rate_hz: float | None = None
    type: str | None = None
    constants: tuple[float, ...] = ()
    noise_floor: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        normalise(self, outputs=tuple(str(o) for o in self.outputs))
        if not _is_name(self.name):
            raise DescriptionError(f"sensor name {self.name!r}: use letters, digits, '_' and '-'")
        where = f"sensor {self.name!r}"
        if not self.outputs:
            raise DescriptionError(f"{where}: 'outputs' is empty")
        normalise(
            self,
            periods=_floats(self.periods, self.size, "periods", where),
            noise_floor=_floats(self.noise_floor, self.size, "noise_floor", where),
        )
        try:
            constants = tuple(float(c) for c in self.constants)
        except (TypeError, ValueError):
            constants = (math.nan,)
        if not all(math.isfinite(c) for c in constants):
            raise DescriptionError(f"{where}: 'constants' must be finite numbers, got {self.constants!r}")
        normalise(self, constants=constants)
        if self.rate_hz is not None and not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise DescriptionError(f"{where}: 'rate_hz' must be > 0, got {self.rate_hz}")

    @property
    def size(self) -> int:
        return len(self.outputs)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Sensor:
        return cls(
            d["name"], tuple(d["outputs"]), tuple(d.get("periods") or ()), d.get("rate_hz"), d.get("type"),
            tuple(d.get("constants") or ()), tuple(d.get("noise_floor") or ()),
        )  # fmt: skip

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name, "outputs": list(self.outputs), "periods": list(self.periods),
            "rate_hz": self.rate_hz, "type": self.type, "constants": list(self.constants),
            "noise_floor": list(self.noise_floor),
        }  # fmt: skip


@dataclass(frozen=True)
class Group:
    """State components scored together, in display units: ``error * factor`` (e.g. 1000 for
    metres shown in mm)."""

    name: str
    indices: tuple[int, ...]
    factor: float = 1.0


@dataclass(frozen=True)
class System:
    """A robot as the estimator sees it (see the module docstring).

    Attributes
    ----------
    name
        E.g. ``"blimp"``.
    state, controls
        Component names ``(n,)`` and ``(k,)``.
    sensors
        Observation layout, in the order of ``z``.
    dt
        Filter step (s): one prediction per ``dt``.
    state_periods
        Per state component, the period of an angle (``2 pi``) or 0; empty: no angles.
    circle_inputs
        State angles a GP sees as ``(cos, sin)`` (they wrap in use); default: every angle.
        The blimp lists only the yaw (roll and pitch stay small).
    groups
        Scoring groups; default one per state component.
    prior_mean, prior_std
        Where a service session starts before a reset (default 0 and 1).
    parametric
        Name of the parametric model family this robot has (``"blimp"``) or None; the
        ``param``, ``egp`` and ``hetgp`` model kinds need one.
    disturbed
        State components that unmodelled forces act on directly (a robot's velocities):
        the adaptive EKF and UKF inflate only their process noise
        (:mod:`estimator_service.filters.adaptive`); None: every component. A filter
        setting, not a data layout: two systems that differ only here are equal.
    prediction_model
        The user's parametric prediction model (:class:`ModelSpec`), or None.
    sensor_types
        Types whose model several sensors share (:class:`SensorType`).
    process_noise_floor
        Per state component, the least process-noise standard deviation per step any
        prediction model may claim; empty: no floor.
    control_delay
        Seconds from a command to its effect (``[0, 60]``): aligning an event log
        (:func:`estimator_service.events.align`) and a service session taking controls at
        their own times act on a command that much later.

    With ``prediction_model`` and a parametric model for every sensor's type the system has
    the ``param``, ``egp`` and ``hetgp`` kinds, as the blimp has with ``parametric="blimp"``
    (:attr:`has_parametric`).
    """

    name: str
    state: tuple[str, ...]
    controls: tuple[str, ...]
    sensors: tuple[Sensor, ...]
    dt: float
    state_periods: tuple[float, ...] = ()
    circle_inputs: tuple[int, ...] | None = None
    groups: tuple[Group, ...] = ()
    prior_mean: tuple[float, ...] = ()
    prior_std: tuple[float, ...] = ()
    parametric: str | None = None
    disturbed: tuple[int, ...] | None = field(default=None, compare=False)
    prediction_model: ModelSpec | None = None
    sensor_types: tuple[SensorType, ...] = ()
    process_noise_floor: tuple[float, ...] = ()
    control_delay: float = 0.0

    def __post_init__(self) -> None:
        fix = functools.partial(normalise, self)
        fix(state=tuple(str(s) for s in self.state))
        fix(controls=tuple(str(c) for c in self.controls))
        fix(sensors=tuple(self.sensors))
        n = len(self.state)
        fix(state_periods=tuple(float(p) for p in self.state_periods) or (0.0,) * n)
        if self.circle_inputs is None:
            fix(circle_inputs=tuple(i for i, p in enumerate(self.state_periods) if p > 0))
        fix(circle_inputs=tuple(int(i) for i in self.circle_inputs))
        if self.disturbed is not None:
            idx = distinct_indices(self.disturbed, n)
            if idx is None:
                raise DescriptionError(
                    f"system {self.name!r}: 'disturbed' must be distinct indices of the state "
                    f"(or null: all), got {self.disturbed!r}"
                )
            fix(disturbed=idx)
        fix(groups=tuple(self.groups) or tuple(Group(s, (i,)) for i, s in enumerate(self.state)))
        fix(prior_mean=tuple(float(v) for v in self.prior_mean) or (0.0,) * n)
        fix(prior_std=tuple(float(v) for v in self.prior_std) or (1.0,) * n)
        fix(sensor_types=tuple(self.sensor_types))
        where = f"system {self.name!r}"
        fix(process_noise_floor=_floats(self.process_noise_floor, n, "process_noise_floor", where))
        self._check()
        self._check_types()

    def _check(self) -> None:
        n, where = len(self.state), f"system {self.name!r}"
        if n == 0 or not self.controls or not self.sensors:
            raise DescriptionError(f"{where}: 'state', 'controls' and 'sensors' must be non-empty")
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise DescriptionError(f"{where}: 'dt' must be a finite time > 0, got {self.dt}")
        delay = self.control_delay
        if (
            isinstance(delay, bool)
            or not isinstance(delay, int | float)
            or not 0 <= delay <= MAX_CONTROL_DELAY
        ):
            raise DescriptionError(
                f"{where}: 'control_delay' must be seconds in [0, {MAX_CONTROL_DELAY:g}], got {delay!r}"
            )
        if len({s.name for s in self.sensors}) != len(self.sensors):
            raise DescriptionError(f"{where}: sensor names must be unique")
        for key in ("state_periods", "prior_mean", "prior_std"):
            vals = getattr(self, key)
            if len(vals) != n or not all(math.isfinite(v) for v in vals):
                raise DescriptionError(f"{where}: '{key}' needs {n} finite values, got {len(vals)}")
        if any(p < 0 for p in self.state_periods) or any(s <= 0 for s in self.prior_std):
            raise DescriptionError(f"{where}: 'state_periods' must be >= 0 and 'prior_std' > 0")
        if any(not 0 <= i < n or self.state_periods[i] <= 0 for i in self.circle_inputs or ()):
            raise DescriptionError(f"{where}: 'circle_inputs' must index angle components of the state")
        for g in self.groups:
            if not g.indices or any(not 0 <= i < n for i in g.indices):
                raise DescriptionError(f"{where}: group {g.name!r} indexes outside the state")

    def _check_types(self) -> None:
        where = f"system {self.name!r}"
        types = {t.name: t for t in self.sensor_types}
        if len(types) != len(self.sensor_types):
            raise DescriptionError(f"{where}: sensor type names must be unique")
        if self.parametric is not None and (self.prediction_model or any(t.model for t in types.values())):
            raise DescriptionError(
                f"{where}: 'parametric' ({self.parametric!r}) and your own models exclude each other"
            )
        for t in types.values():
            if t.model is not None and t.model.noise is not None:
                raise DescriptionError(
                    f"{where}: sensor type {t.name!r}: 'noise' shapes the prediction model's noise only; "
                    "a sensor's noise is its readings' spread (at least its 'noise_floor')"
                )
        layouts: dict[str, tuple] = {}
        for s in self.sensors:
            if s.type is None:
                if s.constants:
                    raise DescriptionError(f"{where}: sensor {s.name!r} has 'constants' but no 'type'")
                continue
            t = types.get(s.type)
            if t is None:
                raise DescriptionError(
                    f"{where}: sensor {s.name!r}: unknown type {s.type!r}; declare it in 'sensor_types'"
                )
            if len(s.constants) != len(t.constants):
                raise DescriptionError(
                    f"{where}: sensor {s.name!r} needs {len(t.constants)} 'constants' {list(t.constants)} "
                    f"of type {t.name!r}, got {len(s.constants)}"
                )
            if layouts.setdefault(t.name, (s.outputs, s.periods)) != (s.outputs, s.periods):
                raise DescriptionError(
                    f"{where}: sensors of type {t.name!r} must have the same outputs and periods"
                )

    # -- parametric models and sensor types ----------------------------------------------------------
    @property
    def has_parametric(self) -> bool:
        """Whether the ``param``, ``egp`` and ``hetgp`` kinds can be trained: the blimp's
        family, or the user's prediction model and a model for every sensor's type."""
        if self.parametric is not None:
            return True
        types = {t.name: t for t in self.sensor_types}
        return self.prediction_model is not None and all(
            s.type is not None and types[s.type].model is not None for s in self.sensors
        )

    def sensors_of_type(self) -> dict[str, tuple[int, ...]]:
        """``{type name: indices of its sensors}`` for every type some sensor has."""
        out: dict[str, list[int]] = {}
        for k, s in enumerate(self.sensors):
            if s.type is not None:
                out.setdefault(s.type, []).append(k)
        return {t: tuple(ks) for t, ks in out.items()}

    def sensor_type(self, name: str) -> SensorType:
        return next(t for t in self.sensor_types if t.name == name)

    # -- sizes and layout ---------------------------------------------------------------------------
    @property
    def state_dim(self) -> int:
        return len(self.state)

    @property
    def control_dim(self) -> int:
        return len(self.controls)

    @property
    def obs_dim(self) -> int:
        return sum(s.size for s in self.sensors)

    @property
    def n_sensors(self) -> int:
        return len(self.sensors)

    def sensor_slice(self, k: int) -> slice:
        """Where sensor ``k``'s outputs sit in ``z``."""
        return self._slices[k]

    @functools.cached_property
    def _slices(self) -> tuple[slice, ...]:
        starts = np.cumsum([0, *(s.size for s in self.sensors)])
        return tuple(slice(int(a), int(b)) for a, b in itertools.pairwise(starts))

    @property
    def obs_periods(self) -> FloatArray:
        """Period of each observation output ``(m,)`` (0: not an angle)."""
        return np.array([p for s in self.sensors for p in s.periods])

    @property
    def sensor_sizes(self) -> NDArray[np.intp]:
        return np.array([s.size for s in self.sensors])

    # -- the one rule from sensor frames to the filters' (z, valid) ------------------------------
    def expand_valid(self, valid: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Per-sensor validity ``(..., S)`` -> per-output ``(..., m)``."""
        return np.repeat(np.asarray(valid, dtype=bool), self.sensor_sizes, axis=-1)

    def frames(self, readings: Mapping[int, Sequence[float]]) -> tuple[FloatArray, NDArray[np.bool_]]:
        """``{sensor index: values}`` -> ``z (m,)`` (0 where missing) and ``valid (m,)``."""
        z, valid = np.zeros(self.obs_dim), np.zeros(self.obs_dim, dtype=bool)
        for k, values in readings.items():
            sl = self.sensor_slice(k)
            z[sl], valid[sl] = values, True
        return z, valid

    def state_error(self, estimate: FloatArray, truth: FloatArray) -> FloatArray:
        """``estimate - truth`` ``(..., n)`` with angle errors wrapped to ``[-p/2, p/2)``."""
        e = np.array(np.asarray(estimate) - np.asarray(truth), dtype=np.float64)
        return wrap_columns(e, np.asarray(self.state_periods))

    def obs_error(self, z: FloatArray, mean: FloatArray) -> FloatArray:
        """``z - mean`` ``(..., m)`` with angle outputs wrapped to ``[-p/2, p/2)``."""
        e = np.array(np.asarray(z) - np.asarray(mean), dtype=np.float64)
        return wrap_columns(e, self.obs_periods)

    def wrapping(self) -> Wrapping:
        """The filters' view of the angles (state and observation periods)."""
        return Wrapping(np.asarray(self.state_periods), self.obs_periods)

    # -- JSON ------------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": SYSTEM_FORMAT,
            "version": SYSTEM_VERSION,
            "name": self.name,
            "state": list(self.state),
            "controls": list(self.controls),
            "sensors": [s.to_dict() for s in self.sensors],
            "dt": self.dt,
            "state_periods": list(self.state_periods),
            "circle_inputs": list(self.circle_inputs or ()),
            "groups": [{"name": g.name, "indices": list(g.indices), "factor": g.factor} for g in self.groups],
            "prior_mean": list(self.prior_mean),
            "prior_std": list(self.prior_std),
            "parametric": self.parametric,
            "disturbed": None if self.disturbed is None else list(self.disturbed),
            "prediction_model": None if self.prediction_model is None else self.prediction_model.to_dict(),
            "sensor_types": [t.to_dict() for t in self.sensor_types],
            "process_noise_floor": list(self.process_noise_floor),
            "control_delay": self.control_delay,
        }

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], where: str = "system description") -> System:
        """Read :meth:`to_dict`'s output; :class:`DescriptionError` names the field at fault."""
        if not isinstance(d, Mapping):
            raise DescriptionError(f"{where}: expected a JSON object")
        if (
            d.get("format", SYSTEM_FORMAT) != SYSTEM_FORMAT
            or d.get("version", SYSTEM_VERSION) != SYSTEM_VERSION
        ):
            raise DescriptionError(f"{where}: not a version-{SYSTEM_VERSION} {SYSTEM_FORMAT} description")
        missing = [k for k in ("name", "state", "controls", "sensors", "dt") if k not in d]
        if missing:
            raise DescriptionError(f"{where}: missing field(s) {missing}")
        try:
            sensors = tuple(Sensor.from_dict(s) for s in d["sensors"])
            types = tuple(SensorType.from_dict(t) for t in d.get("sensor_types") or ())
            pm = d.get("prediction_model")
            prediction = None if pm is None else ModelSpec.from_dict(pm, "'prediction_model'")
            groups = tuple(
                Group(g["name"], tuple(int(i) for i in g["indices"]), float(g.get("factor", 1.0)))
                for g in d.get("groups") or ()
            )
            circle, disturbed = d.get("circle_inputs"), d.get("disturbed")
            return cls(
                str(d["name"]), tuple(d["state"]), tuple(d["controls"]), sensors, float(d["dt"]),
                tuple(d.get("state_periods") or ()), None if circle is None else tuple(circle), groups,
                tuple(d.get("prior_mean") or ()), tuple(d.get("prior_std") or ()), d.get("parametric"),
                disturbed, prediction, types, tuple(d.get("process_noise_floor") or ()),
                d.get("control_delay", 0.0),
            )  # fmt: skip
        except DescriptionError as exc:
            raise DescriptionError(f"{where}: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise DescriptionError(f"{where}: malformed ({type(exc).__name__}: {exc})") from None

    @classmethod
    def from_json(cls, text: str, where: str = "system description") -> System:
        try:
            return cls.from_dict(json.loads(text), where)
        except json.JSONDecodeError as exc:
            raise DescriptionError(f"{where}: not JSON ({exc})") from None

    def __repr__(self) -> str:
        sensors = ", ".join(f"{s.name}({s.size})" for s in self.sensors)
        return (
            f"System({self.name!r}, state={self.state_dim}, controls={self.control_dim}, "
            f"sensors=[{sensors}], dt={self.dt})"
        )
