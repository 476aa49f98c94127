"""The one angle-wrapping rule of the estimator: every angle and angle difference is wrapped
into ``[-p/2, p/2)`` for its period ``p`` (``[-pi, pi)`` for an angle in radians), by
``a - p * floor((a + p/2) / p)``.

The simulator (:mod:`gpbf_env`, which imports nothing of the estimator) computes the same
expression in its compiled kernel ``gpbf_env.dynamics.wrap_angle``; a test pins the two to
equal values, the edges ``+-p/2`` included.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["wrap_angle", "wrap_columns"]

FloatArray = NDArray[np.float64]


def wrap_angle(a: ArrayLike, period: ArrayLike = 2 * math.pi) -> NDArray:
    """Angles ``a`` wrapped into ``[-period/2, period/2)``; ``period`` broadcasts against
    ``a`` and a period of 0 leaves its entries as they are (not angles). A complex ``a``
    (complex-step derivatives) is shifted by whole periods chosen from its real part, so
    its imaginary part, the derivative, passes through."""
    a, p = np.asarray(a), np.asarray(period, dtype=np.float64)
    safe = np.where(p > 0, p, 1.0)
    turns = np.where(p > 0, np.floor((np.real(a) + safe / 2) / safe), 0.0)
    return a - p * turns


def wrap_columns(e: FloatArray, periods: FloatArray) -> FloatArray:
    """``e (..., n)`` with the columns of non-zero period ``periods (n,)`` wrapped in place
    by :func:`wrap_angle`; returns ``e``."""
    ang = np.flatnonzero(periods > 0)
    if ang.size:
        e[..., ang] = wrap_angle(e[..., ang], periods[ang])
    return e
