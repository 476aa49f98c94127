"""The worker threads shared by all sessions of a service, and batched lock-step steps."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Hashable
from typing import Any, Protocol

__all__ = ["GROUP", "Schedulable", "WorkerPool"]

GROUP = 64  # sessions a worker takes from the ready queue at once (batched EKF steps)


class Schedulable(Protocol):
    """What the pool needs of a session."""

    @property
    def batch_key(self) -> Hashable | None:
        """Sessions with equal keys can run a lock-step ``step`` in one batch (None: never)."""
        ...

    def drain(self) -> None:
        """Run some of the session's pending inputs, one after the other."""
        ...

    def head_step(self) -> Any | None:
        """Take the next pending input if it is a lock-step ``step`` (to batch it), else None."""
        ...


class WorkerPool:
    """A few worker threads serving many sessions.

    A session with pending inputs sits on the ready queue at most once, so exactly one
    worker at a time runs its inputs, in arrival order; after ``session.BATCH`` inputs it
    goes to the back of the queue. A handful of threads instead of one per session keeps the
    interpreter from switching between hundreds of threads.

    Under load a worker takes every session waiting on the ready queue (up to
    :data:`GROUP`); those whose next input is a lock-step ``step`` and that share a
    ``batch_key`` (the same batchable filter, the EKF) go to ``run_batch`` together
    (:func:`estimator_service.service.batching.step_together`: one GP call for all of them
    instead of one per blimp).
    """

    def __init__(
        self, workers: int = 2, run_batch: Callable[[list[tuple[Any, Any]]], None] | None = None
    ) -> None:
        self._run_batch = run_batch
        self._ready: queue.SimpleQueue = queue.SimpleQueue()
        self._threads = [threading.Thread(target=self._loop, name=f"estimator-worker-{i}", daemon=True)
                         for i in range(max(1, workers))]  # fmt: skip
        for t in self._threads:
            t.start()

    def schedule(self, session: Schedulable) -> None:
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

    def _serve(self, group: list[Schedulable]) -> None:
        batches: dict[Hashable, list[tuple[Schedulable, Any]]] = {}
        for s in group:
            key = s.batch_key if len(group) > 1 and self._run_batch is not None else None
            job = s.head_step() if key is not None else None
            if job is None:
                s.drain()
            else:
                batches.setdefault(key, []).append((s, job))
        for batch in batches.values():
            self._run_batch(batch)

    def stop(self) -> None:
        for _ in self._threads:
            self._ready.put(None)
        for t in self._threads:
            t.join(timeout=10)
