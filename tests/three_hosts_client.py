"""The clients' host of ``test_three_hosts.py``, run inside its network namespace.

``python tests/three_hosts_client.py SPEC`` with ``SPEC`` a JSON object: ``connect`` (the
routers this host's clients reach, in order), ``config`` (a zenoh configuration file),
``blimps``, ``kill_router`` (the PID of this host's
router, killed first), ``kill_host`` (the PIDs of the other service host's router and
service) and ``host_link`` (``[namespace, interface]`` taken down with it). Prints one
JSON line: owners before, the most time one round of steps took after each fault, the
steps answered, and every service's view of the sessions at the end.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import zenoh

from estimator_service.service import keys
from estimator_service.service.client import EstimatorClient, list_sessions, open_session

ALL, NONE = zenoh.QueryTarget.ALL, zenoh.ConsolidationMode.NONE  # every service's reply
STD = np.repeat([0.05, 0.035, 0.05, 0.035], 3)
DT = 0.25


def wait_for_fleet(session, n: int, within: float = 30.0) -> None:
    deadline = time.time() + within
    while time.time() < deadline:
        views = list_sessions(session)
        if len(views) == n and all(len(v["fleet"]) == n for v in views):
            return
        time.sleep(0.2)
    raise SystemExit(f"no fleet of {n}: {list_sessions(session)}")


def round_of_steps(clients, k: int) -> dict:
    """Step every blimp once: who served each (or the error), the slowest step (s), the
    steps answered and each blimp's step time (s)."""
    served, took, answered = {}, {}, 0
    for c in clients:
        t0 = time.monotonic()
        try:
            served[c.blimp] = c.step(np.zeros(3), [], DT * (k + 1))["service"]
            answered += 1
        except Exception as exc:
            served[c.blimp] = f"error after {time.monotonic() - t0:.2f} s: {exc}"
        took[c.blimp] = round(time.monotonic() - t0, 3)
    return {"slowest_s": max(took.values()), "answered": answered, "served": served, "took": took}


def main(spec: dict) -> dict:
    session = open_session(spec["connect"], config_file=spec["config"])
    wait_for_fleet(session, 2)
    clients = [
        EstimatorClient(session, f"far{i}", failover=True, attempt_timeout=0.5, failover_s=10.0)
        for i in range(spec["blimps"])
    ]
    owners = {c.blimp: c.reset(np.zeros(12), STD, t=0.0)["service"] for c in clients}
    out = {"owners": owners, "rounds": []}
    out["rounds"].append({"fault": "none", **round_of_steps(clients, 0)})
    os.kill(spec["kill_router"], signal.SIGKILL)  # this host's router: the clients keep the other
    out["rounds"].append({"fault": "router", **round_of_steps(clients, 1)})
    ns, link = spec["host_link"]
    subprocess.run(["ip", "-n", ns, "link", "set", link, "down"], check=True)  # the host drops off
    for pid in spec["kill_host"]:
        os.kill(pid, signal.SIGKILL)
    t0 = time.monotonic()
    out["rounds"].append({"fault": "host", **round_of_steps(clients, 2), "round_s": time.monotonic() - t0})
    out["rounds"].append({"fault": "after", **round_of_steps(clients, 3)})
    out["resyncs"] = {c.blimp: c.resyncs for c in clients}
    out["views"] = list_sessions(session)
    out["answers"] = {
        c.blimp: len(list(session.get(keys.blimp_key(c.blimp, "status"), target=ALL, consolidation=NONE,
                                      timeout=2.0)))
        for c in clients
    }  # fmt: skip
    session.close()
    return out


if __name__ == "__main__":
    print(json.dumps(main(json.loads(sys.argv[1]))), flush=True)
