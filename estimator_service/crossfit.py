"""Cross-fitted noise calibration: each scale is measured with models that never saw the
data it is measured on, and applied to models trained on all of it.

For each of one or two blocks of the first training flight (its start and its end), the
model kinds are fitted again without that block, and the block calibrates them
(:mod:`estimator_service.calibrate`): observation scales on its frames, one-step process
scales on its transitions, then per-output matching of the EKF's errors. The folds' scales
are combined by geometric mean and stored beside the models trained on everything.
Holding one block out of the final models instead cost accuracy: uncalibrated 200-point
GP-EKF on a new flight, aggregate RMS 17.6 with the first two minutes of an 8-minute flight
withheld from training vs 14.7 without.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from estimator_service.calibrate import calibrate_all, calibration_rows
from estimator_service.flight import Flight
from estimator_service.models.calibration import (
    read_details,
    read_noise_scales,
    read_observation_scales,
    read_process_scales,
    write_noise_scales,
)
from estimator_service.store import seal
from estimator_service.system import System

__all__ = ["calibration_blocks", "cross_fit"]

FloatArray = NDArray[np.float64]


def calibration_blocks(flight: Flight, seconds: float, folds: int) -> list[slice]:
    """``folds`` (1: the start; 2: the start and the end) blocks of ``seconds`` of
    ``flight``, each :func:`~estimator_service.calibrate.calibration_rows` long (at most a
    quarter of it); none for ``seconds`` 0."""
    if folds not in (1, 2):
        raise ValueError(f"calibration_folds must be 1 or 2, got {folds!r}")
    start = calibration_rows(flight, seconds)
    if start.stop < 2:
        return []
    return [start, slice(len(flight) - start.stop, len(flight))][:folds]


def _without(flight: Flight, block: slice) -> Flight:
    """``flight`` minus a block at its start or end (no false transition across the cut)."""
    keep = np.arange(block.stop, len(flight)) if block.start == 0 else np.arange(0, block.start)
    return flight.select(keep)


def cross_fit(
    out: Path, flights: Sequence[Flight], system: System, kinds: Sequence[str], blocks: Sequence[slice],
    fit: Callable[[Path, list[Flight]], object],
) -> dict[str, FloatArray]:  # fmt: skip
    """Calibrate the models in ``out`` from folds: ``fit(folder, flights)`` trains the kinds
    into ``folder``; returns the combined process-noise scales per kind ``(n,)``."""
    obs: dict[str, list[FloatArray]] = {k: [] for k in kinds}
    proc: dict[str, list[FloatArray]] = {k: [] for k in kinds}
    details: list[dict] = []  # each fold's calibration report
    for i, block in enumerate(blocks):
        fold = out / f"fold{i}"
        fold.mkdir()
        try:
            fit(fold, [_without(flights[0], block), *flights[1:]])
            seal(fold, system)
            calibrate_all(flights[0], fold, kinds, rows=block)
            o, p, g = read_observation_scales(fold), read_process_scales(fold), read_noise_scales(fold)
            details.append(read_details(fold))
            for k in kinds:
                obs[k].append(o[k])
                proc[k].append(g[k] * p[k])
        finally:
            shutil.rmtree(fold)
    geo = {k: np.exp(np.mean(np.log(v), axis=0)) for k, v in proc.items()}
    scalar = {k: float(np.exp(np.mean(np.log(v)))) for k, v in geo.items()}
    write_noise_scales(
        out, scalar, observation={k: np.exp(np.mean(np.log(v), axis=0)) for k, v in obs.items()},
        process={k: v / scalar[k] for k, v in geo.items()},
        folds=[[b.start, b.stop] for b in blocks], fold_details=details,
    )  # fmt: skip
    return geo
