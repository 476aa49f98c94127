"""Noise calibration: prediction and observation models whose noise variance is scaled.

A GP's predictive variance (and the parametric model's residual variance) describes
one-step errors of independent transitions. A filter chains them, and unmodelled effects
that persist over many steps (on the simulated blimp: wind gusts with a 3 s correlation
time) make every filter overconfident. Per model kind and state output, a scale chosen on
blocks of the training flight with models fitted without them (cross-fitting,
:mod:`estimator_service.crossfit`; :func:`estimator_service.calibrate.calibrate_process` and
:func:`estimator_service.calibrate.calibrate_noise`) corrects that; it is stored beside
the models in ``calibration.json`` (``noise_scale`` times ``process_noise_scale``) and
applied by :func:`estimator_service.factory.load_models`.

Observation GPs are overconfident in another way: their variance is smallest on their own
training frames, and held-out states lie between them (measured:
docs/measurements.md#observation-gp-overconfidence).
A particle filter weights by that likelihood, so a too-narrow one leaves a handful of
particles (:func:`estimator_service.calibrate.calibrate_observation` measures it on blocks of
the training flight, with observation models fitted without them; one scale per output).

The scaled process variance is capped per output at :data:`CEILING_FACTOR` times the
variance of that state output over the training flights (``process_variance_ceiling``,
written by :func:`estimator_service.training.train_models`). One prediction that makes the
belief wider than everything the state did in training says the model knows less than
nothing (the law of total variance bounds the mean conditional variance by the marginal
one); the matching gets far past that only when an output's errors grow with its noise,
and the EKF's linearisation then fails. A factor of 10 rather than 1 (measured:
docs/measurements.md#process-variance-ceiling).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from estimator_service.files import atomic_write_text
from estimator_service.frozen import normalise
from estimator_service.models.base import ModelOutput, ObservationModel, PredictionModel, observe_columns
from estimator_service.reprs import short_repr

__all__ = [
    "ADAPTIVE",
    "CALIBRATION_FILE",
    "CEILING_FACTOR",
    "NIS_REFERENCE",
    "PROCESS_CEILING",
    "NoiseScaledObservation",
    "NoiseScaledPrediction",
    "calibration_choices",
    "read_adaptive",
    "read_details",
    "read_nis_reference",
    "read_noise_scales",
    "read_observation_scales",
    "read_process_ceiling",
    "read_process_scales",
    "write_noise_scales",
    "write_process_ceiling",
]

FloatArray = NDArray[np.float64]
CALIBRATION_FILE = "calibration.json"
NOISE_SCALE = "noise_scale"  # calibration.json key: {kind: process-noise factor}
OBSERVATION_SCALES = "observation_noise_scale"  # calibration.json key: {kind: (m,) factors}
PROCESS_SCALES = "process_noise_scale"  # calibration.json key: {kind: (n,) factors}
PROCESS_CEILING = "process_variance_ceiling"  # calibration.json key: (n,) variances
NIS_REFERENCE = "nis_reference"  # calibration.json key: {kind: the calibrated EKF's mean NIS/dof}
ADAPTIVE = "adaptive"  # calibration.json key: {kind: whether the held-out blocks chose the adaptive filter}
CEILING_FACTOR = 10.0  # the ceiling in units of each state output's variance in training


@dataclass(frozen=True)
class NoiseScaledPrediction:
    """``inner`` with its noise variance multiplied by ``scale``, capped per output at
    ``ceiling (n,)`` when given and raised to ``floor (n,)`` (variances: the system's
    process-noise floor) when given (mean and Jacobian as is).

    ``scale`` is one number, ``(n,)``, or ``(B, n)``: one row per query row of every call,
    which must then have ``B`` rows (``B`` noise settings tracked side by side by
    :func:`~estimator_service.tracking.track_many`)."""

    __repr__ = short_repr

    inner: PredictionModel
    scale: float | FloatArray
    ceiling: FloatArray | None = None
    floor: FloatArray | None = None

    def __post_init__(self) -> None:
        s, n = np.asarray(self.scale, dtype=np.float64), self.inner.state_dim
        if s.ndim > 2 or (s.ndim >= 1 and s.shape[-1] != n) or not np.all(np.isfinite(s) & (s > 0)):
            raise ValueError(f"noise scale must be finite and > 0, one number, {n} or rows of {n}, got {s!r}")
        if self.ceiling is not None:
            normalise(self, ceiling=_ceiling(self.ceiling, n))

    @property
    def state_dim(self) -> int:
        return self.inner.state_dim

    @property
    def control_dim(self) -> int:
        return self.inner.control_dim

    def predict(self, x: FloatArray, u: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        """``inner.predict`` with ``min(var * scale, ceiling)``: mean ``(M, n)``, var ``(M, n)``,
        jac ``(M, n, n)``."""
        out = self.inner.predict(x, u, jac=jac, var=var)
        var_out = out.var * _per_row(self.scale, out.var)
        if self.ceiling is not None:
            var_out = np.minimum(var_out, self.ceiling)
        return ModelOutput(out.mean, _floored(var_out, self.floor), out.jac)


class RowMismatch(ValueError):
    """A noise scale with one row per query row met a call with another number of rows."""


def _per_row(scale: float | FloatArray, var: FloatArray) -> float | FloatArray:
    """``scale`` checked against the call's ``var (M, k)``: a ``(B, k)`` scale needs ``M = B``."""
    if np.ndim(scale) == 2 and np.shape(scale)[0] != var.shape[0]:
        raise RowMismatch(
            f"a noise scale of {np.shape(scale)[0]} rows needs as many query rows, got {var.shape[0]}"
        )
    return scale


