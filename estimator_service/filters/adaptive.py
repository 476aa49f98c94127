"""Innovation-driven process-noise inflation for the EKF and UKF (beyond the paper).

A calibrated model is consistent in conditions like its training data; in others (harsher
gusts, a heavier blimp) its process noise is too small, the belief too narrow and the
innovations too large. The adaptive filters watch the normalised innovation squared and
scale the model's process noise by a factor ``lambda`` carried in the belief
(:attr:`~estimator_service.filters.common.GaussianBelief.inflation`):

``lambda_{k+1} = clip(lambda_k * clip(NIS_k / (dof_k c), 1/10, 10) ** rate, 1, max_inflation)``

and applies it to the process noise of the states ``disturbed`` (the system's
:attr:`~estimator_service.system.System.disturbed`: the blimp's body velocities; all states
when a system names none).

This is a multiplicative (integral) form of the continuous noise-level adjustment of
Bar-Shalom, Li and Kirubarajan (Estimation with Applications to Tracking and Navigation,
2001, Sect. 11.2), chosen over covariance matching of a full ``Q`` (Mohamed and Schwarz
1999; Akhlaghi et al. 2017) and the variational adaptive filters (Huang et al. 2018)
because the cameras' 5-10 innovation values cannot identify a full 12 x 12 ``Q`` from a
short window, while one factor is identified by NIS/dof alone. ``rate`` is the one
setting (0: off, the paper's filter; default :data:`ADAPT_RATE` through the factory). The
particle filter does not adapt.

The reference ``c`` is the calibrated filter's own mean NIS/dof on the held-out
calibration blocks (``nis_reference`` in ``calibration.json``, measured by
:func:`estimator_service.crossfit.cross_fit` at the chosen noise; 1, a consistent filter's,
for models without one). The geometric mean of NIS/dof lies below its mean, so in conditions like
training ``lambda`` stays at its floor of 1 (the calibrated filter, unchanged), and it
rises only while the innovations stay larger than they were there. With ``c = 1`` it rose
only once the innovations were consistent *by themselves*, which the calibrated filters'
are not: their noise is widened until the 3-sigma bounds hold, and their mean NIS/dof
sits at 0.5-0.75. In 3x gusts that adaptation brought the NIS/dof to 1.05 while the state left its
3-sigma bounds on a third of the steps, mostly in the roll and the lateral velocity, which
the cameras see weakly. Unmodelled forces (gusts, a heavier blimp) act on the velocities;
inflating the position's process noise as well lets the estimate follow the cameras' noise.
Measured: docs/measurements.md#adaptation-reference-and-states.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from estimator_service.filters.common import GaussianBelief, StepInfo

__all__ = [
    "ADAPT_RATE",
    "MAX_INFLATION",
    "RATIO_CLIP",
    "adapted",
    "check_adaptation",
    "inflation_factors",
    "next_inflation",
]

FloatArray = NDArray[np.float64]
RATIO_CLIP = 10.0  # one step's NIS/dof counts at most this far from 1 (either way)
#: the default cap on the process-noise factor; measured: docs/measurements.md#adaptation-cap
MAX_INFLATION = 30.0
#: the rate :func:`estimator_service.factory.make_filter` gives an EKF or UKF unless told
#: otherwise (the filter classes themselves default to 0, the paper's filters); measured:
#: docs/measurements.md#adaptation-rate
ADAPT_RATE = 0.5


def check_adaptation(rate: float, cap: float, reference: float = 1.0) -> None:
    """Refuse settings the factor could not follow (a clear error naming the field)."""
    if not (math.isfinite(rate) and 0.0 <= rate <= 1.0):
        raise ValueError(f"adapt_rate must be in [0, 1] (0: off), got {rate!r}")
    if not (math.isfinite(cap) and cap >= 1.0):
        raise ValueError(f"max_inflation must be finite and >= 1, got {cap!r}")
    if not (isinstance(reference, (int, float)) and math.isfinite(reference) and reference > 0):
        raise ValueError(f"adapt_reference must be a finite NIS/dof > 0, got {reference!r}")


def inflation_factors(lam: FloatArray, n: int, states: tuple[int, ...] | None) -> FloatArray:
    """Per belief and state output, the factor on the process variance ``(B, n)``: the
    beliefs' ``lam (B,)`` on ``states`` (all when None), 1 elsewhere."""
    if states is None:
        return np.repeat(lam[:, None], n, axis=1)
    out = np.ones((lam.shape[0], n))
    out[:, list(states)] = lam[:, None]
    return out


def next_inflation(
    inflation: float, info: StepInfo, rate: float, cap: float = MAX_INFLATION, reference: float = 1.0
) -> float:
    """The factor after an update with report ``info`` (unchanged when ``rate`` is 0, or the
    update observed nothing, has no finite NIS or was refused by a gate), its NIS/dof taken
    relative to ``reference``. An implausible innovation (flagged ``diverged``) counts,
    clipped like any other: it is the strongest sign that the process noise is too small."""
    if rate <= 0 or info.dof <= 0 or info.gated or not math.isfinite(info.nis):
        return inflation
    ratio = min(max(info.nis / (info.dof * reference), 1.0 / RATIO_CLIP), RATIO_CLIP)
    return min(max(inflation * ratio**rate, 1.0), cap)


def adapted(
    post: GaussianBelief, prior: GaussianBelief, info: StepInfo, rate: float, cap: float = MAX_INFLATION,
    reference: float = 1.0,
) -> GaussianBelief:  # fmt: skip
    """``post`` carrying the prior's factor moved by :func:`next_inflation`."""
    new = next_inflation(prior.inflation, info, rate, cap, reference)
    return post if new == post.inflation else replace(post, inflation=new)
