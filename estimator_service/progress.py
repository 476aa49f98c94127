"""One progress display per long job: a bar with a total and an ETA in a terminal, plain
periodic lines (``desc: 120/480 steps (25%), 3 s elapsed, ETA 9 s``) when the output is a
file or a pipe, nothing with ``enabled=False``. Units of unequal cost take ``weights`` (each
unit's estimated seconds): the percentage and the ETA then follow the weight done, the
count still counts units. The plain lines keep coming every
``every_s`` seconds while a long unit of work reports nothing (a background timer), so a log
never falls silent for minutes."""

from __future__ import annotations

import math
import sys
import threading
from collections.abc import Sequence
from time import monotonic
from typing import TextIO

import numpy as np

__all__ = ["ProgressBar"]

WEIGHT_STEPS = 1000  # a weighted terminal bar's resolution
#: a weighted terminal bar (tqdm writes ", " before a postfix)
WEIGHTED_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}{postfix}]"


def _cumulative(weights: Sequence[float]) -> np.ndarray:
    """``(len + 1,)`` running sums from 0, after checking every weight is finite and positive."""
    w = np.asarray(weights, dtype=float)
    if w.ndim != 1 or not len(w) or not (np.isfinite(w).all() and (w > 0).all()):
        raise ValueError(f"weights must be a non-empty list of positive finite numbers, got {weights!r}")
    return np.concatenate([[0.0], np.cumsum(w)])


