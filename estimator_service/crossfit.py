"""Cross-fitted noise calibration: each scale is measured with models that never saw the
data it is measured on, and applied to models trained on all of it.

Folds (:func:`calibration_folds`): with one training flight, blocks spread from its start
to its end; with several, whole flights held out in turn. For each fold the model kinds are
fitted again without its rows (by default with their own hyperparameters; see
``TrainSettings.calibration_refit``), and its rows give the one-step scales
(:mod:`estimator_service.calibrate`: observation scales on its frames, process scales on its
transitions, no filter run). The held-out log-likelihood of the truth under the EKF's
beliefs over all the folds' rows, each tracked with models that never saw them, then
chooses the scales in two batched passes
(:func:`~estimator_service.matching.calibrate_by_likelihood`); they (or no calibration at
all where it would score worse) are stored beside the models trained on everything.
Holding one block out of the final models instead cost accuracy: uncalibrated 200-point
GP-EKF on a new flight, aggregate RMS 17.6 with the first two minutes of an 8-minute flight
withheld from training vs 14.7 without.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from estimator_service.calibrate import (
    calibrate_observation,
    calibrate_process,
    calibration_rows,
    geometric_mean,
    write_calibration,
)
from estimator_service.flight import Flight
from estimator_service.matching import Block, Setting, adaptation_helps, calibrate_by_likelihood
from estimator_service.models.calibration import read_details, read_process_ceiling
from estimator_service.store import seal
from estimator_service.system import System

__all__ = ["CHOICE_UNITS", "MAX_FOLDS", "Fold", "calibration_blocks", "calibration_folds", "cross_fit"]

FloatArray = NDArray[np.float64]


MAX_FOLDS = 12  # calibration folds a training run may ask for
CHOICE_UNITS = 3  # progress units of one kind's noise choice: two passes, then the adaptation check


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
    fit: Callable[[Path, list[Flight]], object], tick: Callable[[str], None] | None = None,
) -> dict[str, FloatArray]:  # fmt: skip
    """Calibrate the models in ``out`` from folds: ``fit(folder, flights)`` trains the kinds
    into ``folder``; returns the process-noise scales per kind ``(n,)`` (ones where the
    calibration is not applied). ``tick(label)`` is called as each fold's calibration of a
    kind, and each of a kind's :data:`CHOICE_UNITS` parts of the choice, is done.

    Each fold's models are fitted without its rows, which then give one-step scales
    (:func:`~estimator_service.calibrate.calibrate_observation`,
    :func:`~estimator_service.calibrate.calibrate_process`), combined over the folds by
    geometric mean. Factors on them or on the models' own process noise alone, then each
    output's process scale moved once by its EKF errors, are chosen to maximise the
    log-likelihood of the truth under the EKF's beliefs over all the held-out blocks, each
    tracked with the models that never saw it
    (:func:`~estimator_service.matching.calibrate_by_likelihood`). A calibration that scores a
    lower held-out log-likelihood than the uncalibrated models, or a higher RMS, is not
    applied: the models keep scale 1 and ``calibration.json`` says why (``details.noise``
    ``likelihood``). The coverage at 1, 2 and 3 sigma of both is recorded beside it. The
    adaptive EKF and UKF (:mod:`estimator_service.filters.adaptive`) keep adapting only
    where, at the chosen noise, the adaptive EKF scores a higher held-out log-likelihood
    than the plain one without a higher RMS (``calibration.json`` ``adaptive``): on a
    wheeled robot's log adapting cost 2x in position RMS (``docs/results/real_mrclam``).

    Before this rule the factor was the largest that kept every fold's truth within 3 sigma
    as often as a Gaussian's (coverage bought by width: NEES/12 0.2-0.4 on held-out lab
    flights; on a real robot's log process-noise scales of 6,500-15,000). Before the two
    passes each fold matched every output's ``e^2 / P`` to 1 in up to
    :data:`~estimator_service.matching.MATCH_ROUNDS` sequential EKF runs, then one batched
    pass chose the factor: 0.59 of the README's training run
    (docs/measurements.md#calibration-cost)."""
    from estimator_service.factory import load_models, noise_floors

    start: dict[str, list[FloatArray]] = {k: [] for k in kinds}
    obs: dict[str, list[FloatArray]] = {k: [] for k in kinds}
    blocks: dict[str, list[Block]] = {k: [] for k in kinds}
    details: list[dict] = []  # each fold's calibration report
    for i, f in enumerate(folds):
        fold = out / f"fold{i}"
        fold.mkdir()
        try:
            fit(fold, f.rest(flights))
            seal(fold, system)
            held = flights[f.flight]
            seen = calibrate_observation(held, fold, kinds, rows=f.rows)
            one_step = calibrate_process(held, fold, kinds, rows=f.rows)
            details.append(read_details(fold))
            for k in kinds:
                start[k].append(one_step[k])
                obs[k].append(seen[k])
                pred, cam = load_models(fold, k, calibrated=False, check=False)
                ceiling = read_process_ceiling(fold, pred.state_dim)
                blocks[k].append(Block(held, f.rows, pred, cam, ceiling, *noise_floors(system)))
                if tick is not None:
                    tick(f"calibration fold {i + 1}/{len(folds)}: {k}")
        finally:
            shutil.rmtree(fold)
    process, observation, chosen, levels, adaptive = {}, {}, {}, {}, {}
    for k in kinds:
        on_pass = None if tick is None else lambda label, k=k: tick(f"calibration: {k}'s {label}")
        choice = calibrate_by_likelihood(
            blocks[k], geometric_mean(start[k], axis=0), geometric_mean(obs[k], axis=0), on_pass
        )
        n, m = len(start[k][0]), len(obs[k][0])
        process[k] = choice.process if choice.applied else np.ones(n)
        observation[k] = choice.observation if choice.applied else np.ones(m)
        plain = choice.chosen if choice.applied else choice.uncalibrated
        adaptive[k], scores = adaptation_helps(blocks[k], Setting(process[k], observation[k]), plain)
        chosen[k] = {"likelihood": {**choice.details(), "adaptive": scores.as_dict()}}
        levels[k] = plain.nis_level
        if tick is not None:
            tick(f"calibration: {k}'s noise chosen")
    write_calibration(out, process, observation, chosen, levels, adaptive=adaptive, fold_details=details,
                      folds=[[f.flight, f.rows.start, f.rows.stop] for f in folds])  # fmt: skip
    return process
