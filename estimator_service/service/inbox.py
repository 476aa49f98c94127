"""A session's input queue: bounded, served by one worker at a time, in arrival order."""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

__all__ = ["BATCH", "ByteMeter", "Inbox", "Job"]

BATCH = 32  # inputs a worker takes from one session before giving others a turn

#: ``(kind, payload, query or None, extra)``: one input as a zenoh callback queued it
Job = tuple[str, bytes, Any, Any]


class ByteMeter:
    """Payload bytes queued over all sessions of a service, at most ``cap``; thread-safe."""

    def __init__(self, cap: int) -> None:
        self.cap, self.used = cap, 0
        self._lock = threading.Lock()

    def reserve(self, n: int) -> bool:
        """Count ``n`` more bytes, or False (nothing counted) when they would pass the cap."""
        with self._lock:
            if self.used + n > self.cap:
                return False
            self.used += n
            return True

    def release(self, n: int) -> None:
        with self._lock:
            self.used -= n


class Inbox:
    """Pending inputs of one session, at most ``cap`` of them and ``byte_cap`` payload bytes
    (a new input beyond either drops the oldest, O(1) each, and ``on_drop(job)`` answers
    it); with a service-wide ``meter`` a new input that would pass its cap is dropped itself.

    ``put`` says when the session must go on the pool's ready queue: only when it is not
    already there or being served, so a session sits there at most once and exactly one
    worker at a time takes its inputs.
    """

    def __init__(
        self,
        cap: int,
        on_drop: Callable[[Job], None],
        byte_cap: int | None = None,
        meter: ByteMeter | None = None,
    ) -> None:
        self.cap, self.byte_cap, self._meter = cap, byte_cap, meter
        self.bytes = 0
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
        size = len(job[1])
        if self._meter is not None and not self._meter.reserve(size):
            self.dropped += 1  # the service's queues are full: this input is refused itself
            self._on_drop(job)
            return False
        dropped = []
        with self._lock:
            while self._pending and (len(self._pending) >= self.cap or self._over(size)):
                dropped.append(self._pending.popleft())
                self._count(-len(dropped[-1][1]))
            self._pending.append(job)
            self._count(size, meter=False)
            wake, self._scheduled = not self._scheduled, True
        for d in dropped:
            self.dropped += 1
            self._on_drop(d)
        return wake

    def _over(self, size: int) -> bool:
        return self.byte_cap is not None and self.bytes + size > self.byte_cap

    def _count(self, n: int, meter: bool = True) -> None:
        """``n`` bytes more (negative: fewer) queued here (and in the service's meter)."""
        self.bytes += n
        if meter and self._meter is not None and n < 0:
            self._meter.release(-n)

    def put_front(self, job: Job) -> None:
        """Put ``job`` back first (the rest of an input being served; no new bytes: its
        payload is empty), without the caps."""
        with self._lock:
            self._pending.appendleft(job)

    def take(self) -> Job | None:
        """The next input, or None (the session then leaves the ready queue)."""
        with self._lock:
            if self._pending:
                job = self._pending.popleft()
                self._count(-len(job[1]))
                return job
            self._scheduled = False
            return None

    def take_step(self) -> Job | None:
        """The next input if it is a lock-step ``step`` (to batch it), else None."""
        with self._lock:
            if self._pending and self._pending[0][0] == "step":
                job = self._pending.popleft()
                self._count(-len(job[1]))
                return job
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
