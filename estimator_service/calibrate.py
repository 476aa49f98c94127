"""Noise calibration of trained models on a block of a training flight that the models
being calibrated were not trained on (:mod:`estimator_service.crossfit` fits them without
it).

:func:`calibrate_observation` scales each observation output by its mean squared
standardised residual on the block's frames, :func:`calibrate_process` each state output
of the prediction model by its one-step residual on the block's transitions (the two that
cross-fitting uses); :func:`calibrate_noise` then matches each output's process noise to the
EKF's errors there and widens the noise until the 3-sigma bounds hold as often as a Gaussian
belief's (:mod:`estimator_service.matching`). All write ``calibration.json`` beside the models
(:mod:`estimator_service.models.calibration`). Angle outputs and the state dimension come
from the flight's :class:`~estimator_service.system.System`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from estimator_service.flight import Flight
from estimator_service.matching import (
    MATCH_ROUNDS,
    MATCH_STEP,
    Block,
    coverage,
    covering_factor,
    match_scales,
)
from estimator_service.models.calibration import (
    read_observation_scales,
    read_process_ceiling,
    read_process_scales,
)

__all__ = [
    "NOISE_DETAILS",
    "NoiseCalibration",
    "calibrate_noise",
    "calibrate_observation",
    "calibrate_process",
    "calibration_rows",
    "geometric_mean",
    "noise_from_blocks",
    "without_frames",
    "write_calibration",
]

FloatArray = NDArray[np.float64]
NOISE_DETAILS = "noise"  # calibration.json details: what each kind's noise calibration measured


def calibration_rows(flight: Flight, seconds: float) -> slice:
    """The first ``seconds`` of ``flight``, at most a quarter of it (empty for 0)."""
    n = round(seconds / flight.dt) if seconds > 0 else 0
    return slice(0, min(n, len(flight) // 4))


def without_frames(flight: Flight, rows: slice) -> Flight:
    """``flight`` with no sensor readings in ``rows`` (states, controls and transitions kept)."""
    return flight.without_readings(rows)


def calibrate_observation(
    flight: Flight, folder: Path, kinds: Sequence[str], *, rows: slice,
    floor: float = 1.0, cap: float = 100.0, min_frames: int = 10,
) -> dict[str, FloatArray]:  # fmt: skip
    """Per kind and output, the mean squared standardised residual ``(z - mean)^2 / var``
    of the observation model over the frames in ``rows`` of ``flight`` (which no
    observation model was trained on), clipped to ``[floor, cap]`` (1 where an output has
    fewer than ``min_frames`` frames); written to ``folder/calibration.json``.

    A consistent model gives 1. The committed paper-size run (exact GP, four folds) got
    1.3-6.7 for camera 1's ellipse position and 1.0-5.1 for the other outputs.
    """
    from estimator_service.factory import load_models
    from estimator_service.models.calibration import write_noise_scales

    fl = flight.select(np.arange(len(flight))[rows])
    valid = fl.expand_valid()
    count = valid.sum(axis=0)
    chosen = {}
    for kind in kinds:
        _, obs = load_models(folder, kind, calibrated=False, check=False)
        out = obs.observe(fl.state)
        r = fl.system.obs_error(fl.z, out.mean)
        with np.errstate(divide="ignore", invalid="ignore"):
            z2 = np.where(valid, r * r / out.var, 0.0).sum(axis=0) / np.maximum(count, 1)
        z2 = np.nan_to_num(z2, nan=cap, posinf=cap)  # a broken output gets the widest scale
        chosen[kind] = np.clip(np.where(count >= min_frames, z2, 1.0), floor, cap)
    write_noise_scales(folder, {}, observation=chosen, observation_frames=count.tolist())
    return chosen


def calibrate_process(
    flight: Flight, folder: Path, kinds: Sequence[str], *, rows: slice,
    floor: float = 0.1, cap: float = 1e4,
) -> dict[str, FloatArray]:  # fmt: skip
    """Per kind and state output, the mean squared standardised one-step error
    ``(dx - mean)^2 / var`` of the prediction model over the transitions in ``rows`` of
    ``flight`` (which no model was trained on), clipped to ``[floor, cap]``; written to
    ``folder/calibration.json`` as ``process_noise_scale``.

    A consistent model gives 1 per output; a GP's variance is smallest at its own training
    points, so scales chosen on them come out too low (paper-size GP: 0.73 on its training
    transitions, 1.06 on the others of the same minute).
    """
    from estimator_service.factory import load_models
    from estimator_service.models.calibration import write_noise_scales

    fl = flight.select(np.arange(len(flight))[rows])
    x, u, x_next = fl.transitions()
    wrap = fl.system.wrapping()
    chosen = {}
    for kind in kinds:
        pred, _ = load_models(folder, kind, calibrated=False, check=False)
        out = pred.predict(x, u)
        r = wrap.state_diff(fl.system.state_error(x_next, x) - out.mean)
        with np.errstate(divide="ignore", invalid="ignore"):
            z2 = np.mean(r * r / out.var, axis=0) if len(x) else np.ones(x.shape[1])
        chosen[kind] = np.clip(np.nan_to_num(z2, nan=cap, posinf=cap), floor, cap)
    write_noise_scales(folder, {}, process=chosen, process_transitions=len(x))
    return chosen


@dataclass(frozen=True)
class NoiseCalibration:
    """One kind's noise calibration on held-out rows: the matched process scales
    ``matched (n,)``, the observation scales ``observation (m,)`` (None: the models carry
    none), both before the 3-sigma coverage ``factor``, what was measured, and the EKF's
    mean NIS/dof with these noises there (``nis_level``; NaN: no update)."""

    matched: FloatArray
    observation: FloatArray | None
    factor: float
    details: dict
    nis_level: float = math.nan

    @property
    def process(self) -> FloatArray:
        """The process scales to apply ``(n,)``: matched, times the factor."""
        return self.matched * self.factor

    @property
    def scaled_observation(self) -> FloatArray | None:
        """The observation scales to apply ``(m,)``, times the factor."""
        return None if self.observation is None else self.observation * self.factor


def calibrate_noise(
    flight: Flight, folder: Path, kinds: Sequence[str], *, rows: slice,
    rounds: int = MATCH_ROUNDS, max_step: float = MATCH_STEP,
) -> dict[str, FloatArray]:  # fmt: skip
    """Per kind, process-noise scales per state output matched to the EKF's errors over
    ``rows`` of ``flight`` (held out of every model's training: the truth is known there,
    the models never saw it) and the 3-sigma coverage factor on the process and observation
    noise (:mod:`estimator_service.matching`), starting from :func:`calibrate_process`'s
    one-step scales; written to ``folder/calibration.json``: the in-sample calibration
    (cross-fitting, :mod:`estimator_service.crossfit`, uses only the one-step scales and
    chooses by the held-out log-likelihood instead).

    Stored as ``noise_scale`` (the geometric mean) times ``process_noise_scale``; returns
    their product per kind ``(n,)``.
    """
    return {k: v.process for k, v in _noise(flight, folder, kinds, rows, rounds, max_step).items()}


def _noise(flight: Flight, folder: Path, kinds: Sequence[str], rows: slice, rounds: int = MATCH_ROUNDS,
           max_step: float = MATCH_STEP) -> dict[str, NoiseCalibration]:  # fmt: skip
    """:func:`calibrate_noise`, returning each kind's :class:`NoiseCalibration`."""
    from estimator_service.factory import apply_calibration, load_models

    res = {}
    for kind in kinds:
        raw = load_models(folder, kind, calibrated=False, check=False)
        pred, cam = apply_calibration(folder, kind, *raw, process=False)  # observation scales only
        start = read_process_scales(folder).get(kind, np.ones(pred.state_dim))
        scales = read_observation_scales(folder).get(kind)
        block = Block(flight, rows, pred, cam, read_process_ceiling(folder, pred.state_dim))
        res[kind] = noise_from_blocks([block], start, scales, rounds, max_step)
    write_calibration(
        folder, {k: v.process for k, v in res.items()}, {k: v.scaled_observation for k, v in res.items()},
        {k: v.details for k, v in res.items()}, {k: v.nis_level for k, v in res.items()},
        calibration_rows=[rows.start, rows.stop],
    )  # fmt: skip
    return res


