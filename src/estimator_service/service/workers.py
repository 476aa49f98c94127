"""The worker threads shared by all sessions of a service, and batched lock-step steps."""

from __future__ import annotations

import queue
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

from estimator_service.service.protocol import ProtocolError

if TYPE_CHECKING:
    from estimator_service.service.session import Session

__all__ = ["GROUP", "WorkerPool", "step_together"]

GROUP = 64  # sessions a worker takes from the ready queue at once (batched EKF steps)


class WorkerPool:
    """A few worker threads serving many sessions.

    A session with pending inputs sits on the ready queue at most once, so exactly one
    worker at a time runs its inputs, in arrival order; after ``session.BATCH`` inputs it
    goes to the back of the queue. A handful of threads instead of one per session keeps the
    interpreter from switching between hundreds of threads.

    Under load a worker takes every session waiting on the ready queue (up to
    :data:`GROUP`); those whose next input is a lock-step ``step`` for the same batchable
    filter (the EKF) are stepped together: one GP call for all of them instead of one per
    blimp. Each belief equals the one-at-a-time result up to rounding (about 1e-15).
    """

    def __init__(self, workers: int = 2) -> None:
        self._ready: queue.SimpleQueue = queue.SimpleQueue()
        self._threads = [threading.Thread(target=self._loop, name=f"estimator-worker-{i}", daemon=True)
                         for i in range(max(1, workers))]  # fmt: skip
        for t in self._threads:
            t.start()

    def schedule(self, session: Session) -> None:
        self._ready.put(session)

    def _loop(self) -> None:
        while (session := self._ready.get()) is not None:
            group = [session]
            while len(group) < GROUP:
                try:
                    more = self._ready.get_nowait()
                except queue.Empty:
                    break
                if more is None:  # stop: leave the sentinel for this or another worker
                    self._ready.put(None)
                    break
                group.append(more)
            self._serve(group)

    @staticmethod
    def _serve(group: list[Session]) -> None:
        batches: dict[int, list[tuple[Session, tuple]]] = {}
        for s in group:
            job = s._head_step() if len(group) > 1 and hasattr(s._filter, "step_many") else None
            if job is None:
                s._drain()
            else:
                batches.setdefault(id(s._filter), []).append((s, job))
        for batch in batches.values():
            step_together(batch)

    def stop(self) -> None:
        for _ in self._threads:
            self._ready.put(None)
        for t in self._threads:
            t.join(timeout=10)


def step_together(batch: list[tuple[Session, tuple]]) -> None:
    """Run one lock-step ``step`` job of each session in one batched filter call.

    Inputs that fail validation are rejected one by one, exactly as unbatched; if the
    batched call itself fails, every job runs on its own.
    """
    t0 = time.perf_counter()
    ready = []
    for s, job in batch:
        try:
            ready.append((s, job, s._prepare_step(job[1])))
        except ProtocolError as exc:
            s._reject(str(exc), job[0], job[2])
            s._close_job(job)
    try:
        if ready:
            results = ready[0][0]._filter.step_many(
                [s._belief for s, _, _ in ready],
                np.stack([p[0].u for _, _, p in ready]),
                np.stack([p[1] for _, _, p in ready]),
                np.stack([p[2] for _, _, p in ready]),
            )
    except Exception:  # fall back: each job alone, with its own error handling
        for s, job, _ in ready:
            s._answer(job, lambda s=s, job=job: s._handle(job[0], job[1], job[3]))
            s._close_job(job)
        return
    for (s, job, (step, _, _)), (belief, info) in zip(ready, results, strict=True):
        s.batched += len(ready) > 1
        s._answer(
            job,
            lambda s=s, step=step, belief=belief, info=info: s._commit(belief, info, step.seq, step.t, t0),
        )
        s._close_job(job)
