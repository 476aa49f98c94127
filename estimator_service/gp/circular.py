"""Angles in and out of a GP: inputs as ``(cos, sin)`` pairs, an output as a unit vector.

A squared-exponential kernel on a raw angle puts ``pi - e`` and ``-pi + e`` far apart, so a
GP on a yaw that wraps learns two unrelated functions either side of the wrap. Replacing
the angle by ``(cos a, sin a)`` makes the kernel periodic in ``a`` (the SE kernel on the
unit circle). An angular *output* (an image ellipse's orientation, period ``pi``) has the
same problem in the targets; the inner GP regresses ``(cos ka, sin ka)`` with
``k = 2 pi / period`` and the angle is ``atan2(s, c) / k``, with its variance and Jacobian by
the delta method. Where the training angles disagree (a nearly round ellipse) the
predicted vector is short and the angle's variance large, so a filter trusts it less.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from estimator_service.gp.base import GPModel, GPPrediction, check_query, check_training_data
from estimator_service.reprs import short_repr

__all__ = ["CircularGP", "fit_circular"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class CircularGP:
    """A GP whose angular inputs (and optionally one angular output) are circular.

    Attributes
    ----------
    inner
        The fitted GP on features ``[x_other, cos x_a, sin x_a]`` (``d + len(angle_inputs)``
        inputs) and, with an angular output, targets ``[y_other..., cos ky, sin ky]`` with the
        cosine in the angle's own column and the sine appended last (``P + 1`` outputs).
    angle_inputs
        Input columns that are angles (rad).
    angle_output
        Output column that is an angle, or ``-1`` for none.
    period
        Period of the angular output (``pi`` for an ellipse orientation).
    """

    __repr__ = short_repr

    inner: GPModel
    angle_inputs: tuple[int, ...]
    angle_output: int = -1
    period: float = 2 * math.pi
    kind: str = "circular"

    @property
    def input_dim(self) -> int:
        return self.inner.input_dim - len(self.angle_inputs)

    @property
    def output_dim(self) -> int:
        return self.inner.output_dim - (1 if self.angle_output >= 0 else 0)

    def predict(
        self, x: FloatArray, *, return_var: bool = True, return_jac: bool = False,
        include_noise: bool = True,
    ) -> GPPrediction:  # fmt: skip
        """Batched prediction for queries ``x (M, d)``; see :class:`GPPrediction`."""
        xq = check_query(x, self.input_dim)
        p = self.inner.predict(
            circular_features(xq, self.angle_inputs),
            return_var=return_var,
            return_jac=return_jac,
            include_noise=include_noise,
        )
        jac = _input_jacobian(p.jac, xq, self.angle_inputs) if return_jac else None
        if self.angle_output < 0:
            return GPPrediction(p.mean, p.var, jac)
        return _angle_from_vector(
            GPPrediction(p.mean, p.var, jac), self.angle_output, self.period, return_var
        )


def circular_features(x: FloatArray, angle_inputs: tuple[int, ...]) -> FloatArray:
    """``x (M, d)`` -> ``(M, d + A)``: the other columns, then ``cos`` and ``sin`` of the angles."""
    keep = [i for i in range(x.shape[1]) if i not in angle_inputs]
    a = x[:, list(angle_inputs)]
    return np.concatenate([x[:, keep], np.cos(a), np.sin(a)], axis=1)


def _input_jacobian(jf: FloatArray | None, x: FloatArray, angle_inputs: tuple[int, ...]) -> FloatArray:
    """Chain rule from feature Jacobians ``(M, P, d + A)`` to input Jacobians ``(M, P, d)``."""
    assert jf is not None
    m, p, d = jf.shape[0], jf.shape[1], x.shape[1]
    keep = [i for i in range(d) if i not in angle_inputs]
    n_keep, n_a = len(keep), len(angle_inputs)
    out = np.empty((m, p, d))
    out[:, :, keep] = jf[:, :, :n_keep]
    a = x[:, list(angle_inputs)][:, None, :]
    d_cos, d_sin = jf[:, :, n_keep : n_keep + n_a], jf[:, :, n_keep + n_a :]
    out[:, :, list(angle_inputs)] = -np.sin(a) * d_cos + np.cos(a) * d_sin
    return out


def _angle_from_vector(p: GPPrediction, col: int, period: float, return_var: bool) -> GPPrediction:
    """Replace the ``(cos, sin)`` pair (``col`` and last) by the angle and its moments."""
    k = 2 * math.pi / period
    c, s = p.mean[:, col], p.mean[:, -1]
    r2 = np.maximum(c * c + s * s, 1e-12)
    mean = p.mean[:, :-1].copy()
    mean[:, col] = np.arctan2(s, c) / k
    var = None
    if return_var:
        assert p.var is not None
        var = p.var[:, :-1].copy()
        var[:, col] = (s * s * p.var[:, col] + c * c * p.var[:, -1]) / (k * k * r2 * r2)
    jac = None
    if p.jac is not None:
        jac = p.jac[:, :-1].copy()
        jac[:, col] = (c[:, None] * p.jac[:, -1] - s[:, None] * p.jac[:, col]) / (k * r2[:, None])
    return GPPrediction(mean, var, jac)


def fit_circular(
    x: FloatArray,
    y: FloatArray,
    fit: Callable[[FloatArray, FloatArray], GPModel],
    *,
    angle_inputs: tuple[int, ...] = (),
    angle_output: int | None = None,
    period: float = 2 * math.pi,
) -> CircularGP:
    """Fit ``fit(features, targets)`` (e.g. :func:`fit_exact`) on circular features.

    Parameters
    ----------
    x: (n, d)
    y: (n, P)
    fit
        Any fitter taking ``(x, y)`` and returning a :class:`GPModel`.
    angle_inputs
        Columns of ``x`` that are angles.
    angle_output
        Column of ``y`` that is an angle of period ``period``, if any.
    """
    xa, ya = check_training_data(x, y)
    bad = [i for i in angle_inputs if not 0 <= i < xa.shape[1]]
    if bad or len(set(angle_inputs)) != len(angle_inputs):
        raise ValueError(f"angle_inputs {angle_inputs} must be distinct columns of x (d = {xa.shape[1]})")
    if angle_output is not None and not 0 <= angle_output < ya.shape[1]:
        raise ValueError(f"angle_output {angle_output} is not a column of y (P = {ya.shape[1]})")
    if not period > 0:
        raise ValueError(f"period must be > 0, got {period!r}")
    targets = ya
    if angle_output is not None:
        k = 2 * math.pi / period
        targets = np.concatenate([ya, np.sin(k * ya[:, [angle_output]])], axis=1)
        targets[:, angle_output] = np.cos(k * ya[:, angle_output])
    inner = fit(circular_features(xa, tuple(angle_inputs)), targets)
    return CircularGP(inner, tuple(angle_inputs), -1 if angle_output is None else angle_output, period)
