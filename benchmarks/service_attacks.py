"""A hostile peer against real ``gpbf serve`` processes: the figures ``bench_service.py``
adds to its last line (each scenario as the service's tests run it, measured here).

* :func:`forged_tokens`: a peer declares 100 liveliness tokens under the fleet's key while
  10 blimps are served; then 10 new blimps reset. ``forged_token_sessions_lost`` (sessions
  gone after the tokens are withdrawn) and ``forged_token_resets_ok`` (fraction of the new
  resets and old steps answered).
* :func:`frozen_owner`: two services through a router; the owner of some blimps is stopped
  (SIGSTOP). ``hung_owner_failover_s``: from the stop to the first step of one of its blimps
  served by the survivor (the client retries on time-outs); ``stale_owner_overrides``: after
  the owner wakes (SIGCONT), its blimps whose next step was served from its stale session
  instead of one re-created from the survivor's belief.
* :func:`near_horizon`: two attacking blimps, one on the EKF and one on the particle filter,
  send chains of camera frames each just inside the 60 s horizon while a healthy blimp
  lock-steps: ``near_horizon_healthy_p99_ms``, its step latency's 99th percentile. A
  catch-up the budget accepts (up to ``--catch-up-burst``, 2 s) holds a worker until done,
  and a new particle-filter session's first frame costs one full particle-filter step
  (0.3-0.6 s with 2,000 particles on the paper-size GP) before its step time is known.
* :func:`queue_bytes_max_mb`: 300 inputs of 60 KB sent to one blimp while its worker runs
  a particle-filter step; the most payload its queue held (``queue_bytes`` in the sessions
  listing), in 10^6 bytes (the cap: ``--queue-bytes``).
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from service_tools import SERVE_ARGS

from estimator_service.service import keys
from estimator_service.service.client import (
    EstimatorClient,
    ServiceError,
    free_port,
    list_sessions,
    open_session,
    spawn_service,
)

__all__ = ["forged_tokens", "frozen_owner", "near_horizon", "queue_bytes_max_mb"]

MEAN, STD = np.zeros(12), np.repeat([0.05, 0.035, 0.05, 0.035], 3)
U = np.zeros(3)
ELLIPSE = [320.0, 240.0, 40.0, 20.0, 0.1]
DT = 0.25


@contextlib.contextmanager
def _service(models: Path, model: str) -> Iterator[tuple[object, str]]:
    """One new ``gpbf serve`` of ``model``: a zenoh session connected to it and its endpoint;
    both closed on exit."""
    port = free_port()
    proc, _ = spawn_service(models, port, "--model", model, *SERVE_ARGS)
    try:
        endpoint = f"tcp/127.0.0.1:{port}"
        session = open_session([endpoint])
        try:
            time.sleep(0.3)
            yield session, endpoint
        finally:
            session.close()
    finally:
        proc.kill()


def queue_bytes_max_mb(models: Path, puts: int = 300, size: int = 60_000) -> float:
    """The most payload one blimp's queue held (10^6 bytes), polled in the sessions listing
    while ``puts`` inputs of ``size`` bytes arrive behind a particle-filter step."""
    with _service(models, "gp") as (session, _):
        c = EstimatorClient(session, "flood", timeout=30.0)
        c.reset(MEAN, STD, t=0.0, filter="pf")
        c.publish_camera(0, ELLIPSE, DT)  # a particle-filter step keeps the worker busy
        for _ in range(puts):
            c.publish_raw("control", b"x" * size)
        peak, deadline = 0, time.monotonic() + 3.0
        while time.monotonic() < deadline:
            rows = list_sessions(session)[0]["sessions"]
            peak = max([peak, *(r["queue_bytes"] for r in rows if r["blimp"] == "flood")])
            time.sleep(0.01)
    return round(peak / 1e6, 3)


def forged_tokens(models: Path, blimps: int = 10, tokens: int = 100) -> dict[str, float]:
    with _service(models, "sparse") as (session, endpoint):
        held = [EstimatorClient(session, f"held{i}", timeout=3.0) for i in range(blimps)]
        for c in held:
            c.reset(MEAN, STD, t=0.0)
        liar = open_session([endpoint])
        forged = [liar.liveliness().declare_token(keys.liveliness_key(f"fake-{i}")) for i in range(tokens)]
        time.sleep(1.5)
        ok = sum(_answered(lambda c=c: c.step(U, [], DT)) for c in held)
        ok += sum(_answered(lambda i=i: EstimatorClient(session, f"new{i}", timeout=3.0).reset(MEAN, STD))
                  for i in range(blimps))  # fmt: skip
        for t in forged:
            t.undeclare()
        time.sleep(0.5)
        [view] = list_sessions(session)
        lost = 2 * blimps - int(view["count"])
        liar.close()
    return {"forged_token_sessions_lost": lost, "forged_token_resets_ok": round(ok / (2 * blimps), 3)}


def _answered(call) -> bool:
    try:
        call()
        return True
    except ServiceError:
        return False


@contextlib.contextmanager
def _fleet(models: Path, n: int) -> Iterator[tuple[list, object]]:
    port = free_port()
    router = subprocess.Popen(
        [sys.executable, "-m", "estimator_service", "router", "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    started: list = []
    try:
        if "ready" not in router.stdout.readline():  # the router prints one line, or exits
            raise RuntimeError("the zenoh router did not start")
        join = ("--connect", f"tcp/127.0.0.1:{port}", "--model", "sparse", *SERVE_ARGS)
        for _ in range(n):  # each kept as soon as it runs: killed below whatever fails next
            started.append(spawn_service(models, free_port(), *join))
        session = open_session([f"tcp/127.0.0.1:{port}"])
        try:
            deadline = time.time() + 20
            while not _fleet_of(session, n):
                if time.time() > deadline:
                    raise RuntimeError(f"the {n} services did not form one fleet within 20 s")
                time.sleep(0.2)
            yield started, session
        finally:
            session.close()
    finally:
        for p, _ in started:
            p.send_signal(signal.SIGCONT)
            p.kill()
        router.kill()


def _fleet_of(session, n: int) -> bool:
    views = list_sessions(session)
    return len(views) == n and all(len(v["fleet"]) == n for v in views)


def frozen_owner(models: Path, blimps: int = 8) -> dict[str, float]:
    with _fleet(models, 2) as (started, session):
        clients = [
            EstimatorClient(session, f"frozen{i}", failover=True, failover_s=30.0) for i in range(blimps)
        ]
        owner = {c.blimp: c.reset(MEAN, STD, t=0.0)["service"] for c in clients}
        sleeper = owner[clients[0].blimp]
        victim = next(p for p, ready in started if f"service {sleeper}," in ready)
        held = [c for c in clients if owner[c.blimp] == sleeper]
        for c in clients:
            c.step(U, [], DT)
        victim.send_signal(signal.SIGSTOP)
        t0 = time.monotonic()
        served = held[0].step(U, [], 2 * DT)["service"]
        failover = time.monotonic() - t0
        assert served != sleeper, served
        for c in clients[1:]:
            c.step(U, [], 2 * DT)
        time.sleep(max(0.0, 4.0 - (time.monotonic() - t0)))  # past the service lease (2 s)
        before = {c.blimp: c.resyncs for c in held}
        victim.send_signal(signal.SIGCONT)
        time.sleep(3.0)  # the woken service rejoins the fleet
        stale = 0
        for c in held:
            b = c.step(U, [], 3 * DT)
            # a step served from the stale session: no re-creation from the survivor's belief
            stale += int(b["service"] == sleeper and c.resyncs == before[c.blimp])
    return {"hung_owner_failover_s": round(failover, 2), "stale_owner_overrides": stale}


def near_horizon(models: Path, steps: int = 60, chain: int = 32) -> dict[str, float]:
    with _service(models, "gp") as (session, _):
        good = EstimatorClient(session, "healthy", timeout=30.0)
        good.reset(MEAN, STD, t=0.0)
        attackers = [EstimatorClient(session, f"chain-{f}", timeout=30.0) for f in ("ekf", "pf")]
        for a, f in zip(attackers, ("ekf", "pf"), strict=True):
            a.reset(MEAN, STD, t=0.0, filter=f)
        for a in attackers:
            for k in range(1, chain + 1):
                a.publish_camera(0, ELLIPSE, 59.0 * k)
        times = []
        for k in range(steps):
            t0 = time.perf_counter()
            good.step(U, [], DT * (k + 1))
            times.append(1e3 * (time.perf_counter() - t0))
    return {"near_horizon_healthy_p99_ms": round(float(np.percentile(times, 99)), 1)}
