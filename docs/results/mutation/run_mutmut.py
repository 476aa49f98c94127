"""``mutmut run`` with one repair, for ``make mutate`` and ``make mutate-sample``.

mutmut 3.8's fork runner waits for *any* child process (``os.wait``) and stops with a
``KeyError`` when the child that ended is not one of its workers: a process a test started
in mutmut's own process (its clean and coverage runs happen there) and that ends later. Seen
twice on this repository (``KeyError: 25787`` and ``29124``, both runs lost). Here such a
child is reaped and skipped; every worker's result is read as before.

``[tool.mutmut]`` now sets ``process_isolation = "forkserver"`` (mutmut's fork server, which
this repair does not touch): the fork runner's children inherited the zenoh sessions of
mutmut's own test runs and hung closing them (``../gp_models_base/README.md``). The
scores committed before 2026-12-05 16:00 UTC were measured with the fork runner. The repair
reads the runner's private fields, so it refuses to run on a mutmut whose runner lacks them.

Run from the repository root with mutmut's own arguments: ``python
docs/results/mutation/run_mutmut.py run --max-children 2``.
"""

from __future__ import annotations

import os
from datetime import datetime

from mutmut.__main__ import cli
from mutmut.workers import isolation


def _wait_for_result(self: isolation.ForkRunner, timeout: float | None = None) -> isolation.MutantResult:
    """mutmut's ``ForkRunner.wait_for_result``, skipping children that are not its workers."""
    if self._no_tests_results:
        return self._no_tests_results.pop(0)
    while True:
        pid, wait_status = os.wait()
        if pid in self._running:
            break
    worker = self._running.pop(pid)
    duration = (datetime.now() - worker.start_time).total_seconds()
    return isolation.MutantResult(
        mutant_name=worker.mutant_name, exit_code=os.waitstatus_to_exitcode(wait_status), duration=duration
    )


def _repair() -> None:
    """Put :func:`_wait_for_result` in place, or stop naming what this mutmut lacks."""
    import inspect

    source = inspect.getsource(isolation.ForkRunner)
    missing = [f for f in ("self._running", "self._no_tests_results", "os.wait()") if f not in source]
    if missing:
        raise SystemExit(f"run_mutmut.py: this mutmut's ForkRunner has no {', '.join(missing)}: "
                         "run mutmut directly (or with process_isolation = 'forkserver')")  # fmt: skip
    isolation.ForkRunner.wait_for_result = _wait_for_result  # type: ignore[method-assign]


if __name__ == "__main__":
    _repair()
    cli()
