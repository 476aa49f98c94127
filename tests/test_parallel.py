"""Experiment units in worker processes (agents.experiments.parallel)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from agents.experiments.parallel import MAX_JOBS, PARENT_POLL_S, check_jobs, run_all


def _draw(seed: int) -> tuple[int, float]:
    return os.getpid(), float(np.random.default_rng(seed).normal())


def _blas_threads() -> list[int]:
    from threadpoolctl import threadpool_info

    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def _fail(path: Path) -> None:
    raise RuntimeError(f"unit failed at {path}")


def _write(path: Path) -> int:
    path.write_text("done")
    return 1


def test_workers_give_the_serial_results_in_order() -> None:
    units = [partial(_draw, seed) for seed in range(5)]
    ticks: list[tuple[int, int]] = []
    serial = run_all(units, 1, lambda i: ticks.append((1, i)))
    pooled = run_all(units, 2, lambda i: ticks.append((2, i)))
    assert [v for _, v in pooled] == [v for _, v in serial]
    assert {pid for pid, _ in serial} == {os.getpid()}
    assert os.getpid() not in {pid for pid, _ in pooled}  # they ran in other processes
    assert ticks[:5] == [(1, i) for i in range(5)]  # each tick names the unit that finished
    assert sorted(ticks[5:]) == [(2, i) for i in range(5)]
    for threads in run_all([_blas_threads, _blas_threads], 2):
        assert threads and set(threads) == {1}  # one BLAS thread per worker


def _wait_for(path: Path) -> bool:
    """Whether ``path`` appears within 30 s."""
    end = time.monotonic() + 30
    while not path.exists():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


def test_each_unit_ticks_as_it_ends_not_when_all_have(tmp_path: Path) -> None:
    """The first unit's tick writes the file the second waits for: ticks held back until
    every unit ended (waiting for the first exception, i.e. for all) leave it waiting."""
    flag = tmp_path / "ticked"
    seen = run_all([partial(_write, tmp_path / "first"), partial(_wait_for, flag)], 2, lambda i: flag.touch())
    assert seen == [1, True]


def test_a_failing_units_error_reaches_the_caller(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="unit failed"):
        run_all([partial(_fail, tmp_path / "x"), partial(_write, tmp_path / "y")], 2)
    assert run_all([], 2) == []


def _record_and_sleep(folder: str) -> None:
    Path(folder, str(os.getpid())).write_text("")
    time.sleep(120)


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"


@pytest.mark.skipif(not Path("/proc").exists(), reason="reads process states from /proc")
def test_killing_the_experiment_ends_its_workers(tmp_path: Path) -> None:
    n = min(2, os.cpu_count() or 1)  # workers that run at once
    code = (
        f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); from functools import partial; "
        "import test_parallel as t; from agents.experiments.parallel import run_all; "
        f"run_all([partial(t._record_and_sleep, {str(tmp_path)!r})] * {n}, 2)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code])
    deadline = time.monotonic() + 60
    while len(list(tmp_path.iterdir())) < n and time.monotonic() < deadline:
        time.sleep(0.1)
    workers = [int(p.name) for p in tmp_path.iterdir()]
    assert len(workers) == n and all(_running(w) for w in workers)
    proc.kill()  # no clean-up in the experiment's process
    proc.wait()
    deadline = time.monotonic() + 10 * PARENT_POLL_S
    while any(_running(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_running(w) for w in workers)


@pytest.mark.parametrize("jobs", [0, -1, MAX_JOBS + 1, 1.5, "2", True, None])
def test_jobs_out_of_range_is_refused_naming_the_field(jobs: object) -> None:
    with pytest.raises(ValueError, match="jobs must be an integer"):
        check_jobs(jobs)
    with pytest.raises(ValueError, match="jobs must be an integer"):
        run_all([], jobs)  # type: ignore[arg-type]
