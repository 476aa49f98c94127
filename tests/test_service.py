"""The estimator service as a real separate process, over zenoh on loopback."""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh

from agents.sim import collect_flight
from estimator_service.factory import build_filter
from estimator_service.filters import GaussianBelief, step_many
from estimator_service.service.client import EstimatorClient, ServiceError, free_port, open_session, services
from estimator_service.service.limits import Limits, gate_for
from estimator_service.service.protocol import PROTOCOL_VERSION, decode_belief
from estimator_service.training import TrainSettings, train_models

V = PROTOCOL_VERSION
STD = np.repeat([0.05, 0.035, 0.05, 0.035], 3)


class Service:
    def __init__(self, models: Path, port: int) -> None:
        self.port = port
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "estimator_service",
                "--models",
                str(models),
                "--filter",
                "ekf",
                "--model",
                "gp",
                "--particles",
                "300",
                "--listen",
                f"tcp/127.0.0.1:{port}",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        line = self.proc.stdout.readline()
        assert "ready" in line, line

    def stop(self, kill: bool = False) -> int:
        (self.proc.kill if kill else self.proc.terminate)()
        return self.proc.wait(timeout=20)


@pytest.fixture(scope="module")
def flight():
    return collect_flight(40, seed=11)


@pytest.fixture(scope="module")
def models(flight, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("svc_models")
    train_models(
        [flight],
        out,
        kinds=["param", "gp"],
        settings=TrainSettings(  # the tests track this flight's start: keep it in the training data
            n_points=60, n_pseudo=8, restarts=1, max_iter=10, hetero_iterations=1, calibration_seconds=0
        ),
    )
    return out


@pytest.fixture(scope="module")
def service(models):
    svc = Service(models, free_port())
    yield svc
    assert svc.stop() == 0


@pytest.fixture()
def client(service):
    session = open_session([f"tcp/127.0.0.1:{service.port}"])
    time.sleep(0.2)
    yield session
    session.close()


def frames_at(flight, k: int) -> list:
    return [[int(j), flight.z[k].reshape(-1, 5)[j].tolist()] for j in np.flatnonzero(flight.valid[k])]


def in_process(models: Path, flight, steps: int, filter_kind: str = "ekf", seed: int = 0):
    filt = build_filter(filter_kind, "gp", models, **({"n_particles": 300} if filter_kind == "pf" else {}))
    rng = np.random.default_rng(seed)
    b0 = GaussianBelief(flight.state[0], np.diag(STD * STD))
    belief = filt.initial(b0, rng)
    valid = flight.expand_valid()
    gate = gate_for(Limits().gate_p)
    out = []
    for k in range(steps):  # the step policy the service runs, with the service's gate
        [(belief, _)] = step_many(
            filt, [belief], flight.control[k][None], flight.z[k + 1][None], valid[k + 1][None], gate, rng
        )
        out.append(filt.gaussian(belief).mean)
    return np.array(out)


@pytest.mark.parametrize("filter_kind", ["ekf", "pf"])
def test_lock_step_equals_in_process_filter_bit_for_bit(client, models, flight, filter_kind: str) -> None:
    c = EstimatorClient(client, f"lock-{filter_kind}")
    c.reset(flight.state[0], STD, t=flight.t[0], filter=filter_kind, model="gp", seed=5)
    remote = np.array(
        [c.step(flight.control[k], frames_at(flight, k + 1), flight.t[k + 1])["mean"] for k in range(30)]
    )
    np.testing.assert_array_equal(remote, in_process(models, flight, 30, filter_kind, seed=5))


def test_concurrent_blimps_are_batched_and_equal_the_in_process_filter(client, models, flight) -> None:
    """16 blimps step at once: the service runs their EKF steps in batches (one GP call),
    and every belief still equals the one-at-a-time filter up to rounding."""
    clients = [EstimatorClient(client, f"crowd-{i}") for i in range(16)]
    for c in clients:
        c.reset(flight.state[0], STD, t=flight.t[0], filter="ekf", model="gp")
    last: dict[str, np.ndarray] = {}
    for k in range(10):
        done = threading.Semaphore(0)
        payload = msgpack.packb(
            {"v": PROTOCOL_VERSION, "seq": k + 1, "t": flight.t[k + 1], "u": flight.control[k].tolist(),
             "frames": frames_at(flight, k + 1)}
        )  # fmt: skip

        def got(reply, done=done) -> None:
            belief = decode_belief(reply.ok.payload.to_bytes())
            last[belief["blimp"]] = np.array(belief["mean"])
            done.release()

        for c in clients:
            client.get(f"gpbf/{c.blimp}/step", got, payload=payload, timeout=10.0)
        for _ in clients:
            assert done.acquire(timeout=10)
    expected = in_process(models, flight, 10)[-1]
    for c in clients:
        np.testing.assert_allclose(last[c.blimp], expected, rtol=1e-7, atol=1e-9)
    assert sum(c.status()["batched"] for c in clients) > 0
    for c in clients:
        c.close()


def test_two_blimps_do_not_interfere(client, models, flight) -> None:
    a, b = EstimatorClient(client, "twin-a"), EstimatorClient(client, "twin-b")
    other = collect_flight(10, seed=99)
    a.reset(flight.state[0], STD, t=0.0)
    b.reset(other.state[0], STD * 2, t=0.0)
    for k in range(15):
        ra = a.step(flight.control[k], frames_at(flight, k + 1), flight.t[k + 1])
        b.step(other.control[k % 30], frames_at(other, (k % 30) + 1), flight.t[k + 1])
    np.testing.assert_array_equal(ra["mean"], in_process(models, flight, 15)[-1])


def test_streaming_delivers_one_belief_per_frame_in_order(client, flight) -> None:
    c = EstimatorClient(client, "stream", stream=True)
    c.reset(flight.state[0], STD, t=flight.t[0])
    sent = []
    for k in range(40):
        c.publish_control(flight.control[k], flight.t[k])
        for j in np.flatnonzero(flight.valid[k + 1]):
            c.publish_camera(int(j), flight.z[k + 1].reshape(-1, 5)[j], flight.t[k + 1])
            sent.append(flight.t[k + 1])
    got = [c.next_belief(timeout=10) for _ in sent]
    assert [g["t"] for g in got] == sent
    assert [g["seq"] for g in got] == sorted(g["seq"] for g in got)
    assert np.linalg.norm(got[-1]["mean"][:3] - flight.state[40, :3]) < 0.5
    c.close()


BAD = {
    "undecodable": (b"\xc1\xc1not msgpack", "undecodable"),
    "version": (msgpack.packb({"v": 99, "seq": 1, "t": 99.0, "u": [0, 0, 0], "frames": []}), "version"),
    "missing": (msgpack.packb({"v": V, "seq": 1, "t": 99.0, "frames": []}), "missing field 'u'"),
    "shape": (msgpack.packb({"v": V, "seq": 1, "t": 99.0, "u": [0, 0], "frames": []}), "'u'"),
    "nan": (msgpack.packb({"v": V, "seq": 1, "t": 99.0, "u": [0, math.nan, 0], "frames": []}), "NaN"),
    "camera": (
        msgpack.packb({"v": V, "seq": 1, "t": 99.0, "u": [0, 0, 0], "frames": [[7, [1, 2, 3, 4, 0]]]}),
        "camera",
    ),
    "huge": (
        msgpack.packb({"v": V, "seq": 1, "t": 99.0, "u": [0, 0, 0], "frames": [], "pad": "x" * 70000}),
        "exceeds",
    ),
    "late": (msgpack.packb({"v": V, "seq": 1, "t": -5.0, "u": [0, 0, 0], "frames": []}), "session time"),
}


def test_every_bad_input_is_rejected_with_a_clear_error_and_changes_nothing(client, models, flight) -> None:
    c = EstimatorClient(client, "bad")
    c.reset(flight.state[0], STD, t=flight.t[0])
    first = c.step(flight.control[0], frames_at(flight, 1), flight.t[1])
    for payload, needle in BAD.values():
        with pytest.raises(ServiceError, match=needle):
            c.query("step", raw=payload)
        c.publish_raw("control", payload)
    errors = c.errors(wait=0.5)
    assert len(errors) >= 2 * len(BAD) - 1 and all("error" in e for e in errors)
    status = c.status()
    assert status["steps"] == 1
    second = c.step(flight.control[1], frames_at(flight, 2), flight.t[2])
    expected = in_process(models, flight, 2)
    np.testing.assert_array_equal(first["mean"], expected[0])
    np.testing.assert_array_equal(second["mean"], expected[1])


def test_session_survives_ten_thousand_garbage_messages(client, models, flight) -> None:
    c = EstimatorClient(client, "garbage")
    c.reset(flight.state[0], STD, t=flight.t[0])
    rng = np.random.default_rng(0)
    before = c.status()["rejected"]
    for i in range(10_000):
        c.publish_raw("camera/0" if i % 2 else "control", rng.bytes(int(rng.integers(1, 64))))
    deadline = time.time() + 60

    def handled() -> int:  # each rejected, or dropped unread at the queue cap (docs/protocol.md)
        status = c.status()
        return status["rejected"] + status["dropped"]

    while handled() < before + 10_000 and time.time() < deadline:
        time.sleep(0.2)
    assert handled() == before + 10_000
    step = c.step(flight.control[0], frames_at(flight, 1), flight.t[1])
    np.testing.assert_array_equal(step["mean"], in_process(models, flight, 1)[0])


def test_unknown_blimp_ids_get_an_error_reply(client) -> None:
    replies = list(client.get("gpbf/bad.id!/status", timeout=3))
    assert len(replies) == 1 and replies[0].ok is None
    assert b"invalid blimp id" in replies[0].err.payload.to_bytes()


def test_kill_and_restart_is_detected_through_liveliness(models, flight) -> None:
    port = free_port()
    svc = Service(models, port)
    session = open_session([f"tcp/127.0.0.1:{port}"])
    events: list[tuple[str, str]] = []
    seen = threading.Event()

    def on_token(sample: zenoh.Sample) -> None:
        events.append((str(sample.kind), str(sample.key_expr)))
        seen.set()

    sub = session.liveliness().declare_subscriber("gpbf/@service/*", on_token, history=True)
    time.sleep(0.5)
    (first,) = services(session)
    c = EstimatorClient(session, "phoenix")
    c.reset(flight.state[0], STD, t=0.0)
    svc.stop(kill=True)
    deadline = time.time() + 30
    while not any("DELETE" in k for k, _ in events) and time.time() < deadline:
        time.sleep(0.1)
    assert any("DELETE" in k and first in key for k, key in events)
    svc2 = Service(models, port)
    deadline = time.time() + 30
    ids = []
    while time.time() < deadline:
        ids = services(session, timeout=1.0)
        if ids and ids != [first]:
            break
        time.sleep(0.5)
    assert ids and first not in ids
    b = c.reset(flight.state[0], STD, t=0.0)  # the session is re-created on the new service
    np.testing.assert_array_equal(b["mean"], flight.state[0])
    assert c.status()["steps"] == 0
    sub.undeclare()
    session.close()
    assert svc2.stop() == 0


def test_packed_arrays_round_trip_bit_exactly_and_wrong_lengths_are_named() -> None:
    from estimator_service.service.protocol import ProtocolError, encode_belief, pack_array, parse_reset

    rng = np.random.default_rng(3)
    mean, a = rng.normal(size=12), rng.normal(size=(12, 12))
    cov = a @ a.T + np.eye(12)
    b = decode_belief(encode_belief("b1", 4, 1.0, mean, cov, "ekf", "gp", 2.5, 10, False, 1.0))
    assert np.array_equal(b["mean"], mean) and np.array_equal(b["cov"], cov)
    r = parse_reset({"v": V, "seq": 1, "t": 0.0, "mean": pack_array(mean), "cov": pack_array(cov)})
    assert np.array_equal(r.mean, mean) and np.array_equal(r.cov, cov)
    with pytest.raises(ProtocolError, match=r"field 'mean' must hold 12 little-endian float64 \(96 bytes\)"):
        parse_reset({"v": V, "seq": 1, "t": 0.0, "mean": pack_array(mean[:11]), "std": [1.0] * 12})
    with pytest.raises(ProtocolError, match="field 'mean' contains NaN"):
        parse_reset({"v": V, "seq": 1, "t": 0.0, "mean": pack_array(np.full(12, np.nan)), "std": [1.0] * 12})


def test_warm_up_computes_the_model_caches_before_any_blimp_steps(models, monkeypatch) -> None:
    """The service warms every filter it builds: the exact GPs' inverse factors (about a
    second at paper size) are computed then, not in some blimp's first step."""
    import estimator_service.gp.exact as exact
    from estimator_service.factory import build_filter, warm_up
    from estimator_service.store import read_system

    calls = []
    real = exact.inverse_factor
    monkeypatch.setattr(exact, "inverse_factor", lambda *a, **k: calls.append(1) or real(*a, **k))
    filt = build_filter("ekf", "gp", models)
    assert not calls
    warm_up(filt, read_system(models))
    assert calls
    done = len(calls)
    belief = GaussianBelief(np.zeros(12), np.eye(12) * 0.01)
    filt.step(belief, np.zeros(3), np.zeros(10), np.ones(10, bool))  # a blimp's first step
    assert len(calls) == done
