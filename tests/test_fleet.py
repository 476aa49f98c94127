"""A fleet of estimator services through a router: one owner per blimp, failover when an
owner dies, a blimp's session re-created by its client from the last belief."""

from __future__ import annotations

import contextlib
import shlex
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import zenoh

from agents.sim import collect_flight
from estimator_service.service import keys
from estimator_service.service.client import EstimatorClient, free_port, open_session, spawn_service
from estimator_service.service.protocol import decode, decode_belief
from estimator_service.training import TrainSettings, train_models

ALL, NONE = zenoh.QueryTarget.ALL, zenoh.ConsolidationMode.NONE  # every reply of every service
STD = np.repeat([0.05, 0.035, 0.05, 0.035], 3)
BLIMPS = 30


@pytest.fixture(scope="module")
def flight():
    return collect_flight(30, seed=8)


@pytest.fixture(scope="module")
def models(flight, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fleet_models")
    s = TrainSettings(n_points=50, n_pseudo=8, restarts=1, max_iter=8, hetero_iterations=1,
                      calibration_folds=2, calibration_refit=False)  # fmt: skip
    train_models([flight], out, kinds=["param", "gp"], settings=s)
    return out


def _fleet_views(session: zenoh.Session) -> list[list[str]]:
    replies = session.get(keys.sessions_key("*"), target=ALL, consolidation=NONE, timeout=2.0)
    return [decode(r.ok.payload.to_bytes())["fleet"] for r in replies if r.ok is not None]


def _answers(session: zenoh.Session, blimp: str) -> int:
    """How many services answer a status query for ``blimp`` (reply or error reply)."""
    key = keys.blimp_key(blimp, "status")
    return len(list(session.get(key, target=ALL, consolidation=NONE, timeout=2.0)))


def _wait_for_fleet(session: zenoh.Session, n: int, within: float = 20.0) -> None:
    """Until every one of ``n`` services sees a fleet of ``n``."""
    deadline = time.time() + within
    while time.time() < deadline:
        views = _fleet_views(session)
        if len(views) == n and all(len(v) == n for v in views):
            return
        time.sleep(0.2)
    raise AssertionError(f"no fleet of {n}: {_fleet_views(session)}")


@contextlib.contextmanager
def _fleet(models: Path, n: int):
    """A router and ``n`` services connected to it, and a client session once every service
    sees the fleet: ``(started, session)``, ``started`` as :func:`spawn_service` returns."""
    port = free_port()
    router = subprocess.Popen(
        [sys.executable, "-m", "estimator_service", "router", "--listen", f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    started = []
    try:
        assert "mode router" in router.stdout.readline()
        for _ in range(n):  # each kept as soon as it runs: killed below whatever fails next
            started.append(spawn_service(models, free_port(), "--connect", f"tcp/127.0.0.1:{port}"))
        session = open_session([f"tcp/127.0.0.1:{port}"])
        _wait_for_fleet(session, n)
        yield started, session
        session.close()
    finally:
        for p, _ in started:
            p.send_signal(signal.SIGCONT)  # a stopped process is killed too
            p.kill()
        router.kill()


def test_each_blimp_has_one_owner_and_survives_its_owner_dying(models, flight) -> None:
    with _fleet(models, 3) as (started, session):
        streamed: Counter = Counter()

        def count(sample: zenoh.Sample) -> None:
            streamed.update([(str(sample.key_expr), decode_belief(sample.payload.to_bytes())["seq"])])

        sub = session.declare_subscriber(keys.wildcard("belief"), count)
        clients = [EstimatorClient(session, f"blimp{i}", failover=True) for i in range(BLIMPS)]
        owner = {}
        for c in clients:
            owner[c.blimp] = c.reset(flight.state[0], STD, t=float(flight.t[0]))["service"]
        assert len(set(owner.values())) == 3  # the blimps are spread over the fleet

        def round_of_steps(k: int) -> dict[str, str]:
            served = {}
            for c in clients:
                t0 = time.perf_counter()
                b = c.step(flight.control[k], [], float(flight.t[k + 1]))
                assert time.perf_counter() - t0 < 2.0, (c.blimp, time.perf_counter() - t0)
                served[c.blimp] = b["service"]
            return served

        for k in range(3):
            assert round_of_steps(k) == owner
        assert all(_answers(session, c.blimp) == 1 for c in clients)
        dead = owner["blimp0"]
        victim = next(p for p, ready in started if f"service {dead}," in ready)
        victim.kill()
        victim.wait(timeout=10)
        for k in range(3, 8):
            served = round_of_steps(k)
            assert dead not in served.values()
        moved = {b for b, s in owner.items() if s == dead}
        assert {c.blimp for c in clients if c.resyncs} == moved
        assert all(c.resyncs == 1 for c in clients if c.resyncs)
        assert all(_answers(session, c.blimp) == 1 for c in clients)
        time.sleep(0.3)
        sub.undeclare()
        assert streamed and max(streamed.values()) == 1  # no belief delivered twice


def test_forged_liveliness_tokens_never_join_the_fleet(models, flight) -> None:
    """A peer that declares 100 liveliness tokens under ``gpbf/@service/*`` (the default, open
    configuration) becomes no fleet member: existing blimps keep being served, new resets are
    answered, the tokens are counted as unverified, and withdrawing them loses no session.
    Before the hello handshake the tokens made the service give its blimps to fake members:
    existing blimps got no reply, and the sessions were gone."""
    from estimator_service.service.client import list_sessions, spawn_service

    port = free_port()
    proc, _ = spawn_service(models, port)
    try:
        session = open_session([f"tcp/127.0.0.1:{port}"])
        time.sleep(0.3)
        clients = [EstimatorClient(session, f"held{i}", timeout=3.0) for i in range(10)]
        for c in clients:
            c.reset(flight.state[0], STD, t=float(flight.t[0]))
        liar = open_session([f"tcp/127.0.0.1:{port}"])
        tokens = [liar.liveliness().declare_token(keys.liveliness_key(f"fake-{i}")) for i in range(100)]
        time.sleep(1.5)
        for k, c in enumerate(clients):
            assert c.step(flight.control[0], [], float(flight.t[1]))["t"] == float(flight.t[1]), k
        fresh = [EstimatorClient(session, f"new{i}", timeout=3.0) for i in range(10)]
        for c in fresh:
            c.reset(flight.state[0], STD, t=float(flight.t[0]))
        [view] = list_sessions(session)
        assert len(view["fleet"]) == 1 and view["count"] == 20, view["fleet"]
        assert view["unverified_tokens"] + view["pending_tokens"] == 100
        for t in tokens:
            t.undeclare()
        time.sleep(0.5)
        assert all(c.status()["steps"] == 1 for c in clients)  # no session forgotten
        liar.close()
        session.close()
    finally:
        proc.kill()


def test_a_frozen_owner_wakes_without_its_stale_sessions(models, flight) -> None:
    """An owner frozen (SIGSTOP) past its 2 s lease loses its blimps to the survivor;
    on waking (SIGCONT) it forgets its sessions before serving anything (``fenced``), so when
    its blimps hash back to it their clients re-create them from the survivor's last belief
    instead of resuming the stale ones (which silently dropped the survivor's steps)."""
    from estimator_service.service.client import list_sessions

    with _fleet(models, 2) as (started, session):
        clients = [EstimatorClient(session, f"frozen{i}", failover=True) for i in range(12)]
        owner = {c.blimp: c.reset(flight.state[0], STD, t=float(flight.t[0]))["service"] for c in clients}
        sleeper = owner["frozen0"]
        victim = next(p for p, ready in started if f"service {sleeper}," in ready)
        held = [c for c in clients if owner[c.blimp] == sleeper]
        for c in clients:
            c.step(flight.control[0], [], float(flight.t[1]))
        victim.send_signal(signal.SIGSTOP)
        time.sleep(4.0)  # past the lease: the survivor sees the sleeper gone
        for k in (1, 2):
            for c in clients:
                assert c.step(flight.control[k], [], float(flight.t[k + 1]))["service"] != sleeper
        assert all(c.resyncs == 1 for c in held)
        victim.send_signal(signal.SIGCONT)
        _wait_for_fleet(session, 2)
        view = next(v for v in list_sessions(session) if v["service"] == sleeper)
        assert view["fenced"] == len(held) and view["count"] == 0, view
        for c in clients:
            b = c.step(flight.control[3], [], float(flight.t[4]))
            assert b["service"] == owner[c.blimp] and b["t"] == float(flight.t[4])
        assert all(c.resyncs == 2 for c in held)  # re-created from the survivor's belief


def test_a_hung_service_s_timeout_is_no_reply_and_failover_retries_it() -> None:
    """zenoh answers a query that its queryable holds past the time-out with an error reply
    ``Timeout``; the client takes it as no reply (:class:`NoReply`), so a failover client
    sends it again instead of giving up (a hung owner's blimps failed over only when the
    query itself failed, never on a time-out)."""
    from estimator_service.service.client import NoReply

    session = zenoh.open(zenoh.Config())
    held: list = []  # queries kept unanswered: a hung service
    queryable = session.declare_queryable(keys.blimp_key("hung", "status"), held.append)
    try:
        client = EstimatorClient(session, "hung", timeout=0.3)
        t0 = time.monotonic()
        with pytest.raises(NoReply, match=r"within 0\.3 s \(Timeout\)"):
            client.status()
        assert time.monotonic() - t0 < 2.0 and held
        retried = EstimatorClient(session, "hung", failover=True, attempt_timeout=0.2, failover_s=0.9)
        before = len(held)
        with pytest.raises(NoReply):
            retried._with_failover(retried.status)
        assert len(held) - before >= 3  # sent again until failover_s had passed
    finally:
        queryable.undeclare()
        session.close()


def test_the_protocol_documents_fleet_commands_and_client_mode_run_as_written(
    models, flight, tmp_path
) -> None:
    """docs/protocol.md's two-machine commands and its client-mode zenoh configuration, run
    on loopback with the documented addresses replaced by free ports: a router, a service
    in peer mode on each "machine", a third service and the robot's session in client mode,
    one fleet of three that serves a blimp."""
    from tests.doc_blocks import blocks

    page = blocks(Path(__file__).resolve().parents[1] / "docs" / "protocol.md")
    [commands] = [text for lang, text, _ in page if lang == "sh"]
    [config] = [text for lang, text, _ in page if lang == "json5"]
    router = f"127.0.0.1:{free_port()}"
    swap = {"192.0.2.10:7447": router, "models/": f"{models}/"}
    swap |= {f"127.0.0.1:{p}": f"127.0.0.1:{free_port()}" for p in (7450, 7451)}
    (tmp_path / "service.json5").write_text(config.replace("192.0.2.10:7447", router))
    lines = [line for line in commands.splitlines() if line.strip() and not line.startswith("#")]
    lines.append(f"gpbf serve --models {models} --zenoh-config service.json5")  # the text after it
    procs = []
    try:
        for line in lines:
            for a, b in swap.items():
                line = line.replace(a, b)
            gpbf, *args = shlex.split(line)
            assert gpbf == "gpbf", line
            out = {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT, "text": True}
            procs.append(subprocess.Popen([sys.executable, "-m", "agents.cli", *args], cwd=tmp_path, **out))
            first = procs[-1].stdout.readline()
            assert "mode router" in first or "ready" in first, (line, first)
        assert "mode client" in first
        session = open_session(config_file=tmp_path / "service.json5")  # the robot's side
        _wait_for_fleet(session, 3)
        c = EstimatorClient(session, "documented")
        c.reset(flight.state[0], STD, t=float(flight.t[0]))
        assert c.step(flight.control[0], [], float(flight.t[1]))["t"] == pytest.approx(flight.t[1])
        session.close()
    finally:
        for p in procs:
            p.kill()