def _floored(var: FloatArray, floor: FloatArray | None) -> FloatArray:
    """``max(var, floor)`` per output (``var`` as is without a floor)."""
    return var if floor is None else np.maximum(var, floor)


def _ceiling(value: object, n: int) -> FloatArray:
    """``value`` as ``n`` variances > 0, ``inf`` (JSON ``null``) where an output has no
    ceiling (a ValueError naming the field otherwise)."""
    items = [np.inf if v is None else v for v in value] if isinstance(value, list) else value
    try:
        c = np.asarray(items, dtype=np.float64)
    except (TypeError, ValueError):
        c = np.full(n, np.nan)  # not numbers: refused below with the field's name
    if c.shape != (n,) or not np.all(~np.isnan(c) & (c > 0)):
        raise ValueError(f"{PROCESS_CEILING} must be {n} variances > 0 (null: none), got {value!r}")
    return c


@dataclass(frozen=True)
class NoiseScaledObservation:
    """``inner`` with its noise variance multiplied per output by ``scale (m,)`` (or ``(B,
    m)``, one row per query row as for :class:`NoiseScaledPrediction`) and raised to ``floor
    (m,)`` (variances: the sensors' noise floors) when given."""

    __repr__ = short_repr

    inner: ObservationModel
    scale: FloatArray
    floor: FloatArray | None = None

    def __post_init__(self) -> None:
        s = np.asarray(self.scale, dtype=np.float64)
        if s.ndim not in (1, 2) or s.shape[-1] != self.inner.obs_dim or not np.all(np.isfinite(s) & (s > 0)):
            raise ValueError(
                f"observation noise scale must be {self.inner.obs_dim} finite numbers > 0, got {self.scale!r}"
            )
        normalise(self, scale=s)

    @property
    def state_dim(self) -> int:
        return self.inner.state_dim

    @property
    def obs_dim(self) -> int:
        return self.inner.obs_dim

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        """``inner.observe`` with ``var * scale``: mean ``(M, m)``, var ``(M, m)``, jac ``(M, m, n)``."""
        out = self.inner.observe(x, jac=jac, var=var)
        return ModelOutput(out.mean, _floored(out.var * _per_row(self.scale, out.var), self.floor), out.jac)

    def observe_columns(self, x: FloatArray, cols: NDArray[np.intp], *, jac: bool = False,
                        var: bool = True) -> ModelOutput:  # fmt: skip
        """Columns ``cols`` of :meth:`observe`, evaluating only what the inner model needs."""
        out = observe_columns(self.inner, x, cols, jac=jac, var=var)
        scale = _per_row(self.scale, out.var)[..., cols]
        floor = None if self.floor is None else self.floor[cols]
        return ModelOutput(out.mean, _floored(out.var * scale, floor), out.jac)


