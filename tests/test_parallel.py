"""Experiment units in worker processes (agents.experiments.parallel)."""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from agents.experiments.parallel import MAX_JOBS, check_jobs, run_all


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
    ticks: list[int] = []
    serial = run_all(units, 1, lambda: ticks.append(1))
    pooled = run_all(units, 2, lambda: ticks.append(2))
    assert [v for _, v in pooled] == [v for _, v in serial]
    assert {pid for pid, _ in serial} == {os.getpid()}
    assert os.getpid() not in {pid for pid, _ in pooled}  # they ran in other processes
    assert ticks == [1] * 5 + [2] * 5
    for threads in run_all([_blas_threads, _blas_threads], 2):
        assert threads and set(threads) == {1}  # one BLAS thread per worker


def test_a_failing_units_error_reaches_the_caller(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="unit failed"):
        run_all([partial(_fail, tmp_path / "x"), partial(_write, tmp_path / "y")], 2)
    assert run_all([], 2) == []


@pytest.mark.parametrize("jobs", [0, -1, MAX_JOBS + 1, 1.5, "2", True, None])
def test_jobs_out_of_range_is_refused_naming_the_field(jobs: object) -> None:
    with pytest.raises(ValueError, match="jobs must be an integer"):
        check_jobs(jobs)
    with pytest.raises(ValueError, match="jobs must be an integer"):
        run_all([], jobs)  # type: ignore[arg-type]
