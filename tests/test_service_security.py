"""docs/examples/secure: user/password authentication and an ACL that lets only the named
pilot reset and step any blimp and each tenant only its own, tested both ways against a
real service."""

from __future__ import annotations

import contextlib
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agents.sim import collect_flight
from estimator_service.service import keys
from estimator_service.service.client import (
    EstimatorClient,
    NoReply,
    ServiceError,
    free_port,
    list_sessions,
    open_session,
    services,
    spawn_service,
)
from estimator_service.service.protocol import PROTOCOL_VERSION, encode
from estimator_service.training import TrainSettings, train_models

ROOT = Path(__file__).resolve().parents[1]
STD = np.full(12, 0.1)
USERS = ("pilot", "viewer", "alice", "bob")  # the example's clients


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("secure_models")
    s = TrainSettings(
        n_points=40, n_pseudo=8, restarts=1, max_iter=5, hetero_iterations=1, calibration_seconds=0
    )
    train_models([collect_flight(20, seed=3)], out, kinds=["param"], settings=s)
    return out


def _client(endpoint: list[str], config: Path | None, blimp: str):
    session = open_session(endpoint, config_file=config)
    time.sleep(0.3)
    return session, EstimatorClient(session, blimp, timeout=1.5)


@contextlib.contextmanager
def _secure_service(models: Path, folder: Path, *options: str):
    """The secure example's files copied into ``folder`` and a service run from there with
    ``service.json5`` and ``options``: ``(endpoint, ready line, sessions to close)``; the
    sessions appended to the list are closed and the service stopped on leaving."""
    for f in (ROOT / "docs" / "examples" / "secure").iterdir():
        shutil.copy(f, folder / f.name)
    port = free_port()
    proc, ready = spawn_service(
        models, port, "--model", "param", "--zenoh-config", "service.json5", *options, cwd=folder
    )
    opened: list = []
    try:
        yield [f"tcp/127.0.0.1:{port}"], ready, opened
    finally:
        for s in opened:
            s.close()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=20)


def _only_services_publish(owner: EstimatorClient, session, others: list, t: float) -> None:
    """``owner``'s subscriber on its blimp's keys receives the belief the service publishes
    for its step, and nothing that ``others`` (logged-in users' sessions) put on those keys."""
    got: list[bytes] = []

    def keep(sample) -> None:
        got.append(sample.payload.to_bytes())

    subs = [
        session.declare_subscriber(keys.blimp_key(owner.blimp, kind), keep) for kind in ("belief", "error")
    ]
    time.sleep(0.3)
    owner.step(np.zeros(3), [], t)
    deadline = time.monotonic() + 3.0
    while not got and time.monotonic() < deadline:
        time.sleep(0.05)
    assert got, "the service's belief did not arrive"
    for other in others:
        for kind in ("belief", "error"):
            other.put(keys.blimp_key(owner.blimp, kind), b"forged")
    time.sleep(0.5)
    assert b"forged" not in got
    for sub in subs:
        sub.undeclare()


def test_only_the_named_pilot_may_reset_and_step(models: Path, tmp_path: Path) -> None:
    with _secure_service(models, tmp_path) as (endpoint, ready, opened):
        assert f"listening on ['{endpoint[0]}']" in ready
        s, pilot = _client(endpoint, tmp_path / "pilot.json5", "guarded")
        opened.append(s)
        pilot.reset(np.zeros(12), STD)
        assert pilot.step(np.zeros(3), [], 0.25)["t"] == 0.25
        s, viewer = _client(endpoint, tmp_path / "viewer.json5", "guarded")
        opened.append(s)
        assert viewer.status()["steps"] == 1  # a logged-in viewer may read
        with pytest.raises(NoReply):
            viewer.reset(np.zeros(12), STD)
        with pytest.raises(NoReply):
            viewer.step(np.zeros(3), [], 0.5)
        s, anonymous = _client(endpoint, None, "guarded")
        assert not list(s.info.peers_zid()) and not list(s.info.routers_zid())  # not let in at all
        assert list(opened[0].info.peers_zid())  # (the pilot is connected to the service)
        opened.append(s)
        with pytest.raises(NoReply):
            anonymous.reset(np.zeros(12), STD)
        assert pilot.status()["steps"] == 1  # neither changed the pilot's blimp
        # a logged-in viewer posing as a service (its token and a correct hello answer) is refused
        s, _ = _client(endpoint, tmp_path / "viewer.json5", "unused")
        opened.append(s)
        fake = "viewer-as-service"
        hello = encode({"v": PROTOCOL_VERSION, "service": fake, "hello": True})
        answer = s.declare_queryable(keys.hello_key(fake), lambda q: q.reply(keys.hello_key(fake), hello))
        token = s.liveliness().declare_token(keys.liveliness_key(fake))
        time.sleep(1.0)
        assert pilot.step(np.zeros(3), [], 0.5)["t"] == 0.5  # still served: no new owner
        [view] = list_sessions(s)
        assert view["fleet"] == [view["service"]], view
        token.undeclare()
        answer.undeclare()


