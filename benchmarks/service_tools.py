"""Helpers for ``bench_service``: the service process, its timestamped variant's legs and
the bare zenoh floors it is compared with."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from estimator_service.service.client import EstimatorClient, free_port, open_session, spawn_service

WARM_UP = 20  # round trips and steps run before measuring (the service's first ones are slow)
SERVE_ARGS: list[str] = []  # extra ``gpbf serve`` options for every service started (``--serve-arg``)


@contextmanager
def service_session(
    models: Path, model: str, trace: Path | None = None, pids: list[int] | None = None
) -> Iterator[Any]:
    """A zenoh session connected to ``gpbf serve`` (in another process, serving ``model``;
    with ``trace``, the timestamped one of service_trace.py); both closed on exit. The
    service's process id is appended to ``pids`` when given."""
    tracer = (sys.executable, str(Path(__file__).with_name("service_trace.py")), str(trace))
    kw = {} if trace is None else {"command": tracer}
    port = free_port()
    proc, _ = spawn_service(models, port, "--model", model, *SERVE_ARGS, merge_stderr=False, **kw)
    if pids is not None:
        pids.append(proc.pid)
    session = open_session([f"tcp/127.0.0.1:{port}"])
    try:
        time.sleep(0.3)
        yield session
    finally:
        session.close()
        proc.terminate()
        proc.wait(timeout=20)


@contextmanager
def fleet_session(models: Path, model: str, n: int = 2) -> Iterator[Any]:
    """A zenoh session connected to ``n`` ``gpbf serve`` processes that form one fleet (each
    connects to the first); all closed on exit."""
    ports = [free_port() for _ in range(n)]
    join = ("--connect", f"tcp/127.0.0.1:{ports[0]}")
    procs = [
        spawn_service(models, port, "--model", model, *(join if i else ()), *SERVE_ARGS, merge_stderr=False)[
            0
        ]
        for i, port in enumerate(ports)
    ]
    session = open_session([f"tcp/127.0.0.1:{port}" for port in ports])
    try:
        time.sleep(1.0)  # the services see each other's liveliness tokens
        yield session
    finally:
        session.close()
        for proc in procs:
            proc.terminate()
        for proc in procs:
            proc.wait(timeout=20)


def step_inputs(rng: np.random.Generator, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` lock-step inputs: a control ``(3,)`` and two cameras' ellipses ``(10,)`` each."""
    return [(rng.normal(size=3), rng.normal(size=10) * 0.3) for _ in range(n)]


def lockstep(
    session, blimp: str, filt: str, model: str, mean: np.ndarray, inputs: list
) -> tuple[np.ndarray, np.ndarray]:
    """Reset ``blimp`` at ``mean`` and step it through ``inputs`` over zenoh: each step's send
    and receive times ``(N, 2)`` and the service's own step times ``(N,)``, in seconds."""
    c = EstimatorClient(session, blimp)
    c.reset(mean, np.full(12, 0.1), t=0.0, filter=filt, model=model)
    times, served = [], []
    for k, (u, z) in enumerate(inputs):
        t0 = time.perf_counter()
        reply = c.step(u, [[0, z[:5].tolist()], [1, z[5:].tolist()]], 0.25 * (k + 1))
        times.append((t0, time.perf_counter()))
        served.append(reply["step_ms"] / 1e3)
    return np.array(times), np.array(served)


def phases(models: Path, n: int) -> dict[str, float]:
    """p50 (ms) of each leg of a GP-EKF round trip, from a timestamped service (one clock)."""
    trace = models / "trace.json"
    with service_session(models, "gp", trace) as session:
        rng = np.random.default_rng(3)
        mean = rng.normal(size=12) * 0.5
        times = lockstep(session, "trace", "ekf", "gp", mean, step_inputs(rng, n + WARM_UP))[0]
    send, recv = times[WARM_UP:].T
    cb, worker, start, end, replied = np.array(json.loads(trace.read_text())[WARM_UP:]).T
    legs = {
        "zenoh_in": cb - send, "queue_hand_off": worker - cb, "dispatch": start - worker,
        "step": end - start, "reply_to_zenoh": replied - end, "zenoh_out": recv - replied,
        "zenoh": (cb - send) + (recv - replied),  # both legs of each round trip
        "service_code": (worker - cb) + (start - worker) + (replied - end),
    }  # fmt: skip
    return {k: float(np.median(v) * 1e3) for k, v in legs.items()}


def factor_mb(models: Path, kind: str = "gp") -> float:
    """MB of Cholesky factors one step reads (lower triangles of every exact GP's ``P`` factors
    of ``n x n``, factored on load: its ``alpha`` of ``(P, n)`` gives the sizes)."""
    total = 0
    for path in models.glob(f"*_{kind}*.npz"):
        with np.load(path) as f:
            shapes = [f[k].shape for k in f.files if k.endswith("alpha")]
        total += sum(p * n * n * 8 // 2 for p, n in shapes)
    return total / 2**20


@contextmanager
def echo_session(work_s: float, stream_mb: float = 0.0, pids: list[int] | None = None) -> Iterator[Any]:
    """A zenoh session connected to a bare queryable (``zenoh_echo.py``) in another process
    (its process id appended to ``pids`` when given)."""
    port = free_port()
    echo = Path(__file__).with_name("zenoh_echo.py")
    proc = subprocess.Popen(
        [sys.executable, str(echo), str(port), str(work_s), str(stream_mb)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert "ready" in proc.stdout.readline()
    if pids is not None:
        pids.append(proc.pid)
    session = open_session([f"tcp/127.0.0.1:{port}"])
    time.sleep(0.3)
    try:
        yield session
    finally:
        session.close()
        proc.stdin.close()
        proc.wait(timeout=20)


def cpu_seconds(pid: int) -> float:
    """CPU seconds process ``pid``'s threads have run, from Linux's per-thread
    ``/proc/<pid>/task/<tid>/schedstat`` (nanoseconds; a thread that ended between two
    readings is missing from the second, so measure across threads that live on); from
    ``/proc/<pid>/stat``'s user and system time (clock ticks) on a kernel without schedstat."""
    total, read = 0, False
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            total += int((task / "schedstat").read_text().split()[0])
            read = True
        except FileNotFoundError:  # the thread ended while we read, or no schedstat
            continue
    if read:
        return total / 1e9
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def echo_floor(work_ms: float, n: int, stream_mb: float = 0.0) -> float:
    """p50 of (round trip - work) to a bare zenoh queryable doing ``work_ms`` per query, over
    ``n`` queries after ``WARM_UP`` uncounted ones (as the service's round trips).

    With ``stream_mb`` the work reads that many MB once (then spins for the rest); the
    echo reports how long its work took, and that is what is subtracted.
    """
    out = []
    with echo_session(work_ms / 1e3, stream_mb) as session:
        for _ in range(n + WARM_UP):
            t0 = time.perf_counter()
            reply = session.get("echo/x", payload=b"y" * 150).recv()
            out.append(time.perf_counter() - t0 - float(reply.ok.payload.to_bytes().decode()))
    return float(np.median(np.array(out[WARM_UP:]) * 1e3))
