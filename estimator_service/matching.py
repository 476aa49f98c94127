"""Process-noise matching and 3-sigma coverage on held-out blocks of training flights.

A *block* is rows of a flight with models that never saw them (:mod:`estimator_service.crossfit`
fits one set of models per block). :func:`match_scales` chooses one process-noise scale per
state output so that, over the given blocks, the EKF's mean normalised squared error
``e_i^2 / P_ii`` is 1; :func:`coverage_curve` and :func:`covering_factor` then choose the
factor on both the process and the observation noise at which the truth lies within
3 sigma on every dimension as often as it would for a Gaussian belief (``0.9973 ** n``).

Cross-fitting (:mod:`estimator_service.crossfit`) matches on each held-out block alone and
combines the blocks' scales; pooling them in one match drove the cameras-pinned position's
process noise to 260-700 times its one-step value and cost 12 % RMS (200-point GP models,
8-minute lab flight, four blocks).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.flight import Flight
from estimator_service.models.base import ObservationModel, PredictionModel
from estimator_service.tracking import TrackResult

__all__ = [
    "COVERAGE_FACTORS",
    "GAUSSIAN_WITHIN3",
    "MATCH_ROUNDS",
    "MATCH_STEP",
    "MATCH_TOLERANCE",
    "MIN_LEVERAGE",
    "Block",
    "coverage",
    "coverage_curve",
    "covering_factor",
    "leverage",
    "match_scales",
    "nis_level",
    "track_block",
]

FloatArray = NDArray[np.float64]
GAUSSIAN_WITHIN3 = 0.9973  # P(|z| <= 3) for one Gaussian dimension
MATCH_ROUNDS = 8  # matching rounds
MATCH_STEP = 4.0  # the most one round changes an output's scale (either way)
MATCH_TOLERANCE = 0.1  # matching stops once every output's e^2 / P is within 10 % of 1
MIN_LEVERAGE = 0.25  # the weakest response of e^2 / P to its own scale that is followed
#: factors on the matched process and observation noise tried, smallest first
COVERAGE_FACTORS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0)


@dataclass(frozen=True)
class Block:
    """Rows ``rows`` of ``flight`` and models (calibrated observation noise, raw prediction
    noise) that never saw them, with the models' process-variance ceiling ``(n,)`` (None:
    none), which applies to every scale tried on the block as it will in the filter."""

    flight: Flight
    rows: slice
    prediction: PredictionModel
    observation: ObservationModel
    ceiling: FloatArray | None = None


def track_block(block: Block, scale: FloatArray, factor: float = 1.0) -> TrackResult | None:
    """The plain EKF over the block (the adaptive one would hide what is calibrated here),
    its process noise scaled by ``scale * factor (n,)`` (capped at the block's ceiling) and
    its observation noise by ``factor``; None when the filter's covariance blew up (not
    finite, or at some step no longer factorable, which the filter flags as divergence and
    carries on), which the callers count as a block the scales do not cover."""
    from estimator_service.factory import make_filter
    from estimator_service.models.calibration import NoiseScaledObservation, NoiseScaledPrediction
    from estimator_service.tracking import track_flight

    obs = block.observation
    if factor != 1.0:
        obs = NoiseScaledObservation(obs, np.full(obs.obs_dim, factor))
    pred = NoiseScaledPrediction(block.prediction, scale * factor, block.ceiling)
    filt = make_filter("ekf", pred, obs, system=block.flight.system, adapt_rate=0.0)
    try:
        with np.errstate(all="ignore"):
            r = track_flight(filt, block.flight, rows=block.rows)
            if not (np.isfinite(r.cov).all() and np.isfinite(r.mean).all()):
                return None
            np.linalg.cholesky(r.cov)  # every step's belief factorable
    except np.linalg.LinAlgError:  # other errors are bugs, not a covariance blown up
        return None
    return r


def match_scales(
    blocks: Sequence[Block], scale: FloatArray, *, rounds: int = MATCH_ROUNDS, max_step: float = MATCH_STEP
) -> tuple[FloatArray, list[dict]]:
    """Process-noise scales ``(n,)`` from ``scale``: each round tracks every block and
    multiplies each output's scale by its ``e_i^2 / P_ii`` over all their steps raised to the inverse of
    its :func:`leverage` (the factor clipped to ``[1 / max_step, max_step]``); returns the
    scales and each round's NEES and ratios.

    One-step residuals alone miss errors that persist over many steps (gusts with a 3 s
    correlation time, actuator lag, an unobserved drift such as the yaw's): on a held-out
    flight the yaw's ``e^2 / P`` was 14 with one-step scales.
    """
    history, last = [], None  # last: the previous round's (scale, z2), for the leverage
    for _ in range(rounds):
        if history and history[-1]["e2_over_var"] is not None and _converged(history[-1]["e2_over_var"]):
            break
        runs = [r for r in (track_block(b, scale) for b in blocks) if r is not None]
        if not runs:  # every block blew up: keep the last scales that tracked
            history.append({"nees": None, "e2_over_var": None})
            return (last[0] if last is not None else scale), history
        z2 = np.concatenate([r.error**2 / np.diagonal(r.cov, axis1=1, axis2=2) for r in runs]).mean(axis=0)
        z2 = np.nan_to_num(z2, nan=max_step, posinf=max_step)
        nees = float(np.mean([r.scores()["nees"] for r in runs]))
        history.append({"nees": nees, "e2_over_var": z2.tolist()})
        power = 1.0 if last is None else 1.0 / leverage(last, (scale, z2))
        last = (scale, z2)
        scale = scale * np.clip(z2**power, 1 / max_step, max_step)
    return scale, history


def _converged(z2: list[float]) -> bool:
    return bool(np.all(np.abs(np.log(np.maximum(z2, 1e-12))) <= math.log(1 + MATCH_TOLERANCE)))


def leverage(before: tuple[FloatArray, FloatArray], after: tuple[FloatArray, FloatArray]) -> FloatArray:
    """Per output, how strongly ``e^2 / P`` fell as its process-noise scale rose between two
    rounds, ``-d log(e^2/P) / d log(scale)`` in ``[MIN_LEVERAGE, 1]`` (1 where the scale did
    not move or the ratio rose). A state the sensors pin (the yaw, the position) has a
    posterior variance near ``sqrt(Q R)``, so its ratio falls about as ``scale^-1/2``."""
    ds = np.log(after[0] / before[0])
    dz = np.log(np.maximum(after[1], 1e-12) / np.maximum(before[1], 1e-12))
    with np.errstate(divide="ignore", invalid="ignore"):
        lev = np.where(np.abs(ds) > 1e-3, -dz / ds, 1.0)
    return np.clip(np.nan_to_num(lev, nan=1.0), MIN_LEVERAGE, 1.0)


def coverage_curve(blocks: Sequence[Block], scale: FloatArray) -> list[float]:
    """Per factor of :data:`COVERAGE_FACTORS` up to the first that reaches a Gaussian
    belief's ``0.9973 ** n`` (the larger ones are not tracked), the fraction of all the
    blocks' steps on which the EKF keeps the truth within 3 sigma on every dimension."""
    return coverage(blocks, scale)[0]


def coverage(blocks: Sequence[Block], scale: FloatArray) -> tuple[list[float], float]:
    """:func:`coverage_curve`, and the :func:`nis_level` of the EKF's runs at the last
    factor tracked (the one :func:`covering_factor` chooses from that curve)."""
    from estimator_service.tracking import within_3sigma

    curve: list[float] = []
    level = math.nan
    for factor in COVERAGE_FACTORS:
        if curve and curve[-1] >= GAUSSIAN_WITHIN3 ** len(scale):
            break
        runs = [track_block(b, scale, factor) for b in blocks]
        inside = sum(within_3sigma(r.error, r.cov) * len(r.error) for r in runs if r is not None)
        steps = sum(len(r.error) if r is not None else len(range(len(b.flight))[b.rows]) - 1
                    for r, b in zip(runs, blocks, strict=True))  # fmt: skip
        curve.append(float(inside / max(1, steps)))
        level = nis_level([r for r in runs if r is not None])
    return curve, level


def nis_level(runs: Sequence[TrackResult]) -> float:
    """The mean NIS/dof over every update of ``runs`` (NaN without one): the innovation
    level the adaptive filters refer their process-noise factor to
    (:mod:`estimator_service.filters.adaptive`); 1 for a consistent filter."""
    ratios = [r.nis[r.dof > 0] / r.dof[r.dof > 0] for r in runs]
    flat = np.concatenate(ratios) if ratios else np.zeros(0)
    flat = flat[np.isfinite(flat)]
    return float(np.mean(flat)) if flat.size else math.nan


def covering_factor(curve: Sequence[float], state_dim: int) -> float:
    """The smallest of :data:`COVERAGE_FACTORS` whose :func:`coverage_curve` value reaches a
    Gaussian belief's ``0.9973 ** n`` (the largest factor when none does).

    Matched second moments still leave the bursts of persistent errors outside the bounds
    more often than a Gaussian belief would. Scaling the process and the observation noise
    together scales a linear filter's whole covariance, so the states the sensors pin (whose
    spread hardly follows their process noise) widen too."""
    hits = np.flatnonzero(np.asarray(curve) >= GAUSSIAN_WITHIN3**state_dim)
    return COVERAGE_FACTORS[int(hits[0]) if hits.size else -1]
