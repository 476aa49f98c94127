"""A session's input queue: bounded, served by one worker at a time, in arrival order."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

__all__ = ["BATCH", "Inbox", "Job"]

BATCH = 32  # inputs a worker takes from one session before giving others a turn

#: ``(kind, payload, query or None, extra)``: one input as a zenoh callback queued it
Job = tuple[str, bytes, Any, Any]


class Inbox:
    """Pending inputs of one session, at most ``cap`` (a new input beyond it drops the
    oldest, O(1), and ``on_drop(job)`` answers it).

    ``put`` says when the session must go on the pool's ready queue: only when it is not
    already there or being served, so a session sits there at most once and exactly one
    worker at a time takes its inputs.
    """

    def __init__(self, cap: int, on_drop: Callable[[Job], None]) -> None:
        self.cap = cap
        self.dropped = 0
        self.last_active = time.monotonic()
        self._on_drop = on_drop
        self._pending: deque[Job] = deque()
        self._lock = threading.Lock()
        self._scheduled = False

    def __len__(self) -> int:
        return len(self._pending)

    def put(self, job: Job) -> bool:
        """Queue ``job`` (from a zenoh callback); True when the session must be scheduled."""
        self.last_active = time.monotonic()
        with self._lock:
            dropped = self._pending.popleft() if len(self._pending) >= self.cap else None
            self._pending.append(job)
            wake, self._scheduled = not self._scheduled, True
        if dropped is not None:
            self.dropped += 1
            self._on_drop(dropped)
        return wake

    def take(self) -> Job | None:
        """The next input, or None (the session then leaves the ready queue)."""
        with self._lock:
            if self._pending:
                return self._pending.popleft()
            self._scheduled = False
            return None

    def take_step(self) -> Job | None:
        """The next input if it is a lock-step ``step`` (to batch it), else None."""
        with self._lock:
            if self._pending and self._pending[0][0] == "step":
                return self._pending.popleft()
        return None

    def again(self) -> bool:
        """After a worker's turn: True when inputs wait (schedule the session again)."""
        with self._lock:
            self._scheduled = bool(self._pending)
            return self._scheduled

    def idle_s(self, now: float | None = None) -> float:
        """Seconds since the last input; 0 while inputs are pending or being served."""
        with self._lock:
            busy = bool(self._pending) or self._scheduled
        return 0.0 if busy else (now or time.monotonic()) - self.last_active