def test_a_tenant_drives_only_its_own_blimps_and_cannot_lock_others_out(models: Path, tmp_path: Path) -> None:
    """The example's tenants: "alice" may reset and step only ids ``alice.<name>`` (the ACL
    binds the tenant to the logged-in user), and however many resets she sends she holds at
    most ``--session-quota`` sessions, so "bob" and the operator still get theirs."""
    quota = ("--session-quota", "3", "--max-sessions", "7")
    with _secure_service(models, tmp_path, *quota) as (endpoint, _, opened):
        alice = open_session(endpoint, config_file=tmp_path / "alice.json5")
        bob = open_session(endpoint, config_file=tmp_path / "bob.json5")
        pilot = open_session(endpoint, config_file=tmp_path / "pilot.json5")
        opened += [alice, bob, pilot]
        time.sleep(0.3)
        refused = 0
        for k in range(8):  # a flood of new blimps: three sessions, then refusals naming the quota
            try:
                EstimatorClient(alice, f"alice.{k}", timeout=1.5).reset(np.zeros(12), STD)
            except ServiceError as err:
                assert "tenant 'alice' holds its quota of 3 sessions" in str(err)
                refused += 1
        assert refused == 5
        for k in range(3):
            assert EstimatorClient(bob, f"bob.{k}", timeout=1.5).reset(np.zeros(12), STD)["t"] == 0.0
        assert EstimatorClient(pilot, "guarded", timeout=1.5).reset(np.zeros(12), STD)["t"] == 0.0
        for other in ("bob.0", "bob.new", "guarded"):  # another tenant's ids, or the shared ones
            with pytest.raises(NoReply):
                EstimatorClient(alice, other, timeout=1.5).reset(np.zeros(12), STD)
        with pytest.raises(NoReply):
            EstimatorClient(alice, "bob.0", timeout=1.5).step(np.zeros(3), [], 0.25)
        assert EstimatorClient(alice, "alice.0", timeout=1.5).step(np.zeros(3), [], 0.25)["t"] == 0.25
        [view] = list_sessions(pilot)
        blimps = sorted(s["blimp"] for s in view["sessions"])
        assert blimps == ["alice.0", "alice.1", "alice.2", "bob.0", "bob.1", "bob.2", "guarded"]
        assert all(s["steps"] == 0 for s in view["sessions"] if s["blimp"] != "alice.0")
        bob_client = EstimatorClient(bob, "bob.0", timeout=1.5)
        _only_services_publish(bob_client, bob, [alice, pilot], 0.25)


