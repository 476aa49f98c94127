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

With ``SHARED_FIXTURES=1`` in the environment, a second repair: each function's tests also
take every test that shares one of their module-, class-, package- or session-scoped
fixtures (the project's own, not pytest's). mutmut maps a function to the tests during
whose setup, call or teardown it ran, so a function that only such a fixture calls is mapped
to the first test that built the fixture, and a mutant there is never run against the other
tests of that fixture, which may be the ones that see it (``fit_circular``'s angle-output
mutants survived this way, 2026-12-05). The fixtures come from a collection run in a process
of its own (``--shared-fixtures FILE``), so mutmut's process stays free of the tests. The
driver (``mutate_sample.py``) runs the survivors of a run again with it.

Run from the repository root with mutmut's own arguments: ``python
docs/results/mutation/run_mutmut.py run --max-children 2``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections import defaultdict
from datetime import datetime

import mutmut.__main__ as mutmut_main
from mutmut.__main__ import cli
from mutmut.configuration import config
from mutmut.state import state
from mutmut.workers import isolation

#: environment variable: widen each function's tests by the tests sharing their fixtures
SHARED_FIXTURES = "SHARED_FIXTURES"
SCOPES = ("class", "module", "package", "session")  # fixtures built once for several tests
COLLECT_TIMEOUT_S = 600  # the collection run (13 s on this repository's 586 tests)


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


def widen(tests_by_function: dict[str, set[str]], fixtures: dict[str, list[str]]) -> dict[str, set[str]]:
    """Each function's tests with every test sharing one of their ``fixtures`` (per test id,
    its wider-scoped fixtures' ids: :func:`shared_fixtures`)."""
    users: defaultdict[str, set[str]] = defaultdict(set)
    for test, keys in fixtures.items():
        for k in keys:
            users[k].add(test)
    return {f: set(tests).union(*(users[k] for t in tests for k in fixtures.get(t, ())))
            for f, tests in tests_by_function.items()}  # fmt: skip


def shared_fixtures(args: list[str]) -> dict[str, list[str]]:
    """Per test id collected by ``pytest --collect-only args``, the ids
    (``baseid::name``) of the project's fixtures of a scope in :data:`SCOPES` it uses."""
    import pytest

    class Collector:
        def __init__(self) -> None:
            self.found: dict[str, list[str]] = {}

        def pytest_collection_modifyitems(self, items) -> None:
            for item in items:
                info = getattr(item, "_fixtureinfo", None)
                defs = [] if info is None else [d[-1] for d in info.name2fixturedefs.values() if d]
                self.found[item.nodeid] = sorted(
                    f"{d.baseid}::{d.argname}" for d in defs if d.scope in SCOPES and d.baseid
                )

    collector = Collector()
    code = pytest.main(["--collect-only", "-q", *args], plugins=[collector])
    if code not in (0, 5):  # 5: no tests collected
        raise SystemExit(f"run_mutmut.py --shared-fixtures: pytest could not collect the tests (exit {code})")
    return collector.found


def _collect_fixtures() -> dict[str, list[str]]:
    """:func:`shared_fixtures` of mutmut's copy of the tests, in a process of its own."""
    cfg = config()
    with tempfile.TemporaryDirectory() as tmp:
        out = f"{tmp}/fixtures.json"
        cmd = [sys.executable, __file__, "--shared-fixtures", out, *cfg.pytest_add_cli_args,
               *cfg.pytest_add_cli_args_test_selection]  # fmt: skip
        run = subprocess.run(cmd, cwd="mutants", capture_output=True, text=True, timeout=COLLECT_TIMEOUT_S)
        if run.returncode != 0:
            raise SystemExit(f"run_mutmut.py: collecting the tests' fixtures failed:\n{run.stdout[-2000:]}"
                             f"{run.stderr[-2000:]}")  # fmt: skip
        with open(out) as f:
            return json.load(f)


def _widen_after_stats() -> None:
    """Widen mutmut's map of tests (:func:`widen`) each time it collects or loads it."""
    collect = mutmut_main.collect_or_load_stats

    def collect_then_widen(*args, **kwargs):
        collect(*args, **kwargs)
        fixtures = _collect_fixtures()
        tests, known = state().tests_by_mangled_function_name, set(state().duration_by_test)
        for function, wider in widen(tests, fixtures).items():
            tests[function] = wider & known | tests[function]

    mutmut_main.collect_or_load_stats = collect_then_widen


if __name__ == "__main__":
    if sys.argv[1:2] == ["--shared-fixtures"]:  # the collection run of _collect_fixtures
        sys.path.insert(0, os.getcwd())  # the mutated copy, as mutmut's own runs import it

        with open(sys.argv[2], "w") as f:
            json.dump(shared_fixtures(sys.argv[3:]), f)
        sys.exit(0)
    _repair()
    if os.environ.get(SHARED_FIXTURES) == "1":
        _widen_after_stats()
    cli()
