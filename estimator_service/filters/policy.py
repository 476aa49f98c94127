"""The one step policy every filter, the service, the RL environments and ``gpbf track`` run.

:func:`step_many` owns what happens around the filter's prediction and update equations,
for ``B`` independent beliefs at once (one belief is a batch of one):

1. **predict** each belief with its control (one model call for all of them where the
   filter has ``predict_many``: the EKF and UKF);
2. a **non-finite prediction** (a model evaluated far outside its data) keeps that belief
   as it was and reports ``StepInfo(diverged=True)``: never NaN, and never dependent on
   which other beliefs share the batch;
3. **no reading**: the belief is the prediction;
4. **update** with exactly the valid entries (one model call for all beliefs where the
   filter has ``update_many``; the adaptive filters adapt inside their update);
5. an innovation the **gate** refuses (``gate(info)`` True) keeps the prediction, reported
   by :meth:`~estimator_service.filters.common.StepInfo.refused`.

:func:`update_many` is steps 3-5 alone: a reading at the time of the belief (a second
reading of a sensor within a step, a camera frame at the service's current time).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimator_service.filters.common import ParticleBelief, StepInfo, finite

__all__ = ["Gate", "batchable", "step_many", "step_one", "update_many"]

FloatArray = NDArray[np.float64]
#: ``gate(info)`` True refuses an update (an implausible innovation)
Gate = Callable[[StepInfo], bool]
Rngs = np.random.Generator | Sequence[np.random.Generator] | None


def batchable(filt: Any) -> bool:
    """Whether ``filt`` predicts and updates many beliefs in one model call (EKF, UKF)."""
    return hasattr(filt, "predict_many") and hasattr(filt, "update_many")


def step_many(
    filt: Any, beliefs: Sequence[Any], u: FloatArray, z: FloatArray, valid: NDArray[np.bool_],
    gate: Gate | None = None, rng: Rngs = None,
) -> list[tuple[Any, StepInfo]]:  # fmt: skip
    """One step of ``B`` independent beliefs under the module's policy.

    Parameters
    ----------
    filt
        Any filter of the common interface (``predict``, ``update``; ``predict_many`` and
        ``update_many`` when it batches).
    beliefs
        ``B`` beliefs in the filter's own form.
    u
        Controls ``(B, k)``.
    z, valid
        Readings and which entries are present ``(B, m)``.
    gate
        Refuses an update when ``gate(info)`` is True (None: every update applies).
    rng
        One generator for all beliefs, or one per belief (the particle filter draws; the
        Kalman filters draw nothing).

    Returns
    -------
    ``B`` pairs ``(belief, StepInfo)``.
    """
    u, z, valid = _batch(len(beliefs), u, z, valid)
    rngs = _rngs(rng, len(beliefs))
    if batchable(filt):
        priors = filt.predict_many(list(beliefs), u)
    else:
        priors = [filt.predict(b, u[i], rngs[i]) for i, b in enumerate(beliefs)]
    ok = np.array([_finite(p) for p in priors], bool)
    out: list[tuple[Any, StepInfo]] = [(b, StepInfo(diverged=True, ess=_ess(b))) for b in beliefs]
    rows = np.flatnonzero(ok)
    if rows.size:
        picked = [rngs[i] for i in rows]
        done = update_many(filt, [priors[i] for i in rows], z[rows], valid[rows], gate, picked)
        for i, res in zip(rows, done, strict=True):
            out[i] = res
    return out


def step_one(
    filt: Any, belief: Any, u: FloatArray, z: FloatArray | None = None,
    valid: NDArray[np.bool_] | None = None, rng: np.random.Generator | None = None, gate: Gate | None = None,
) -> tuple[Any, StepInfo]:  # fmt: skip
    """:func:`step_many` for one belief: ``u (k,)``, ``z (m,)`` (None: no reading), ``valid
    (m,)`` (None: every entry of ``z``)."""
    if z is None:
        m = filt.observation.obs_dim
        z, valid = np.zeros(m), np.zeros(m, bool)
    z = np.asarray(z, dtype=np.float64)
    v = np.ones(z.shape, bool) if valid is None else np.asarray(valid, dtype=bool)
    return step_many(filt, [belief], np.asarray(u, dtype=np.float64)[None], z[None], v[None], gate, rng)[0]


def update_many(
    filt: Any, priors: Sequence[Any], z: FloatArray, valid: NDArray[np.bool_], gate: Gate | None = None,
    rng: Rngs = None,
) -> list[tuple[Any, StepInfo]]:  # fmt: skip
    """Steps 3-5 of the policy for ``B`` beliefs ``priors`` with readings ``z, valid (B, m)``:
    the prediction where nothing was read, else the update (the prediction, reported
    refused, where ``gate`` refuses it)."""
    z, valid = np.asarray(z, dtype=np.float64), np.asarray(valid, dtype=bool)
    rngs = _rngs(rng, len(priors))
    out: list[tuple[Any, StepInfo]] = [(p, StepInfo(ess=_ess(p))) for p in priors]
    rows = np.flatnonzero(valid.any(axis=1))
    if rows.size == 0:
        return out
    if batchable(filt):
        done = filt.update_many([priors[i] for i in rows], z[rows], valid[rows])
    else:
        done = [filt.update(priors[i], z[i], valid[i], rngs[i]) for i in rows]
    for i, (post, info) in zip(rows, done, strict=True):
        out[i] = (priors[i], info.refused()) if gate is not None and gate(info) else (post, info)
    return out


def _batch(b: int, u: object, z: object, valid: object) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """``u (B, k)``, ``z`` and ``valid (B, m)`` as arrays, their batch sizes checked."""
    u, z, valid = (np.asarray(u, dtype=np.float64), np.asarray(z, dtype=np.float64),
                   np.asarray(valid, dtype=bool))  # fmt: skip
    for name, a in (("u", u), ("z", z), ("valid", valid)):
        if a.ndim != 2 or a.shape[0] != b:
            raise ValueError(f"step_many: '{name}' must have one row per belief ({b}), got shape {a.shape}")
    if z.shape != valid.shape:
        raise ValueError(f"step_many: 'z' {z.shape} and 'valid' {valid.shape} must have the same shape")
    return u, z, valid


def _rngs(rng: Rngs, b: int) -> list[np.random.Generator | None]:
    if rng is None or isinstance(rng, np.random.Generator):
        return [rng] * b
    rngs = list(rng)
    if len(rngs) != b:
        raise ValueError(f"step_many: 'rng' must be one generator or one per belief ({b}), got {len(rngs)}")
    return rngs


def _finite(belief: Any) -> bool:
    if isinstance(belief, ParticleBelief):
        return finite(belief.particles)
    return finite(belief.mean, belief.cov)


def _ess(belief: Any) -> float | None:
    return belief.ess if isinstance(belief, ParticleBelief) else None
