"""Prediction and observation models backed by any fitted GP (paper eq. 12-15)."""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.base import GPModel
from estimator_service.models.base import (
    ModelOutput,
    controls_for,
    observe_columns,
    sensor_rows,
    side_by_side,
)
from estimator_service.reprs import short_repr

__all__ = ["GPObservationModel", "GPPredictionModel", "SharedGPObservation", "StackedObservationModel"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GPPredictionModel:
    """GP on ``[x, u] -> x_{k+1} - x_k``; the Jacobian is the state block of the GP's."""

    __repr__ = short_repr

    gp: GPModel
    state_dim: int

    def __post_init__(self) -> None:
        if self.gp.output_dim != self.state_dim:
            raise ValueError(f"prediction GP has {self.gp.output_dim} outputs, state has {self.state_dim}")

    @property
    def control_dim(self) -> int:
        return self.gp.input_dim - self.state_dim

    def predict(self, x: FloatArray, u: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        inp = np.concatenate([x, controls_for(u, x.shape[0])], axis=1)
        p = self.gp.predict(inp, return_var=var, return_jac=jac)
        v = p.var if p.var is not None else np.zeros_like(p.mean)
        return ModelOutput(p.mean, v, None if p.jac is None else p.jac[:, :, : self.state_dim])


@dataclass(frozen=True)
class GPObservationModel:
    """GP on ``x -> z``."""

    __repr__ = short_repr

    gp: GPModel

    @property
    def state_dim(self) -> int:
        return self.gp.input_dim

    @property
    def obs_dim(self) -> int:
        return self.gp.output_dim

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        p = self.gp.predict(x, return_var=var, return_jac=jac)
        return ModelOutput(p.mean, p.var if p.var is not None else np.zeros_like(p.mean), p.jac)


@dataclass(frozen=True, eq=False)
class SharedGPObservation:
    """One GP on ``[x, c] -> z`` shared by ``S`` sensors of a type, each with its constants
    ``c``: outputs side by side, sensor by sensor (``obs_dim = S * size``); the Jacobian is
    the state block of the GP's.

    Attributes
    ----------
    gp
        Fitted on ``[x, c]`` rows of every sensor of the type.
    constants: (S, c)
        Each sensor's constants.
    """

    __repr__ = short_repr

    gp: GPModel
    constants: FloatArray

    @property
    def state_dim(self) -> int:
        return self.gp.input_dim - self.constants.shape[1]

    @property
    def obs_dim(self) -> int:
        return len(self.constants) * self.gp.output_dim

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        return self._sensors(x, self.constants, jac, var)

    def observe_columns(self, x: FloatArray, cols: NDArray[np.intp], *, jac: bool = False,
                        var: bool = True) -> ModelOutput:  # fmt: skip
        """Columns ``cols`` of :meth:`observe`, evaluating only the sensors they belong to."""
        size = self.gp.output_dim
        used = np.unique(cols // size)
        out = self._sensors(x, self.constants[used], jac, var)
        pos = np.searchsorted(used, cols // size) * size + cols % size
        return ModelOutput(out.mean[:, pos], out.var[:, pos], None if out.jac is None else out.jac[:, pos])

    def _sensors(self, x: FloatArray, constants: FloatArray, jac: bool, var: bool) -> ModelOutput:
        s = len(constants)
        p = self.gp.predict(np.concatenate(sensor_rows(x, constants), axis=1), return_var=var, return_jac=jac)
        v = p.var if p.var is not None else np.zeros_like(p.mean)
        j = None if p.jac is None else side_by_side(p.jac[:, :, : self.state_dim], s)
        return ModelOutput(side_by_side(p.mean, s), side_by_side(v, s), j)


@dataclass(frozen=True, eq=False)
class StackedObservationModel:
    """Several observation models (e.g. one per camera, or one per sensor type) side by side:
    part ``i``'s outputs go to ``columns[i]`` of the observation (default: one after another)."""

    __repr__ = short_repr

    parts: tuple
    columns: tuple[NDArray[np.intp], ...] | None = None

    def __post_init__(self) -> None:
        dims = {p.state_dim for p in self.parts}
        if len(dims) != 1:
            raise ValueError(f"stacked observation models disagree on the state size: {dims}")
        if self.columns is not None:
            cols = np.concatenate([np.asarray(c, dtype=np.intp) for c in self.columns])
            sizes = [len(c) for c in self.columns]
            whole = np.arange(self.obs_dim)
            if sizes != [p.obs_dim for p in self.parts] or not np.array_equal(np.sort(cols), whole):
                raise ValueError("stacked observation models' columns must cover the observation once")

    @functools.cached_property
    def state_dim(self) -> int:
        return self.parts[0].state_dim

    @functools.cached_property
    def obs_dim(self) -> int:  # read by the filters every step: summed once
        return sum(p.obs_dim for p in self.parts)

    @functools.cached_property
    def _order(self) -> NDArray[np.intp] | None:
        """Part-major -> observation order (``None``: the parts one after another)."""
        return None if self.columns is None else np.argsort(np.concatenate(self._placement()))

    def observe_columns(self, x: FloatArray, cols: NDArray[np.intp], *, jac: bool = False,
                        var: bool = True) -> ModelOutput:  # fmt: skip
        """Columns ``cols`` of :meth:`observe`, evaluating only the parts (and, through
        :func:`~estimator_service.models.base.observe_columns`, the sensors) they need."""
        picked, where = [], []
        for part, place in zip(self.parts, self._placement(), strict=True):
            hit = np.flatnonzero(np.isin(place, cols))  # the part's own columns that are asked for
            if hit.size:
                picked.append(observe_columns(part, x, hit, jac=jac, var=var))
                where.append(place[hit])
        order = np.argsort(np.concatenate(where))  # into ascending observation columns
        mean = np.concatenate([o.mean for o in picked], axis=1)[:, order]
        v = np.concatenate([np.broadcast_to(o.var, o.mean.shape) for o in picked], axis=1)[:, order]
        j = np.concatenate([o.jac for o in picked], axis=1)[:, order] if jac else None
        return ModelOutput(mean, v, j)

    def _placement(self) -> list[NDArray[np.intp]]:
        """Each part's observation columns."""
        if self.columns is not None:
            return [np.asarray(c, dtype=np.intp) for c in self.columns]
        edges = np.cumsum([0] + [p.obs_dim for p in self.parts])
        return [np.arange(a, b) for a, b in itertools.pairwise(edges)]

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        outs = [p.observe(x, jac=jac, var=var) for p in self.parts]  # a few cameras or types
        out = ModelOutput(
            np.concatenate([o.mean for o in outs], axis=1),
            np.concatenate([np.broadcast_to(o.var, o.mean.shape) for o in outs], axis=1),
            np.concatenate([o.jac for o in outs], axis=1) if jac else None,
        )
        if (order := self._order) is None:
            return out
        return ModelOutput(
            out.mean[:, order], out.var[:, order], None if out.jac is None else out.jac[:, order]
        )
