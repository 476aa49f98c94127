"""Enhanced GP (EGP, paper Sect. 4.2, eq. 16-19): a GP on the residual of a parametric model."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.base import GPModel, GPPrediction, check_query, check_training_data
from estimator_service.reprs import short_repr

__all__ = ["EnhancedGP", "MeanFunction", "fit_enhanced", "numeric_jacobian", "value_and_jacobian"]

FloatArray = NDArray[np.float64]
MeanFunction = Callable[[FloatArray], FloatArray]  # (M, d) -> (M, P)
JacobianFunction = Callable[[FloatArray], FloatArray]  # (M, d) -> (M, P, d)


def numeric_jacobian(f: MeanFunction, x: FloatArray, rel_step: float = 1e-6) -> FloatArray:
    """Central-difference Jacobian ``(M, P, d)`` of ``f`` at ``x (M, d)`` in one batched call."""
    return value_and_jacobian(f, x, rel_step)[1]


def value_and_jacobian(
    f: MeanFunction, x: FloatArray, rel_step: float = 1e-6
) -> tuple[FloatArray, FloatArray]:
    """``f(x) (M, P)`` and its central-difference Jacobian ``(M, P, d)`` from one batched
    call of ``f`` at ``x (M, d)`` and the ``2 d`` points around each row (a parametric model's
    cost is mostly per call, not per point)."""
    m, d = x.shape
    h = rel_step * np.maximum(1.0, np.abs(x))  # (M, d)
    eye = np.eye(d)
    pts = np.concatenate([x[:, None, :] + h[:, :, None] * eye, x[:, None, :] - h[:, :, None] * eye], axis=1)
    vals = np.asarray(f(np.concatenate([x, pts.reshape(-1, d)]))).reshape(m * (2 * d + 1), -1)
    at, vals = vals[:m], vals[m:].reshape(m, 2 * d, -1)
    return at, ((vals[:, :d] - vals[:, d:]) / (2.0 * h[:, :, None])).transpose(0, 2, 1)


@dataclass(frozen=True, eq=False)
class EnhancedGP:
    """Parametric mean ``f`` plus a GP on ``y - f(x)``.

    Mean and Jacobian add both parts; the variance is the residual GP's.

    Attributes
    ----------
    mean_function
        ``f(x): (M, d) -> (M, P)``.
    residual
        Any fitted :class:`GPModel` of the residual.
    mean_jacobian
        ``(M, d) -> (M, P, d)``; central differences of ``f`` when None.
    """

    __repr__ = short_repr

    mean_function: MeanFunction
    residual: GPModel
    mean_jacobian: JacobianFunction | None = None
    kind: str = "enhanced"

    @property
    def input_dim(self) -> int:
        return self.residual.input_dim

    @property
    def output_dim(self) -> int:
        return self.residual.output_dim

    def predict(
        self, x: FloatArray, *, return_var: bool = True, return_jac: bool = False,
        include_noise: bool = True,
    ) -> GPPrediction:  # fmt: skip
        """Batched prediction for queries ``x (M, d)``; see :class:`GPPrediction`."""
        xq = check_query(x, self.input_dim)
        res = self.residual.predict(
            xq, return_var=return_var, return_jac=return_jac, include_noise=include_noise
        )
        jac = None
        if return_jac and self.mean_jacobian is None:
            fx, fj = value_and_jacobian(self.mean_function, xq)
            jac = res.jac + fj
        else:
            fx = self.mean_function(xq)
            if return_jac and self.mean_jacobian is not None:
                jac = res.jac + self.mean_jacobian(xq)
        mean = res.mean + np.asarray(fx).reshape(res.mean.shape)
        return GPPrediction(mean, res.var, jac)


def fit_enhanced(
    x: FloatArray,
    y: FloatArray,
    mean_function: MeanFunction,
    fit: Callable[..., GPModel],
    *,
    mean_jacobian: JacobianFunction | None = None,
    **fit_kwargs: object,
) -> EnhancedGP:
    """Fit ``fit(x, y - f(x), **fit_kwargs)`` (e.g. :func:`fit_exact`) and wrap it (eq. 16)."""
    xa, ya = check_training_data(x, y)
    fx = np.asarray(mean_function(xa), dtype=np.float64).reshape(ya.shape)
    if not np.all(np.isfinite(fx)):
        raise ValueError("parametric mean function returned NaN or Inf on the training inputs")
    return EnhancedGP(mean_function, fit(xa, ya - fx, **fit_kwargs), mean_jacobian)
