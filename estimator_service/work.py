"""Estimated work of a training run's parts, so a progress display's share done and ETA
follow time rather than the count of parts.

:func:`~estimator_service.training.train_models` reports its parts as done in a fixed
order (one weight each here, :func:`part_weights`), and the parts differ by two
orders of magnitude: on the README's 20-minute flight a heteroscedastic fit took 73 s and
one fold's conditioning of a kind about a second. Counted as equal parts, the ETA shown
was 2,225 s at 120 s into a 231-s run. Each weight here is the part's estimated seconds
on the machine the constants were measured on (docs/measurements.md#progress-weights),
scaled by the run's sizes (training points, iterations, outputs, calibration steps); only
their ratios matter to a display.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from estimator_service.crossfit import calibration_folds
from estimator_service.factory import ENHANCED_KINDS, observation_parts
from estimator_service.flight import Flight
from estimator_service.gp.inverse import BLOCKS
from estimator_service.matching import LIKELIHOOD_FACTORS, PROCESS_FACTORS, REFINE_FACTORS
from estimator_service.progress import ProgressBar
from estimator_service.training import TrainSettings, train_models

__all__ = ["fit_seconds", "part_weights", "track_seconds", "train_with_progress"]

# Measured on the README's 20-minute flight with the default settings (2-core AMD EPYC,
# 2026-12-05; docs/measurements.md#progress-weights):
#: seconds per output and unit of ``restarts * max_iter * h^3 + polish_iter * n^3`` (exact fit)
EXACT_FIT_S = 6.9e-11
#: exact fits a heteroscedastic GP's EM round costs (its noise GP and the mean GP's refit)
HETERO_ROUND_FITS = 1.5
#: seconds per output and sparse optimiser iteration: a fixed part and one per ``n * m^2``
SPARSE_ITER_S, SPARSE_NM2_S = 1.0e-3, 4.0e-10
#: seconds per transition of the parametric fit (the blimp's ODE by least squares)
PARAM_ROW_S = 3.3e-4
#: a fold's part per kind, seconds: fixed (its one-step scales, saving, loading) and per
#: output and ``n^3`` of conditioning a GP on the fold's data
FOLD_KIND_S, CONDITION_S = 0.25, 0.85e-10
#: a calibration step of the batched EKF, seconds: per step and per candidate tracked; the
#: parametric model's share (param, egp, hetgp) per step and per candidate; an exact GP's
#: per byte of its inverse factors (a triangle of ``n^2`` doubles per output, read each
#: step) and per candidate, output and training point
STEP_S, CANDIDATE_S = 1.8e-4, 1.8e-5
PARAM_STEP_S, PARAM_CANDIDATE_S = 2.8e-4, 3.0e-5
BYTE_S, POINT_S = 2.0e-11, 1.4e-8
#: one tracking step, seconds: EKF and UKF per step (exact GP kinds, the others); the PF per
#: particle (the others) and per particle, output and training point (exact GP kinds)
EKF_STEP_S, UKF_STEP_S, LIGHT_STEP_S = 3.0e-3, 4.5e-3, 6.0e-4
PF_PARTICLE_S, PF_POINT_S = 5.0e-6, 1.35e-8
EXACT_KINDS = ("gp", "egp", "hetgp")  # kinds whose GPs keep n x n inverse factors
#: candidates each of a kind's crossfit.CHOICE_UNITS choice parts scores (two passes, the adaptation check)
CHOICE_CANDIDATES = (1 + len(LIKELIHOOD_FACTORS) + len(PROCESS_FACTORS), len(REFINE_FACTORS), 1)


def _outputs(flights: Sequence[Flight]) -> list[tuple[int, int]]:
    """``(outputs, training points)`` of each GP a kind fits: the prediction GP's state
    outputs on the transitions, each observation part's outputs on its readings."""
    system = flights[0].system
    out = [(system.state_dim, sum(len(f.transition_rows()) for f in flights))]
    for ks in observation_parts(system).values():
        readings = sum(len(f.readings(k)[0]) for f in flights for k in ks)
        out.append((len(system.sensors[ks[0]].outputs), readings))
    return out


def fit_seconds(flights: Sequence[Flight], kind: str, s: TrainSettings) -> float:
    """Estimated seconds to fit ``kind`` on ``flights`` (``param``: the parametric models)."""
    if kind == "param":
        return PARAM_ROW_S * sum(len(f.transition_rows()) for f in flights)
    total = 0.0
    for outputs, rows in _outputs(flights):
        n = min(s.n_points, rows)
        if kind == "sparse":
            m = min(s.n_pseudo, n)
            total += outputs * s.sparse_iter * (SPARSE_ITER_S + SPARSE_NM2_S * n * m * m)
            continue
        h = min(s.hyper_points or n, n)
        restarts, fits = (s.restarts, 1)
        if kind == "hetgp":  # one restart, then its EM rounds
            restarts, fits = 1, 1 + HETERO_ROUND_FITS * s.hetero_iterations
        polish = s.polish_iter * n**3 if h < n else 0
        total += outputs * fits * EXACT_FIT_S * (restarts * s.max_iter * h**3 + polish)
    return total


