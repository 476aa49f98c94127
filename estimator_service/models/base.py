"""The model interface every filter depends on, and linear-Gaussian models for tests.

A prediction model maps ``(x, u)`` to the mean state *change*, its noise variance and
the Jacobian of the change with respect to ``x`` (paper eq. 14); an observation model
maps ``x`` to the mean observation, its noise variance and Jacobian (eq. 15). Both are
batched over rows; noise is diagonal (one independent GP per output, paper Sect. 4.1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "LinearGaussianObservation",
    "LinearGaussianPrediction",
    "ModelOutput",
    "ObservationModel",
    "PredictionModel",
    "controls_for",
    "observe_columns",
    "sensor_rows",
    "side_by_side",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ModelOutput:
    """Batched model evaluation for ``M`` rows.

    Attributes
    ----------
    mean: (M, k)
    var: (M, k)
        Diagonal noise variance (including model uncertainty for GP models).
    jac: (M, k, n) or None
        Jacobian of ``mean`` with respect to the state.
    """

    mean: FloatArray
    var: FloatArray
    jac: FloatArray | None = None


@runtime_checkable
class PredictionModel(Protocol):
    """``p(x_k | x_{k-1}, u_{k-1})`` as a Gaussian on the state change."""

    state_dim: int
    control_dim: int

    def predict(self, x: FloatArray, u: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        """Change ``x_k - x_{k-1}`` for states ``x (M, n)`` and controls ``u (k,)`` or ``(M, k)``.

        ``var=False`` may skip the variance (returned as zeros) where that saves work.
        """
        ...


@runtime_checkable
class ObservationModel(Protocol):
    """``p(z_k | x_k)`` as a Gaussian."""

    state_dim: int
    obs_dim: int

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        """Observation of states ``x (M, n)``: mean, variance ``(M, m)``, Jacobian ``(M, m, n)``."""
        ...


def observe_columns(
    model: ObservationModel, x: FloatArray, cols: NDArray[np.intp], *, jac: bool = False, var: bool = True
) -> ModelOutput:
    """Columns ``cols (q,)`` (ascending) of ``model.observe(x)``: mean, variance ``(M, q)``,
    Jacobian ``(M, q, n)``. Models with an ``observe_columns`` method evaluate only what
    those columns need (a sensor type's model only the sensors that read, a stack of cameras
    only the cameras that saw); any other model is evaluated whole and sliced."""
    cols = np.asarray(cols, dtype=np.intp)
    if hasattr(model, "observe_columns"):
        return model.observe_columns(x, cols, jac=jac, var=var)
    out = model.observe(x, jac=jac, var=var)
    v = np.broadcast_to(out.var, out.mean.shape)
    return ModelOutput(out.mean[:, cols], v[:, cols], None if out.jac is None else out.jac[:, cols])


def controls_for(u: FloatArray, m: int) -> FloatArray:
    """Broadcast a control ``(k,)`` or ``(M, k)`` to ``(M, k)``."""
    u = np.asarray(u, dtype=np.float64)
    return np.broadcast_to(u, (m, u.shape[-1])) if u.ndim == 1 else u


def sensor_rows(x: FloatArray, constants: FloatArray) -> tuple[FloatArray, FloatArray]:
    """States ``x (M, n)`` and ``S`` sensors' constants ``(S, c)`` as one batch of rows,
    sensor by sensor: ``(S M, n)`` and ``(S M, c)`` (a sensor type's model evaluates all its
    sensors in one call; :func:`side_by_side` puts the results back per state)."""
    return np.tile(x, (len(constants), 1)), np.repeat(constants, len(x), axis=0)


def side_by_side(a: FloatArray, s: int) -> FloatArray:
    """Per-row results of :func:`sensor_rows`' batch ``(S M, size, ...)`` as ``(M, S size, ...)``:
    each state's readings of all ``S`` sensors side by side, sensor by sensor."""
    a = a.reshape(s, -1, *a.shape[1:])
    return np.moveaxis(a, 0, 1).reshape(a.shape[1], s * a.shape[2], *a.shape[3:])


@dataclass(frozen=True)
class LinearGaussianPrediction:
    """``x_k = A x_{k-1} + B u_{k-1} + w``, ``w ~ N(0, diag(q))``."""

    a: FloatArray
    b: FloatArray
    q: FloatArray

    @property
    def state_dim(self) -> int:
        return self.a.shape[0]

    @property
    def control_dim(self) -> int:
        return self.b.shape[1]

    def predict(self, x: FloatArray, u: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        uu = controls_for(u, x.shape[0])
        change = x @ (self.a - np.eye(self.state_dim)).T + uu @ self.b.T
        j = np.broadcast_to(self.a - np.eye(self.state_dim), (x.shape[0], *self.a.shape)) if jac else None
        return ModelOutput(change, np.broadcast_to(self.q, change.shape), j)


@dataclass(frozen=True)
class LinearGaussianObservation:
    """``z = H x + v``, ``v ~ N(0, diag(r))``."""

    h: FloatArray
    r: FloatArray

    @property
    def state_dim(self) -> int:
        return self.h.shape[1]

    @property
    def obs_dim(self) -> int:
        return self.h.shape[0]

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        z = x @ self.h.T
        j = np.broadcast_to(self.h, (x.shape[0], *self.h.shape)) if jac else None
        return ModelOutput(z, np.broadcast_to(self.r, z.shape), j)
