"""A fleet across three hosts: network namespaces made by the test (root only), a zenoh
router on each, estimator services on two, the robots' clients on the third. The clients'
own router is killed, then a whole service host (its link taken down, its router and
service killed): every blimp keeps being served, each by exactly one service.

Hosts ``a`` and ``b`` run a router and a service each, host ``c`` a router and the
clients; the routers connect to each other, the services (in zenoh's client mode) to their
own host's router, the clients to theirs and, when it is lost, another (what
``docs/deployment.md`` recommends), over a bridge 10.77.x.0/24.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from agents.sim import collect_flight
from estimator_service.service.client import spawn_service
from estimator_service.training import TrainSettings, train_models

ROOT = Path(__file__).resolve().parent.parent
HOSTS = ("a", "b", "c")
PORT = 7447
BLIMPS = 12


CLIENT_MODE = '{ mode: "client" }'  # one router at a time, the next listed when it is lost


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=10)


def _namespaces_unavailable() -> str | None:
    """Why namespaces cannot be made here, or None."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("ip") is None:
        return "the 'ip' tool (iproute2) is missing"
    probe = f"gpbfprobe{os.getpid()}"
    try:
        _ip("netns", "add", probe)
    except subprocess.CalledProcessError as exc:
        return f"'ip netns add' failed: {exc.stderr.decode().strip()}"
    try:
        _ip("-n", probe, "link", "add", "x0", "type", "veth", "peer", "name", "x1")
        _ip("-n", probe, "link", "add", "br0", "type", "bridge")
    except subprocess.CalledProcessError as exc:
        return f"no veth pairs or bridges in a namespace: {exc.stderr.decode().strip()}"
    finally:
        _ip("netns", "del", probe)
    return None


@contextlib.contextmanager
def _lan(tag: str):
    """Three namespaces on a bridge (itself in a fourth): ``{host: (namespace, address,
    interface)}``; all deleted on exit."""
    net = 10 + os.getpid() % 200
    names = {h: f"gpbf{tag}{h}" for h in HOSTS}
    switch = f"gpbf{tag}sw"
    made = []
    try:
        for ns in (*names.values(), switch):
            _ip("netns", "add", ns)
            made.append(ns)
        _ip("-n", switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", switch, "link", "set", "br0", "up")
        hosts = {}
        for i, h in enumerate(HOSTS, start=1):
            ns, dev, peer = names[h], f"v{tag}{h}", f"p{tag}{h}"
            _ip("link", "add", dev, "type", "veth", "peer", "name", peer)
            _ip("link", "set", dev, "netns", ns)
            _ip("link", "set", peer, "netns", switch)
            _ip("-n", switch, "link", "set", peer, "master", "br0")
            _ip("-n", switch, "link", "set", peer, "up")
            _ip("-n", ns, "addr", "add", f"10.77.{net}.{i}/24", "dev", dev)
            _ip("-n", ns, "link", "set", dev, "up")
            _ip("-n", ns, "link", "set", "lo", "up")
            hosts[h] = (ns, f"10.77.{net}.{i}", dev)
        yield hosts
    finally:
        for ns in made:
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)


def _in(ns: str) -> list[str]:
    return ["ip", "netns", "exec", ns]