def _fold_seconds(flights: Sequence[Flight], kind: str, s: TrainSettings) -> float:
    """A fold's part for ``kind``: the parametric refit, or a GP kind's conditioning on the
    fold's data ``flights``, and the fixed part."""
    if kind == "param":
        return FOLD_KIND_S + fit_seconds(flights, "param", s)
    if kind == "sparse":  # n m^2, not n^3: a sparse GP's conditioning costs about one optimiser step
        return FOLD_KIND_S + fit_seconds(flights, kind, s) / s.sparse_iter
    gps = 2 if kind == "hetgp" else 1  # the mean GP and the noise GP
    cubes = sum(outputs * min(s.n_points, rows) ** 3 for outputs, rows in _outputs(flights))
    return FOLD_KIND_S + gps * CONDITION_S * cubes


def _choice_seconds(flights: Sequence[Flight], kind: str, s: TrainSettings, steps: int) -> list[float]:
    """Seconds of each of a kind's three choice parts over ``steps`` calibration steps."""
    per_step, per_candidate = STEP_S, CANDIDATE_S
    if kind == "param" or kind in ENHANCED_KINDS:
        per_step, per_candidate = per_step + PARAM_STEP_S, per_candidate + PARAM_CANDIDATE_S
    if kind in EXACT_KINDS:
        sizes = [(outputs, min(s.n_points, rows)) for outputs, rows in _outputs(flights)]
        held = (BLOCKS + 1) / (2 * BLOCKS)  # the share of the square the row blocks hold
        per_step += BYTE_S * sum(outputs * n * n * 8 * held for outputs, n in sizes)
        per_candidate += POINT_S * sum(outputs * n for outputs, n in sizes)
    return [steps * (per_step + per_candidate * c) for c in CHOICE_CANDIDATES]


def track_seconds(
    flights: Sequence[Flight], kind: str, s: TrainSettings, filt: str, steps: int, particles: int = 0
) -> float:
    """Estimated seconds to track ``steps`` steps with filter ``filt`` ("ekf", "ukf", "pf"
    with ``particles``) and ``kind`` models trained on ``flights`` with ``s``."""
    exact = kind in EXACT_KINDS
    if filt == "pf":
        points = sum(outputs * min(s.n_points, rows) for outputs, rows in _outputs(flights)) if exact else 0
        return steps * particles * (PF_PARTICLE_S + PF_POINT_S * points)
    per_step = (UKF_STEP_S if filt == "ukf" else EKF_STEP_S) if exact else LIGHT_STEP_S
    return steps * per_step


def part_weights(flights: Sequence[Flight], kinds: Sequence[str], s: TrainSettings) -> list[float]:
    """Estimated seconds of each part :func:`~estimator_service.training.train_models`
    reports as done, in its order, one per part (their number is a progress display's
    total): the GP kinds' fits (the first
    also carrying the parametric fit before it), each fold's refits (with
    ``calibration_refit``) and calibration of each kind, then each kind's three choice
    parts."""
    gp = [k for k in kinds if k != "param"]
    weights = [fit_seconds(flights, k, s) for k in gp]
    parametric = any(k == "param" or k in ENHANCED_KINDS for k in kinds)
    if weights and parametric and flights[0].system.has_parametric:  # fitted before the GP kinds
        weights[0] += fit_seconds(flights, "param", s)
    folds = calibration_folds(flights, s.calibration_seconds, s.calibration_folds)
    if not folds:
        return weights
    for fold in folds:
        rest = fold.rest(flights)
        if s.calibration_refit:
            weights += [fit_seconds(rest, k, s) for k in gp]
        weights += [_fold_seconds(rest, k, s) for k in kinds]
    steps = sum(f.rows.stop - f.rows.start for f in folds)
    for k in kinds:
        weights += _choice_seconds(flights, k, s, steps)
    return weights


#: optimiser iterations between two status texts of :func:`train_with_progress`
STATUS_EVERY_ITERATIONS = 25


def train_with_progress(
    desc: str, flights: Sequence[Flight], out: str | Path, *, kinds: Sequence[str],
    settings: TrainSettings, seed: int = 0, enabled: bool = True,
) -> dict[str, float]:  # fmt: skip
    """:func:`~estimator_service.training.train_models` with a progress display ``desc``
    weighted by :func:`part_weights` (every part counted: the fits, the calibration's folds,
    the noise choices; 100 % when the models are saved) and the optimiser's status now and
    then, so a log is never silent while models train. Returns training seconds per kind."""
    bar = ProgressBar(desc, unit="part", enabled=enabled, weights=part_weights(flights, kinds, settings))
    iterations = [0]

    def progress(kind: str, p) -> None:
        if p is None:  # one part of the work done
            bar.advance(1, postfix=f"{kind} done")
            return
        iterations[0] += 1
        if iterations[0] % STATUS_EVERY_ITERATIONS == 0:
            bar.update_to(
                bar.n, postfix=f"{kind}: output {p.output}, restart {p.restart}, nll {p.objective:.4g}"
            )

    with bar:
        return train_models(flights, out, kinds=kinds, settings=settings, seed=seed, on_progress=progress)
