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

With ``WHOLE_TEST_FILES=1`` in the environment, a second repair: each function's tests are
all the tests of the files of the tests mutmut mapped it to. mutmut maps a function to the
tests during whose setup, call or teardown it ran, so a function that only a module- or
session-scoped fixture calls is mapped to the first test that built the fixture, and a
mutant there is never run against the file's other tests, which may be the ones that see
it (``fit_circular``'s angle-output mutants survived this way, 2026-12-05). The driver
(``mutate_sample.py``) runs the survivors of a run again with it.

Run from the repository root with mutmut's own arguments: ``python
docs/results/mutation/run_mutmut.py run --max-children 2``.
"""

from __future__ import annotations

import os
from collections import defaultdict
from datetime import datetime

import mutmut.__main__ as mutmut_main
from mutmut.__main__ import cli
from mutmut.state import state
from mutmut.workers import isolation

#: environment variable: map each function to every test of its tests' files
WHOLE_TEST_FILES = "WHOLE_TEST_FILES"


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


def whole_files(tests_by_function: dict[str, set[str]], all_tests: set[str]) -> dict[str, set[str]]:
    """Each function's tests widened to every test (of ``all_tests``) in their files."""
    by_file: defaultdict[str, set[str]] = defaultdict(set)
    for t in all_tests:
        by_file[t.split("::", 1)[0]].add(t)
    return {f: set().union(*(by_file[t.split("::", 1)[0]] for t in tests)) if tests else set()
            for f, tests in tests_by_function.items()}  # fmt: skip


def _widen_after_stats() -> None:
    """Widen mutmut's map of tests (:func:`whole_files`) each time it collects or loads it."""
    collect = mutmut_main.collect_or_load_stats

    def collect_then_widen(*args, **kwargs):
        collect(*args, **kwargs)
        tests = state().tests_by_mangled_function_name
        known = set(state().duration_by_test)
        for function, wider in whole_files(tests, known).items():
            tests[function] = wider

    mutmut_main.collect_or_load_stats = collect_then_widen


if __name__ == "__main__":
    _repair()
    if os.environ.get(WHOLE_TEST_FILES) == "1":
        _widen_after_stats()
    cli()