def _router(ns: str, address: str, others: list[str], procs: list[subprocess.Popen]) -> subprocess.Popen:
    """``gpbf router`` in ``ns`` listening on ``address``, connected to the ``others``; added
    to ``procs`` before it is waited for."""
    connect = [a for o in others for a in ("--connect", f"tcp/{o}:{PORT}")]
    proc = subprocess.Popen(
        [*_in(ns), sys.executable, "-m", "estimator_service", "router", "--listen", f"tcp/{address}:{PORT}",
         *connect],
        stdout=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    procs.append(proc)
    assert proc.stdout is not None and "mode router" in proc.stdout.readline()
    return proc


@pytest.fixture(scope="module")
def lan_ok() -> None:
    """Skips, with the reason, where the test cannot make its namespaces."""
    why = _namespaces_unavailable()
    if why is not None:
        pytest.skip(why)


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("three_host_models")
    s = TrainSettings(n_points=50, n_pseudo=8, restarts=1, max_iter=8, calibration_seconds=0)
    train_models([collect_flight(30, seed=9)], out, kinds=["gp"], settings=s)
    return out


def test_a_fleet_on_three_hosts_survives_a_router_and_a_whole_host(lan_ok, models, tmp_path: Path) -> None:
    procs: list[subprocess.Popen] = []
    with _lan(str(os.getpid() % 10000)) as hosts:
        try:
            addr = {h: hosts[h][1] for h in HOSTS}
            routers = {}
            for h in HOSTS:  # each kept as soon as it runs: killed below whatever fails next
                routers[h] = _router(hosts[h][0], addr[h], [addr[o] for o in HOSTS if o != h], procs)
            services = {}
            client_cfg = tmp_path / "client.json5"
            client_cfg.write_text(CLIENT_MODE)
            for h in ("a", "b"):
                proc, ready = spawn_service(
                    models, 7450, "--connect", f"tcp/{addr[h]}:{PORT}", "--zenoh-config", str(client_cfg),
                    command=(*_in(hosts[h][0]), sys.executable, "-m", "estimator_service"), cwd=ROOT,
                )  # fmt: skip
                procs.append(proc)
                services[h] = (proc, ready.split("service ")[1].split(",")[0])
            spec = {
                "connect": [f"tcp/{addr['c']}:{PORT}", f"tcp/{addr['b']}:{PORT}"], "config": str(client_cfg),
                "blimps": BLIMPS,
                "kill_router": routers["c"].pid, "kill_host": [routers["a"].pid, services["a"][0].pid],
                "host_link": [hosts["a"][0], hosts["a"][2]],
            }  # fmt: skip
            out = subprocess.run(
                [*_in(hosts["c"][0]), sys.executable, str(ROOT / "tests" / "three_hosts_client.py"),
                 json.dumps(spec)],
                capture_output=True, text=True, timeout=180, cwd=ROOT,
            )  # fmt: skip
            assert out.returncode == 0, out.stdout + out.stderr
            result = json.loads(out.stdout.strip().splitlines()[-1])
        finally:
            for p in procs:
                p.kill()
                p.wait(timeout=10)
    a_id, b_id = services["a"][1], services["b"][1]
    owners = result["owners"]
    assert set(owners.values()) == {a_id, b_id}, owners  # the blimps are spread over both hosts
    rounds = {r["fault"]: r for r in result["rounds"]}
    summary = {f: (r["answered"], round(r["slowest_s"], 3)) for f, r in rounds.items()}
    # no blimp lost: every one answered before the faults, after the router's loss and afterwards
    assert all(rounds[f]["answered"] == BLIMPS for f in ("none", "router", "after")), summary
    assert rounds["router"]["slowest_s"] < 3.0, summary
    # the machine's loss: measured 2.0 s; about 1 run in 16 one blimp's step stalls for the client's
    # whole 10 s of retries (cause not found, docs/deployment.md): then it is answered at the end
    # of them or fails by time-out, never refused, and the next round serves it
    host = rounds["host"]
    stalled = {b: t for b, t in host["took"].items() if t >= 5.0}
    assert len(stalled) <= 1 and all(9.5 <= t < 12.0 for t in stalled.values()), (host["took"], summary)
    failed = [s for s in host["served"].values() if s.startswith("error")]
    assert all(float(s.split()[2]) >= 9.5 for s in failed) and len(failed) <= len(stalled), host["served"]
    assert rounds["none"]["served"] == owners and rounds["router"]["served"] == owners
    assert set(rounds["after"]["served"].values()) == {b_id}  # host a's blimps moved to b
    moved = {b for b, s in owners.items() if s == a_id}
    assert {b for b, n in result["resyncs"].items() if n} == moved
    [view] = result["views"]  # one service left, holding every blimp once
    assert view["service"] == b_id and sorted(s["blimp"] for s in view["sessions"]) == sorted(owners)
    assert set(result["answers"].values()) == {1}, result["answers"]  # no double owner
    print(json.dumps({f: round(r["slowest_s"], 3) for f, r in rounds.items()}))
