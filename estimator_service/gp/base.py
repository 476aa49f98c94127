"""What every GP model shares: the prediction record, input checks, scaling, progress."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "GPModel",
    "GPPrediction",
    "Progress",
    "ProgressCallback",
    "Scaler",
    "check_conditioning_data",
    "check_query",
    "check_training_data",
]

FloatArray = NDArray[np.float64]
log = logging.getLogger("estimator_service.gp")


@dataclass(frozen=True)
class GPPrediction:
    """Batched GP prediction for ``M`` queries and ``P`` outputs, in original units.

    Attributes
    ----------
    mean: (M, P)
    var: (M, P) or None
        Predictive variance (latent variance, plus noise when asked for).
    jac: (M, P, d) or None
        Jacobian of the mean with respect to the query (paper eq. 20-22).
    """

    mean: FloatArray
    var: FloatArray | None = None
    jac: FloatArray | None = None


@runtime_checkable
class GPModel(Protocol):
    """A fitted multi-output GP: immutable, batched prediction."""

    kind: str

    @property
    def input_dim(self) -> int: ...

    @property
    def output_dim(self) -> int: ...

    def predict(
        self,
        x: FloatArray,
        *,
        return_var: bool = True,
        return_jac: bool = False,
        include_noise: bool = True,
    ) -> GPPrediction: ...


@dataclass(frozen=True)
class Progress:
    """One optimiser report: output dimension, restart, iteration and objective."""

    model: str
    output: int
    restart: int
    iteration: int
    objective: float


ProgressCallback = Callable[[Progress], None]


def report(callback: ProgressCallback | None, progress: Progress) -> None:
    """Send progress to the callback, and to the ``estimator_service.gp`` logger (debug)."""
    log.debug(
        "%s output %d restart %d iter %d objective %.6g",
        progress.model, progress.output, progress.restart, progress.iteration, progress.objective,
    )  # fmt: skip
    if callback is not None:
        callback(progress)


@dataclass(frozen=True)
class Scaler:
    """Affine standardisation ``(v - mean) / std`` per column.

    Attributes
    ----------
    mean, std: (k,)
    """

    mean: FloatArray
    std: FloatArray

    @classmethod
    def fit(cls, v: FloatArray) -> Scaler:
        """Column means and standard deviations (a constant column gets std 1)."""
        std = v.std(axis=0)
        return cls(v.mean(axis=0), np.where(std > 1e-12 * (1 + np.abs(v).max(axis=0)), std, 1.0))

    def apply(self, v: FloatArray) -> FloatArray:
        return (v - self.mean) / self.std


def check_training_data(x: object, y: object, min_points: int = 2) -> tuple[FloatArray, FloatArray]:
    """Validate training inputs ``x (n, d)`` and targets ``y (n, P)`` (or ``(n,)``).

    Raises
    ------
    ValueError
        Naming the array and the problem: shape, mismatch, too few rows, NaN/Inf.
    """
    xa = np.asarray(x, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64)
    if ya.ndim == 1:
        ya = ya[:, None]
    if xa.ndim != 2:
        raise ValueError(f"training inputs X must be 2-D (n, d), got shape {xa.shape}")
    if ya.ndim != 2:
        raise ValueError(f"training targets Y must be (n,) or (n, P), got shape {ya.shape}")
    if xa.shape[0] != ya.shape[0]:
        raise ValueError(f"X has {xa.shape[0]} rows but Y has {ya.shape[0]}")
    if xa.shape[0] < min_points:
        raise ValueError(f"need at least {min_points} training points, got {xa.shape[0]}")
    for name, arr in (("X", xa), ("Y", ya)):
        bad = ~np.isfinite(arr)
        if bad.any():
            row = int(np.argwhere(bad)[0, 0])
            raise ValueError(f"training {name} contains NaN or Inf (first at row {row})")
    return xa, ya


def check_conditioning_data(
    x: object, y: object, input_dim: int, output_dim: int
) -> tuple[FloatArray, FloatArray]:
    """:func:`check_training_data` for a fitted GP of ``input_dim`` inputs and
    ``output_dim`` outputs conditioned on new data (at least one point; shapes must match)."""
    xa, ya = check_training_data(x, y, min_points=1)
    if xa.shape[1] != input_dim:
        raise ValueError(f"training inputs X have {xa.shape[1]} columns, the GP takes {input_dim}")
    if ya.shape[1] != output_dim:
        raise ValueError(f"training targets Y have {ya.shape[1]} columns, the GP has {output_dim} outputs")
    return xa, ya


def check_query(x: object, input_dim: int) -> FloatArray:
    """Validate query points ``x (M, d)`` (a single ``(d,)`` point is promoted)."""
    xa = np.asarray(x, dtype=np.float64)
    if xa.ndim == 1:
        xa = xa[None, :]
    if xa.ndim != 2 or xa.shape[1] != input_dim:
        raise ValueError(f"query X must have shape (M, {input_dim}), got {np.shape(x)}")
    if not np.all(np.isfinite(xa)):
        raise ValueError("query X contains NaN or Inf")
    return xa