def noise_from_blocks(
    blocks: Sequence[Block], start: FloatArray, obs_scale: FloatArray | None,
    rounds: int = MATCH_ROUNDS, max_step: float = MATCH_STEP,
) -> NoiseCalibration:  # fmt: skip
    """Process scales matched from ``start (n,)`` and the covering factor on the blocks, with
    the observation scales ``obs_scale (m,)`` the blocks' models carry (or None): the
    in-sample rule (cross-fitting chooses by the held-out log-likelihood instead)."""
    scale, history = match_scales(blocks, start, rounds=rounds, max_step=max_step)
    curve, level = coverage(blocks, scale)
    factor = covering_factor(curve, len(scale))
    details = {"matching": history, "coverage": curve, "coverage_factor": factor, "nis_level": level}
    return NoiseCalibration(scale, obs_scale, factor, details, level)


def geometric_mean(values: object, axis: int | None = None) -> FloatArray:
    """``exp(mean(log(values)))`` over ``axis`` (all entries when None)."""
    return np.exp(np.mean(np.log(values), axis=axis))


def write_calibration(
    folder: Path, process: dict[str, FloatArray], observation: dict[str, FloatArray | None],
    details: dict[str, dict], nis_levels: dict[str, float], adaptive: dict[str, bool] | None = None,
    **extra: object,
) -> None:  # fmt: skip
    """Write per-kind process scales (as a geometric-mean ``noise_scale`` times per-output
    scales), observation scales, the adaptive filters' NIS/dof reference (the kinds whose
    ``nis_levels`` are finite and > 0) and what each kind's calibration measured."""
    from estimator_service.models.calibration import write_noise_scales

    mean = {k: float(geometric_mean(v)) for k, v in process.items()}
    write_noise_scales(
        folder, mean, observation={k: v for k, v in observation.items() if v is not None},
        process={k: v / mean[k] for k, v in process.items()},
        nis_reference={k: v for k, v in nis_levels.items() if math.isfinite(v) and v > 0}, adaptive=adaptive,
        **{NOISE_DETAILS: details}, **extra,
    )  # fmt: skip