class ProgressBar:
    """Progress of a job of ``total`` units (the total may be set later, see :meth:`update_to`).

    Parameters
    ----------
    every_s
        Seconds between two plain lines when the stream is not a terminal (also while no
        progress is reported, from a background thread until :meth:`close` or :meth:`stop`:
        use the bar as a context manager so an error ends it too).
    weights: (total,)
        Each unit's estimated cost (positive, any scale; e.g.
        :func:`estimator_service.work.part_weights`): the share done and the ETA are the
        weight of the units done over the whole weight. The total is then ``len(weights)``.
    done
        With ``weights``: the indices of units already done before this job started (a
        resumed run's kept work). They count as done from the start, do not set the pace of
        the ETA (their cost is not this job's), and a later ``advance(index=...)`` of one of
        them changes nothing.
    """

    def __init__(
        self, desc: str, total: int | None = None, *, unit: str = "step", enabled: bool = True,
        stream: TextIO | None = None, every_s: float = 10.0, weights: Sequence[float] | None = None,
        done: Sequence[int] = (),
    ) -> None:  # fmt: skip
        if not (math.isfinite(every_s) and every_s > 0):
            raise ValueError(f"every_s must be a positive number of seconds, got {every_s!r}")
        self._cum = None if weights is None else _cumulative(weights)
        if self._cum is not None:
            if total is not None and total != len(weights):
                raise ValueError(f"total {total} differs from the {len(weights)} weights")
            total = len(weights)
        self.desc, self.total, self.unit = desc, total, unit
        self._units_done = self._kept_units(done)  # with weights: the indices of the units done
        self._by_index = bool(self._units_done)  # units counted by their index, not in order
        self.n = len(self._units_done)
        # with weights: the weight of the units done, and of those done before this job began
        self._weight_done = self._weight_kept = sum(self._unit_weight(i) for i in self._units_done)
        self._stream = stream or sys.stderr
        self._enabled, self._every = enabled, every_s
        self._t0 = self._last = self._t_done = monotonic()  # _t_done: when the share last grew
        self._postfix = ""
        self._bar = None
        self._lock, self._done = threading.Lock(), threading.Event()
        if enabled and getattr(self._stream, "isatty", lambda: False)():
            from tqdm import tqdm

            if self._cum is None:
                self._bar = tqdm(total=total, desc=desc, unit=unit, file=self._stream, dynamic_ncols=True)
            else:  # the bar's length and rate in weight: the count of units goes in the postfix
                kept = round(WEIGHT_STEPS * self._fraction())  # tqdm's rate leaves out its initial
                self._bar = tqdm(total=WEIGHT_STEPS, desc=desc, file=self._stream, dynamic_ncols=True,
                                 bar_format=WEIGHTED_FORMAT, initial=kept)  # fmt: skip
        elif enabled:
            threading.Thread(target=self._heartbeat, name=f"progress {desc}", daemon=True).start()

    def _kept_units(self, done: Sequence[int]) -> set[int]:
        """``done`` checked: only with weights, each index one of the units."""
        if len(done) and self._cum is None:
            raise ValueError("done needs weights: the units done are indices into them")
        bad = [i for i in done if not (isinstance(i, int | np.integer) and 0 <= i < len(self._cum) - 1)]
        if bad:
            raise ValueError(f"done: {bad} not among the {len(self._cum) - 1} weighted units")
        return {int(i) for i in done}

    def _unit_weight(self, index: int) -> float:
        return float(self._cum[index + 1] - self._cum[index])

    def _heartbeat(self) -> None:
        """A plain line whenever ``every_s`` passed without one, until the job ends."""
        while not self._done.wait(self._every / 4):
            with self._lock:
                if self._enabled and monotonic() - self._last >= self._every:
                    self._line()

    def update_to(self, n: int, total: int | None = None, postfix: str = "") -> None:
        """Set the units done (and the total, and a short status text)."""
        if total is not None:
            if self._cum is not None and total != self.total:
                raise ValueError(f"total {total} differs from the {self.total} weights")
            self.total = total
        self._postfix = postfix or self._postfix
        if self._cum is not None:
            self._weight_done = float(self._cum[min(max(n, 0), len(self._cum) - 1)])
        elif self._bar is not None and total is not None and self._bar.total != total:
            self._bar.total = total
        self._show(n, postfix)

    def _show(self, n: int, postfix: str) -> None:
        if n > self.n:
            self._t_done = monotonic()
        delta, self.n = n - self.n, n
        if self._bar is not None:
            if self._cum is not None:
                status = f"{self._count()} {self.unit}s" + (f", {self._postfix}" if self._postfix else "")
                self._bar.set_postfix_str(status, refresh=False)
                self._bar.update(round(WEIGHT_STEPS * self._fraction()) - self._bar.n)
                return
            if postfix:
                self._bar.set_postfix_str(postfix, refresh=False)
            self._bar.update(delta)
        elif self._enabled and monotonic() - self._last >= self._every:
            with self._lock:
                if monotonic() - self._last >= self._every:  # the heartbeat may have printed
                    self._line()

    def advance(self, k: int = 1, postfix: str = "", *, index: int | None = None) -> None:
        """``k`` more units done; with weights and ``index``, the one unit ``index`` (units
        that end out of order, e.g. in worker processes), else the next ``k`` in order."""
        if index is None or self._cum is None:
            self.update_to(self.n + k, postfix=postfix)
            return
        if not 0 <= index < len(self._cum) - 1:
            raise ValueError(f"index {index} is not one of the {len(self._cum) - 1} weighted units")
        self._postfix = postfix or self._postfix
        self._by_index = True
        if index in self._units_done:  # counted already (kept from before this job)
            return
        self._units_done.add(index)
        self._weight_done += self._unit_weight(index)
        self._show(self.n + 1, postfix)

    def _count(self) -> str:
        return f"{self.n}/{self.total}" if self.total else str(self.n)

    def _fraction(self) -> float:
        """The share done: units, or with weights the weight of the units done."""
        if self._cum is not None:
            return min(1.0, self._weight_done / float(self._cum[-1]))
        return min(1.0, self.n / self.total) if self.total else 0.0

    def _next_share(self) -> float:
        """The share of the job the running unit stands for (0 when none is left): the next
        in order, or, where units are counted by index (kept units, units ending out of
        order), the lowest index not done, the unit that began first among those left."""
        if not self.total or self.n >= self.total:
            return 0.0
        if self._cum is None:
            return 1.0 / self.total
        i = min(set(range(self.total)) - self._units_done) if self._by_index else self.n
        return self._unit_weight(i) / float(self._cum[-1])

    def _eta(self, now: float) -> float | None:
        """Seconds left: the share left at the pace of the share this job did (up to when it
        last grew; units kept from before it are not its pace), less the time the running
        unit has taken, at most its own estimate, so the ETA counts down while a long unit
        runs instead of growing with the elapsed time."""
        frac = self._fraction()
        worked = frac - (self._weight_kept / float(self._cum[-1]) if self._cum is not None else 0.0)
        if worked <= 0:
            return None if frac < 1 else 0.0
        per_share = (self._t_done - self._t0) / worked  # seconds per share at the pace so far
        running = min(now - self._t_done, per_share * self._next_share())
        return max(0.0, per_share * (1 - frac) - running)

    def _line(self) -> None:
        self._last = monotonic()
        elapsed = self._last - self._t0
        text = f"{self.desc}: {self._count()} {self.unit}s"
        if self.total:
            frac, left = self._fraction(), self._eta(self._last)
            eta = f"after the first {self.unit}" if left is None else f"{left:.0f} s"
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
                print(f"{self.desc}: stopped at {self._count()} {self.unit}s: {reason}", file=self._stream,
                      flush=True)  # fmt: skip
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
