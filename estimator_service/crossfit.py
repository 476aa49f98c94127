"""Cross-fitted noise calibration: each scale is measured with models that never saw the
data it is measured on, and applied to models trained on all of it.

Folds (:func:`calibration_folds`): with one training flight, blocks spread from its start
to its end; with several, whole flights held out in turn. For each fold the model kinds are
fitted again without its rows (by default with their own hyperparameters; see
``TrainSettings.calibration_refit``), and its rows calibrate them
(:mod:`estimator_service.calibrate`): observation scales on its frames, one-step process
scales on its transitions, then per-output matching of the EKF's errors and the factor at
which the 3-sigma bounds hold as often as a Gaussian belief's
(:mod:`estimator_service.matching`). The combined scales are stored beside the models
trained on everything. Holding one block out of the final models instead cost accuracy:
uncalibrated 200-point GP-EKF on a new flight, aggregate RMS 17.6 with the first two minutes
of an 8-minute flight withheld from training vs 14.7 without.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from estimator_service.calibrate import calibrate_all, calibration_rows, geometric_mean, write_calibration
from estimator_service.flight import Flight
from estimator_service.models.calibration import read_details
from estimator_service.store import seal
from estimator_service.system import System

__all__ = ["MAX_FOLDS", "Fold", "calibration_blocks", "calibration_folds", "cross_fit"]

FloatArray = NDArray[np.float64]


MAX_FOLDS = 12  # calibration folds a training run may ask for


@dataclass(frozen=True)
class Fold:
    """Rows ``rows`` of training flight ``flight``: held out of a fold's models and scored."""

    flight: int
    rows: slice

    def rest(self, flights: Sequence[Flight]) -> list[Flight]:
        """The training flights without this fold's rows (a cut flight becomes two)."""
        out = []
        for i, f in enumerate(flights):
            parts = [np.arange(len(f))] if i != self.flight else [
                np.arange(0, self.rows.start), np.arange(self.rows.stop, len(f))]  # fmt: skip
            out += [f if len(p) == len(f) else f.select(p) for p in parts if len(p) >= 2]
        return out


def _check_folds(folds: object) -> None:
    if not (isinstance(folds, int) and 1 <= folds <= MAX_FOLDS):
        raise ValueError(f"calibration_folds must be an integer in [1, {MAX_FOLDS}], got {folds!r}")


def calibration_blocks(flight: Flight, seconds: float, folds: int) -> list[slice]:
    """``folds`` blocks of ``seconds`` of ``flight`` (each at most ``1 / max(folds, 4)`` of
    it), spread evenly from its start to its end (1: the start; 2: the start and the end);
    none for ``seconds`` 0."""
    _check_folds(folds)
    n = min(calibration_rows(flight, seconds).stop, len(flight) // max(folds, 4))
    if n < 2:
        return []
    starts = np.linspace(0, len(flight) - n, folds).round().astype(int) if folds > 1 else [0]
    return [slice(int(a), int(a) + n) for a in starts]


def calibration_folds(flights: Sequence[Flight], seconds: float, folds: int) -> list[Fold]:
    """The folds of a training run: with one flight, :func:`calibration_blocks` of it; with
    several, each of the first ``folds`` flights held out whole in turn and scored on its
    first ``seconds`` (models meet new flights, not new minutes of a flight they know: on
    held-out flights the errors of models cross-fitted within one flight came out larger
    than on the blocks that calibrated them). None for ``seconds`` 0."""
    if len(flights) == 1 or seconds <= 0:
        return [Fold(0, b) for b in calibration_blocks(flights[0], seconds, folds)] if flights else []
    _check_folds(folds)
    chosen = [(i, round(seconds / f.dt)) for i, f in enumerate(flights[:folds])]
    return [Fold(i, slice(0, min(n, len(flights[i])))) for i, n in chosen if min(n, len(flights[i])) >= 2]


def cross_fit(
    out: Path, flights: Sequence[Flight], system: System, kinds: Sequence[str], folds: Sequence[Fold],
    fit: Callable[[Path, list[Flight]], object],
) -> dict[str, FloatArray]:  # fmt: skip
    """Calibrate the models in ``out`` from folds: ``fit(folder, flights)`` trains the kinds
    into ``folder``; returns the process-noise scales per kind ``(n,)``.

    Each fold's models are fitted without its rows, which then calibrate them
    (:func:`~estimator_service.calibrate.calibrate_all`: observation scales, matched process
    scales, the factor at which the 3-sigma bounds hold as often as a Gaussian belief's).
    The saved scales are the folds' matched scales by geometric mean times the largest of
    their factors: the bounds must hold on every held-out block, as they must on a flight
    none of them resembles (the conformal choice over ``K`` folds). Measured (200-point
    gp and sparse models, 8-minute lab flight, 4 folds, GP-EKF on new 4-minute flights
    seeds 22 and 24-27): truth within 3 sigma on every dimension 0.936-0.974 of the steps,
    NEES/12 0.55-0.69, with the largest factor; 0.88-0.96 and 0.71-0.99 with the factor
    that covers the folds pooled. Pooling the blocks in the matching itself instead drove
    the position's process noise to 260-700 times its one-step value (the cameras pin it)
    and cost 12 % RMS."""
    matched: dict[str, list[FloatArray]] = {k: [] for k in kinds}
    obs: dict[str, list[FloatArray]] = {k: [] for k in kinds}
    factors: dict[str, list[float]] = {k: [] for k in kinds}
    levels: dict[str, list[float]] = {k: [] for k in kinds}
    details: list[dict] = []  # each fold's calibration report
    for i, f in enumerate(folds):
        fold = out / f"fold{i}"
        fold.mkdir()
        try:
            fit(fold, f.rest(flights))
            seal(fold, system)
            res = calibrate_all(flights[f.flight], fold, kinds, rows=f.rows)
            details.append(read_details(fold))
            for k, r in res.items():
                factors[k].append(r.factor)
                levels[k].append(r.nis_level)
                matched[k].append(r.matched)
                obs[k].append(r.observation)
        finally:
            shutil.rmtree(fold)
    process = {k: geometric_mean(v, axis=0) * max(factors[k]) for k, v in matched.items()}
    observation = {k: geometric_mean(v, axis=0) * max(factors[k]) for k, v in obs.items()}
    chosen = {k: {"coverage_factor": max(v)} for k, v in factors.items()}
    write_calibration(out, process, observation, chosen, {k: _level(v) for k, v in levels.items()},
                      fold_details=details,
                      folds=[[f.flight, f.rows.start, f.rows.stop] for f in folds])  # fmt: skip
    return process


def _level(levels: list[float]) -> float:
    """The folds' mean NIS/dof levels combined by geometric mean, like their scales (NaN
    when no fold had one).

    Each level is measured at its fold's own coverage factor; the saved noise takes the
    largest factor, so the saved filter's innovations are, if anything, below the level in
    conditions like training and its adaptation starts later, not sooner."""
    ok = [v for v in levels if math.isfinite(v) and v > 0]
    return float(geometric_mean(ok)) if ok else math.nan
