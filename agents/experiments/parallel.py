"""Independent experiment units in worker processes (``--jobs``).

A unit is a picklable zero-argument callable (a module-level function bound with
:func:`functools.partial`) that writes what it finishes into the run's folder (models,
kept JSON scores), so a run stopped part way resumes from the units already done. Units
draw from their own seeds, so ``jobs`` changes how long a run takes, not what it finds.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import TypeVar

__all__ = ["MAX_JOBS", "check_jobs", "run_all"]

T = TypeVar("T")
MAX_JOBS = 64  # worker processes an experiment may ask for


def check_jobs(jobs: object) -> int:
    """``jobs`` if it is an integer in ``[1, MAX_JOBS]``; otherwise a ValueError naming it."""
    if isinstance(jobs, bool) or not isinstance(jobs, int) or not 1 <= jobs <= MAX_JOBS:
        raise ValueError(f"jobs must be an integer in [1, {MAX_JOBS}], got {jobs!r}")
    return jobs


PARENT_POLL_S = 1.0  # how often a worker checks that the process that started it is alive


def _worker_start(parent: int) -> None:
    """Worker start-up: BLAS on one thread (``jobs`` processes share the cores), and an exit
    once ``parent`` (the experiment's process) is gone, so that killing an experiment leaves
    no workers computing for nobody."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    threading.Thread(target=_exit_with, args=(parent,), daemon=True, name="parent-watch").start()


def _exit_with(parent: int) -> None:
    while True:
        time.sleep(PARENT_POLL_S)
        try:
            os.kill(parent, 0)
        except ProcessLookupError:
            os._exit(1)
        except PermissionError:  # alive, another user's: cannot be ours
            pass


def run_all(
    units: Sequence[Callable[[], T]], jobs: int = 1, tick: Callable[[int], None] | None = None
) -> list[T]:
    """Each unit's result, in the order given; ``tick(i)`` after unit ``i`` finishes.

    ``jobs`` 1 runs them here, one after the other; more start that many worker processes
    (at most one per unit and one per core), each with single-threaded BLAS, each ending when this process
    ends (killed or not). The first unit to fail cancels
    the units not yet started and its error is raised once the running ones finish (what
    they finished is kept on disk for a resumed run)."""
    check_jobs(jobs)
    if jobs == 1 or len(units) <= 1:
        out = []
        for i, unit in enumerate(units):
            out.append(unit())
            if tick:
                tick(i)
        return out
    ctx = multiprocessing.get_context("forkserver" if os.name == "posix" else "spawn")
    workers = min(jobs, len(units), os.cpu_count() or 1)  # memory grows with workers, not speed
    with ProcessPoolExecutor(
        workers, mp_context=ctx, initializer=_worker_start, initargs=(os.getpid(),)
    ) as pool:
        futures = [pool.submit(unit) for unit in units]
        index = {f: i for i, f in enumerate(futures)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)  # a tick as each ends
            for f in done:
                if f.exception() is not None:
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise f.exception()  # type: ignore[misc]
                if tick:
                    tick(index[f])
        return [f.result() for f in futures]