def _read(folder: str | os.PathLike[str]) -> dict:
    path = Path(folder) / CALIBRATION_FILE
    if not path.exists():
        return {}
    try:
        raw = json.loads(path.read_text())
        if not isinstance(raw, dict):
            raise TypeError("not an object")
        return raw
    except (ValueError, TypeError) as e:
        raise ValueError(f"{os.fspath(path)!r}: expected a JSON object ({e})") from e


def _section(folder: str | os.PathLike[str], key: str, convert, want: str) -> dict[str, FloatArray]:
    """``{kind: convert(value)}`` of one section of ``folder/calibration.json``, each value
    checked to be finite and > 0."""
    path = os.fspath(Path(folder) / CALIBRATION_FILE)
    try:
        out = {str(k): convert(v) for k, v in _read(folder).get(key, {}).items()}
    except (ValueError, TypeError, AttributeError) as e:
        raise ValueError(f"{path!r}: expected {{'{key}': {want}}} ({e})") from e
    bad = {k: v.tolist() for k, v in out.items() if not np.all(np.isfinite(v) & (v > 0))}
    if bad:
        raise ValueError(f"{path!r}: {key} values must be finite and > 0, got {bad}")
    return out


def read_noise_scales(folder: str | os.PathLike[str]) -> dict[str, float]:
    """``{model kind: process-noise scale}`` from ``folder/calibration.json`` (empty when
    there is none)."""
    scales = _section(folder, NOISE_SCALE, lambda v: np.array(float(v)), "{kind: number}")
    return {k: float(v) for k, v in scales.items()}


def read_observation_scales(folder: str | os.PathLike[str]) -> dict[str, FloatArray]:
    """``{model kind: observation-noise scales (m,)}`` from ``folder/calibration.json``."""
    return _section(
        folder,
        OBSERVATION_SCALES,
        lambda v: np.array(v, dtype=np.float64).reshape(-1),
        "{kind: [numbers]}",
    )


def read_nis_reference(folder: str | os.PathLike[str]) -> dict[str, float]:
    """``{model kind: mean NIS/dof}`` of the calibrated EKF on the held-out calibration
    blocks (the adaptive filters' reference level,
    :mod:`estimator_service.filters.adaptive`); empty for models calibrated before it was
    stored."""
    ref = _section(folder, NIS_REFERENCE, lambda v: np.array(float(v)), "{kind: number}")
    return {k: float(v) for k, v in ref.items()}


def read_adaptive(folder: str | os.PathLike[str]) -> dict[str, bool]:
    """``{model kind: whether its EKF and UKF adapt their process noise}`` as the cross-fitted
    calibration chose by held-out log-likelihood; empty where it did not choose (the
    filters' default then holds)."""
    flags = _read(folder).get(ADAPTIVE, {})
    if not (isinstance(flags, dict) and all(isinstance(v, bool) for v in flags.values())):
        raise ValueError(f"{CALIBRATION_FILE}: '{ADAPTIVE}' must be {{kind: true or false}}")
    return dict(flags)


def read_details(folder: str | os.PathLike[str]) -> dict:
    """The ``details`` section of ``folder/calibration.json`` (what each calibration measured)."""
    return _read(folder).get("details", {})


def calibration_choices(folder: str | os.PathLike[str]) -> dict[str, dict]:
    """Per kind, whether its cross-fitted calibration was applied, its family and factor (and
    for the second pass's scales the candidate they were moved ``from``) and the held-out
    mean log-likelihood with and without it (empty without a cross-fitted calibration)."""
    out = {}
    for kind, d in read_details(folder).get("noise", {}).items():
        c = d.get("likelihood") if isinstance(d, dict) else None
        if c:
            mll = (round(c["chosen"]["mll"], 4), round(c["uncalibrated"]["mll"], 4))
            keep = {k: c[k] for k in ("applied", "family", "factor", "reason")}
            if c.get("from"):  # the second pass's scales: moved from this first-pass candidate
                keep["from"] = c["from"]
            out[kind] = {**keep, "heldout_mll": mll[0], "uncalibrated_mll": mll[1]}
    return out


