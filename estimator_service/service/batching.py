"""Lock-step steps of many sessions in one batched filter call (the worker pool's
``run_batch``; see :class:`~estimator_service.service.workers.WorkerPool`)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from estimator_service.filters.policy import step_many
from estimator_service.service.inbox import Job
from estimator_service.service.limits import gate_for
from estimator_service.service.protocol import ProtocolError, RepeatedStep

if TYPE_CHECKING:  # sessions call this module; it only uses their methods
    from estimator_service.service.session import Session

__all__ = ["step_together"]


def step_together(batch: list[tuple[Session, Job]]) -> None:
    """Run one lock-step ``step`` job of each session in one batched filter call.

    Inputs that fail validation are rejected one by one, exactly as unbatched; if the
    batched call itself fails, every job runs on its own.
    """
    t0 = time.perf_counter()
    ready = []
    for s, job in batch:
        try:
            ready.append((s, job, s.prepare_step(job[1])))
        except ProtocolError as exc:
            s.reject(str(exc), job[0], job[2])
            s.finish(job)
        except RepeatedStep as rep:  # a retried query: answered again, not stepped
            s.answer(job, lambda rep=rep: _raise(rep))
            s.finish(job)
    if not ready:
        return
    try:
        gate_p = ready[0][0].settings.limits.gate_p
        results = step_many(
            ready[0][0].filter,
            [s.belief for s, _, _ in ready],
            np.stack([p[0].u for _, _, p in ready]),
            np.stack([p[1] for _, _, p in ready]),
            np.stack([p[2] for _, _, p in ready]),
            gate=gate_for(gate_p),
        )
    except Exception:  # fall back: each job alone, with its own error handling
        for s, job, _ in ready:
            s.answer(job, lambda s=s, job=job: s.handle(job))
            s.finish(job)
        return
    for (s, job, (step, _, _)), (belief, info) in zip(ready, results, strict=True):
        s.answer(job, lambda s=s, step=step, b=belief, i=info: s.commit_batched(step, b, i, t0, len(ready)))
        s.finish(job)


def _raise(exc: Exception) -> bytes:
    raise exc
