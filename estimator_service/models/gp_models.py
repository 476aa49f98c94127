"""Prediction and observation models backed by any fitted GP (paper eq. 12-15)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.base import GPModel
from estimator_service.models.base import ModelOutput, controls_for
from estimator_service.reprs import short_repr

__all__ = ["GPObservationModel", "GPPredictionModel", "StackedObservationModel"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class GPPredictionModel:
    """GP on ``[x, u] -> x_{k+1} - x_k``; the Jacobian is the state block of the GP's."""

    __repr__ = short_repr

    gp: GPModel
    state_dim: int
    control_dim: int = field(init=False)

    def __post_init__(self) -> None:
        if self.gp.output_dim != self.state_dim:
            raise ValueError(f"prediction GP has {self.gp.output_dim} outputs, state has {self.state_dim}")
        object.__setattr__(self, "control_dim", self.gp.input_dim - self.state_dim)

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
    state_dim: int = field(init=False)
    obs_dim: int = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "state_dim", self.gp.input_dim)
        object.__setattr__(self, "obs_dim", self.gp.output_dim)

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        p = self.gp.predict(x, return_var=var, return_jac=jac)
        return ModelOutput(p.mean, p.var if p.var is not None else np.zeros_like(p.mean), p.jac)


@dataclass(frozen=True)
class StackedObservationModel:
    """Several observation models (e.g. one per camera) side by side: outputs concatenated."""

    __repr__ = short_repr

    parts: tuple
    state_dim: int = field(init=False)
    obs_dim: int = field(init=False)

    def __post_init__(self) -> None:
        dims = {p.state_dim for p in self.parts}
        if len(dims) != 1:
            raise ValueError(f"stacked observation models disagree on the state size: {dims}")
        object.__setattr__(self, "state_dim", dims.pop())
        object.__setattr__(self, "obs_dim", sum(p.obs_dim for p in self.parts))

    def observe(self, x: FloatArray, *, jac: bool = False, var: bool = True) -> ModelOutput:
        outs = [p.observe(x, jac=jac, var=var) for p in self.parts]  # a few cameras
        j = np.concatenate([o.jac for o in outs], axis=1) if jac else None
        return ModelOutput(
            np.concatenate([o.mean for o in outs], axis=1),
            np.concatenate([o.var for o in outs], axis=1),
            j,
        )