def read_process_scales(folder: str | os.PathLike[str]) -> dict[str, FloatArray]:
    """``{model kind: per-output process-noise scales (n,)}`` from ``folder/calibration.json``
    (they multiply the one-step variances before the kind's ``noise_scale``)."""
    return _section(
        folder,
        PROCESS_SCALES,
        lambda v: np.array(v, dtype=np.float64).reshape(-1),
        "{kind: [numbers]}",
    )


def read_process_ceiling(folder: str | os.PathLike[str], n: int) -> FloatArray | None:
    """The per-output process-variance ceiling ``(n,)`` of ``folder/calibration.json``, or
    None when it has none (models trained before it existed)."""
    raw = _read(folder).get(PROCESS_CEILING)
    if raw is None:
        return None
    try:
        return _ceiling(raw, n)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{os.fspath(Path(folder) / CALIBRATION_FILE)!r}: {e}") from e


def write_process_ceiling(folder: str | os.PathLike[str], states: FloatArray) -> Path:
    """Store :data:`CEILING_FACTOR` times the variance of each state output over the training
    ``states (T, n)`` as the process-variance ceiling of ``folder/calibration.json`` (merged,
    written atomically); an output that never varied in training gets none (``null``)."""
    variance = CEILING_FACTOR * np.var(np.asarray(states, dtype=np.float64), axis=0)
    stored = [float(v) if v > 0 else None for v in variance]
    _ceiling(stored, variance.shape[0])  # a NaN state is refused before anything is written
    body = {**_read(folder), PROCESS_CEILING: stored}
    return atomic_write_text(Path(folder) / CALIBRATION_FILE, json.dumps(body, indent=2, default=_plain))


def write_noise_scales(
    folder: str | os.PathLike[str],
    scales: dict[str, float],
    observation: dict[str, FloatArray] | None = None,
    process: dict[str, FloatArray] | None = None,
    nis_reference: dict[str, float] | None = None,
    adaptive: dict[str, bool] | None = None,
    **details: object,
) -> Path:
    """Merge process-noise ``scales``, per-output ``observation`` and ``process`` scales and
    the ``nis_reference`` levels into ``folder/calibration.json`` (written to a temporary
    file, then renamed)."""
    path = Path(folder) / CALIBRATION_FILE
    merged = {**read_noise_scales(folder), **{k: float(v) for k, v in scales.items()}}
    levels = {**read_nis_reference(folder), **{k: float(v) for k, v in (nis_reference or {}).items()}}
    bad = {k: v for k, v in levels.items() if not (math.isfinite(v) and v > 0)}
    if bad:  # refused before anything is written
        raise ValueError(f"{NIS_REFERENCE} values must be finite and > 0, got {bad}")
    vectors = {}
    for key, new, read in ((OBSERVATION_SCALES, observation, read_observation_scales),
                           (PROCESS_SCALES, process, read_process_scales)):  # fmt: skip
        vectors[key] = {k: v.tolist() for k, v in read(folder).items()}
        vectors[key].update({k: np.asarray(v, dtype=np.float64).tolist() for k, v in (new or {}).items()})
    old = _read(folder)  # other sections (the process-variance ceiling) are kept as they are
    body = {**old, NOISE_SCALE: merged, **vectors, "details": {**old.get("details", {}), **details}}
    if levels:
        body[NIS_REFERENCE] = levels
    if adaptive:
        body[ADAPTIVE] = {**old.get(ADAPTIVE, {}), **{k: bool(v) for k, v in adaptive.items()}}
    return atomic_write_text(path, json.dumps(body, indent=2, default=_plain))


def _plain(o: object) -> object:
    return np.asarray(o).tolist()