def test_the_secure_example_holds_through_a_router(models: Path, tmp_path: Path) -> None:
    """The same ``service.json5`` on a router in between, the services in zenoh's client mode
    (``service-client.json5``) and the clients connected to the router only: the router
    checks each client's rights, so the pilot drives, a tenant
    drives only its own blimps, a viewer only reads and cannot join the fleet, and a client
    without credentials is not let in."""
    for f in (ROOT / "docs" / "examples" / "secure").iterdir():
        shutil.copy(f, tmp_path / f.name)
    port = free_port()
    router = subprocess.Popen(
        [sys.executable, "-m", "estimator_service", "router", "--listen", f"tcp/127.0.0.1:{port}",
         "--zenoh-config", "service.json5"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    endpoint, started, opened = [f"tcp/127.0.0.1:{port}"], [router], []
    try:
        assert "mode router" in router.stdout.readline()
        for _ in range(2):
            options = ("--model", "param", "--zenoh-config", "service-client.json5", "--connect", endpoint[0])
            proc, ready = spawn_service(models, free_port(), *options, cwd=tmp_path)
            assert "mode client" in ready
            started.append(proc)
        sessions = {u: open_session(endpoint, config_file=tmp_path / f"{u}.json5") for u in USERS}
        opened += sessions.values()
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            views = list_sessions(sessions["viewer"])
            if len(views) == 2 and all(len(v["fleet"]) == 2 for v in views):
                break
            time.sleep(0.5)
        assert len(views) == 2 and all(len(v["fleet"]) == 2 for v in views), views
        pilot = EstimatorClient(sessions["pilot"], "guarded", timeout=1.5)
        assert pilot.reset(np.zeros(12), STD)["t"] == 0.0 and pilot.step(np.zeros(3), [], 0.25)["t"] == 0.25
        alice = EstimatorClient(sessions["alice"], "alice.one", timeout=1.5)
        assert alice.reset(np.zeros(12), STD)["t"] == 0.0
        for user, blimp in (
            ("viewer", "guarded"),
            ("alice", "guarded"),
            ("alice", "bob.one"),
            ("bob", "alice.one"),
        ):
            with pytest.raises(NoReply):
                EstimatorClient(sessions[user], blimp, timeout=1.5).reset(np.zeros(12), STD)
        assert EstimatorClient(sessions["viewer"], "guarded", timeout=1.5).status()["steps"] == 1
        fake = "viewer-as-service"  # a viewer's token and hello answer do not join the fleet
        hello = encode({"v": PROTOCOL_VERSION, "service": fake, "hello": True})
        viewer = sessions["viewer"]
        answer = viewer.declare_queryable(
            keys.hello_key(fake), lambda q: q.reply(keys.hello_key(fake), hello)
        )
        token = viewer.liveliness().declare_token(keys.liveliness_key(fake))
        time.sleep(1.0)
        assert all(len(v["fleet"]) == 2 for v in list_sessions(sessions["pilot"]))
        assert fake not in services(sessions["pilot"])  # the router let its token through to no one
        token.undeclare()
        answer.undeclare()
        stranger = open_session(endpoint)  # no credentials: the router does not let it in
        opened.append(stranger)
        assert not list(stranger.info.routers_zid()) and not list(stranger.info.peers_zid())
        assert list(sessions["viewer"].info.routers_zid())  # (a logged-in client is connected)
        with pytest.raises(NoReply):
            EstimatorClient(stranger, "guarded", timeout=1.5).status()
        assert pilot.step(np.zeros(3), [], 0.5)["t"] == 0.5
        pilot.publish_control(np.zeros(3), 0.5)  # streamed inputs pass the router too: a camera
        pilot.publish_camera(0, [320.0, 240.0, 40.0, 20.0, 0.1], 0.75)  # frame steps the blimp
        deadline = time.monotonic() + 3.0
        while pilot.status()["steps"] < 3 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert pilot.status()["steps"] == 3 and pilot.status()["t"] == 0.75
        owner = EstimatorClient(sessions["alice"], "alice.one", timeout=1.5)
        _only_services_publish(owner, sessions["alice"], [sessions["viewer"], sessions["bob"]], 0.25)
    finally:
        for s in opened:
            s.close()
        for p in started:
            p.kill()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command for make-certs.sh")
def test_the_secure_example_holds_across_two_routers_joined_by_mutual_tls(
    models: Path, tmp_path: Path
) -> None:
    """Two routers, each running ``service.json5`` from its own folder with its certificate
    (``make-certs.sh``), joined over ``tls/``, a service behind each: the two services form
    one fleet (with user and password alone they never did: login is one way) and the pilot,
    connected to one router, drives blimps owned by either."""
    secure = ROOT / "docs" / "examples" / "secure"
    subprocess.run(["sh", str(secure / "make-certs.sh"), str(tmp_path / "certs"), "router-a", "router-b"],
                   check=True, timeout=60)  # fmt: skip
    tls, tcp = {n: free_port() for n in "ab"}, {n: free_port() for n in "ab"}
    started, opened = [], []
    try:
        for n in "ab":
            folder = tmp_path / n
            shutil.copytree(secure, folder)
            for f in ("ca.pem", "node.pem", "node.key"):
                shutil.copy(tmp_path / "certs" / f"router-{n}" / f, folder / f)
            join = ["--connect", f"tls/127.0.0.1:{tls['a']}"] if n == "b" else []
            router = subprocess.Popen(
                [sys.executable, "-m", "estimator_service", "router", "--listen", f"tls/127.0.0.1:{tls[n]}",
                 "--listen", f"tcp/127.0.0.1:{tcp[n]}", *join, "--zenoh-config", "service.json5"],
                cwd=folder, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            )  # fmt: skip
            started.append(router)
            assert "mode router" in router.stdout.readline()
            options = (
                "--model",
                "param",
                "--zenoh-config",
                "service-client.json5",
                "--connect",
                f"tcp/127.0.0.1:{tcp[n]}",
            )
            started.append(spawn_service(models, free_port(), *options, cwd=folder)[0])
        pilot = open_session([f"tcp/127.0.0.1:{tcp['a']}"], config_file=tmp_path / "a" / "pilot.json5")
        opened.append(pilot)
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline:
            views = list_sessions(pilot)
            if len(views) == 2 and all(len(v["fleet"]) == 2 for v in views):
                break
            time.sleep(0.5)
        assert len(views) == 2 and all(len(v["fleet"]) == 2 for v in views), views
        owners = set()
        for k in range(8):
            c = EstimatorClient(pilot, f"blimp{k}", timeout=3.0)
            owners.add(c.reset(np.zeros(12), STD)["service"])
            assert c.step(np.zeros(3), [], 0.25)["t"] == 0.25
        assert owners == {v["service"] for v in views}  # blimps on both routers' services
    finally:
        for s in opened:
            s.close()
        for p in started:
            p.kill()
