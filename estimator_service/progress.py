"""One progress display per long job: a bar with a total and an ETA in a terminal, plain
periodic lines (``desc: 120/480 steps (25%), 3 s elapsed, ETA 9 s``) when the output is a
file or a pipe, nothing with ``enabled=False``. The plain lines keep coming every
``every_s`` seconds while a long unit of work reports nothing (a background timer), so a log
never falls silent for minutes."""

from __future__ import annotations

import math
import sys
import threading
import time
from typing import TextIO

__all__ = ["ProgressBar"]


class ProgressBar:
    """Progress of a job of ``total`` units (the total may be set later, see :meth:`update_to`).

    Parameters
    ----------
    every_s
        Seconds between two plain lines when the stream is not a terminal (also while no
        progress is reported, from a background thread until :meth:`close` or :meth:`stop`:
        use the bar as a context manager so an error ends it too).
    """

    def __init__(
        self, desc: str, total: int | None = None, *, unit: str = "step", enabled: bool = True,
        stream: TextIO | None = None, every_s: float = 10.0,
    ) -> None:  # fmt: skip
        if not (math.isfinite(every_s) and every_s > 0):
            raise ValueError(f"every_s must be a positive number of seconds, got {every_s!r}")
        self.desc, self.total, self.unit, self.n = desc, total, unit, 0
        self._stream = stream or sys.stderr
        self._enabled, self._every = enabled, every_s
        self._t0 = self._last = time.monotonic()
        self._postfix = ""
        self._bar = None
        self._lock, self._done = threading.Lock(), threading.Event()
        if enabled and getattr(self._stream, "isatty", lambda: False)():
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit=unit, file=self._stream, dynamic_ncols=True)
        elif enabled:
            threading.Thread(target=self._heartbeat, name=f"progress {desc}", daemon=True).start()

    def _heartbeat(self) -> None:
        """A plain line whenever ``every_s`` passed without one, until the job ends."""
        while not self._done.wait(self._every / 4):
            with self._lock:
                if self._enabled and time.monotonic() - self._last >= self._every:
                    self._line()

    def update_to(self, n: int, total: int | None = None, postfix: str = "") -> None:
        """Set the units done (and the total, and a short status text)."""
        if total is not None:
            self.total = total
        self._postfix = postfix or self._postfix
        delta, self.n = n - self.n, n
        if self._bar is not None:
            if total is not None and self._bar.total != total:
                self._bar.total = total
            if postfix:
                self._bar.set_postfix_str(postfix, refresh=False)
            self._bar.update(delta)
        elif self._enabled and time.monotonic() - self._last >= self._every:
            with self._lock:
                if time.monotonic() - self._last >= self._every:  # the heartbeat may have printed
                    self._line()

    def advance(self, k: int = 1, postfix: str = "") -> None:
        self.update_to(self.n + k, postfix=postfix)

    def _line(self) -> None:
        self._last = time.monotonic()
        elapsed = self._last - self._t0
        done = f"{self.n}/{self.total}" if self.total else str(self.n)
        text = f"{self.desc}: {done} {self.unit}s"
        if self.total:
            frac = min(1.0, self.n / self.total)
            eta = f"{elapsed * (1 - frac) / frac:.0f} s" if frac > 0 else "?"
            text += f" ({100 * frac:.0f}%), {elapsed:.0f} s elapsed, ETA {eta}"
        else:
            text += f", {elapsed:.0f} s elapsed"
        if self._postfix:
            text += f" [{self._postfix}]"
        print(text, file=self._stream, flush=True)

    def stop(self, reason: str) -> None:
        """End the job early at the units done, saying why (the display stays below 100 %)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        with self._lock:
            if self._enabled:
                done = f"{self.n}/{self.total}" if self.total else str(self.n)
                print(f"{self.desc}: stopped at {done} {self.unit}s: {reason}", file=self._stream, flush=True)
            self._enabled = False
        self._done.set()

    def close(self, *, final_line: bool = True) -> None:
        if self._bar is not None:
            self._bar.close()
        with self._lock:
            if self._bar is None and self._enabled and final_line:
                self._line()
            self._enabled = False
        self._done.set()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self.close(final_line=exc_type is None)  # a failed job's error is the last word
