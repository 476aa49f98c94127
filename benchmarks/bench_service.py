"""Estimator service over zenoh loopback: lock-step round trips and capacity.

Paper-sized synthetic models (prediction GP n = 900, 15 inputs, 12 outputs; observation
GP n = 900, 12 inputs, 10 outputs; sparse variants with m = 50) are written to a temporary
model folder; ``gpbf serve`` runs as a separate process.

1. Lock-step round trip p50/p99 for GP-EKF and GP-UKF vs the in-process filter step in the
   same run; overhead = p50 difference (target <= 0.5 ms). Also: round trip minus the
   service's own step time (``transport_p50_ms``) and, as the floor, a bare zenoh
   queryable in another process with the same worker hand-off spinning for the same time
   (``zenoh_floor_p50_ms``, see ``zenoh_echo.py``), and the same with the echo's work
   reading as many MB as the exact GP's factors (``zenoh_floor_streaming_p50_ms``). The same
   round trip with the sparse models (``sparse_overhead_p50_ms``) shows what the exact GP's
   cache footprint adds. A timestamped service (``service_trace.py``) splits the GP-EKF
   round trip into legs: zenoh's two (client to callback, reply to client:
   ``zenoh_legs_p50_ms``) and the service's own code around the step (queue hand-off to a
   worker, dispatch, handing the reply to zenoh: ``service_code_p50_ms``).
2. Blimps at 4 Hz: N clients each send one GP-EKF step every 250 ms (asynchronous
   queries, staggered); the largest N whose p99 latency stays under 50 ms (target >= 200),
   for the sparse GP (``blimps_at_4hz``) and the exact GP, and for the sparse GP served by
   a fleet of two processes on this machine (``fleet_blimps_at_4hz``).
3. ``overhead_over_zenoh_floor``: the GP-EKF lock-step overhead over the bare zenoh echo
   measured in the same run. ``service_cpu_per_step_over_echo`` (target <= 2): the CPU
   time, all threads, the service process spends per step message with 50 sparse-GP blimps
   at 4 Hz (``service_cpu_per_step_ms``; its filter step alone in-process:
   ``sparse_inprocess_step_ms``), over what the bare zenoh echo's process spends per message
   under the same load (``echo_cpu_per_step_ms``).
4. A hostile peer (``service_attacks.py``): forged fleet tokens (``forged_token_sessions_lost``,
   ``forged_token_resets_ok``), a hung owner (``hung_owner_failover_s``,
   ``stale_owner_overrides``), near-horizon frame chains against EKF and PF blimps
   (``near_horizon_healthy_p99_ms``) and the per-blimp queue bound (``queue_bytes_max_mb``).

The last output line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).parent))
import bench_filters as bf
import service_attacks
import service_tools
from machine import limits
from service_tools import (
    WARM_UP,
    cpu_seconds,
    echo_floor,
    echo_session,
    factor_mb,
    fleet_session,
    lockstep,
    phases,
    service_session,
    step_inputs,
)

from estimator_service.blimp import blimp_system, save_parametric
from estimator_service.factory import build_filter
from estimator_service.filters import GaussianBelief
from estimator_service.gp import save_gp
from estimator_service.models.blimp import DEFAULT_PARAMS, BlimpODE
from estimator_service.models.camera import CameraModel, PinholeCalibration
from estimator_service.service import keys
from estimator_service.service.client import EstimatorClient
from estimator_service.service.protocol import PROTOCOL_VERSION, encode
from estimator_service.store import seal


def write_models(folder: Path) -> None:
    exact, sparse, *_ = bf.build(np.random.default_rng(0))
    for kind, (p, o) in (("gp", exact), ("sparse", sparse)):
        save_gp(p, folder / f"prediction_{kind}.npz")
        save_gp(o, folder / f"observation_{kind}.npz")
    cams = tuple(
        PinholeCalibration(np.array([0.0, 0.0, 3.9]), np.eye(3), 380.0, (319.5, 239.5)) for _ in range(2)
    )
    save_parametric(
        BlimpODE(DEFAULT_PARAMS, np.ones(12)),
        CameraModel(cams, np.array([0.85, 0.32]), np.ones(10)),
        folder / "parametric.npz",
    )
    seal(folder, blimp_system(2))


def round_trips(
    client, models: Path, filt: str, n: int, model: str = "gp"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Round trips, in-process steps and the service's own step times (ms), ``n`` each.

    The round trips run first and the in-process steps after them, on the same inputs: run
    in between, each in-process step would leave this process's BLAS threads spinning and
    its data in the caches while the next round trip is served on the same two cores. The
    first ``WARM_UP`` of each are not counted.
    """
    rng = np.random.default_rng(1)
    inputs = step_inputs(rng, n + WARM_UP)
    mean = rng.normal(size=12) * 0.5
    times, served = lockstep(client, f"rtt-{filt}-{model}", filt, model, mean, inputs)
    rtt, loc = times[:, 1] - times[:, 0], []
    local = build_filter(filt, model, models)
    belief = GaussianBelief(mean, np.eye(12) * 0.01)
    for u, z in inputs:
        t0 = time.perf_counter()
        belief, _ = local.step(belief, u, z, np.ones(10, bool))
        loc.append(time.perf_counter() - t0)
    return tuple(np.array(x[WARM_UP:]) * 1e3 for x in (rtt, loc, served))


ALL = zenoh.QueryTarget.ALL  # a fleet's services all see the query; the owner answers
LATE_S = 0.05  # a load generator that ends further than this behind its schedule did not keep 4 Hz


def load(session, keys_: list[str], payload, seconds: float) -> tuple[float, float]:
    """Send one query per key every 250 ms (staggered over the period) for ``seconds``:
    the p99 latency (ms; inf if a reply is missing or the sender fell behind its schedule)
    and the sender's lag at the end (s). ``payload(tick)`` gives each tick's bytes."""
    lat: list[float] = []
    lock, pending = threading.Lock(), threading.Semaphore(0)
    period, ticks, n = 0.25, int(seconds / 0.25), len(keys_)
    start, sent = time.perf_counter(), 0
    for tick in range(ticks):
        body = payload(tick)
        for i, key in enumerate(keys_):
            due = start + tick * period + i * period / n
            while (now := time.perf_counter()) < due:
                time.sleep(min(due - now, 0.002))
            t0 = time.perf_counter()

            def done(reply, t0=t0) -> None:
                with lock:
                    lat.append(time.perf_counter() - t0)
                pending.release()

            session.get(key, done, payload=body, timeout=10.0, target=ALL)
            sent += 1
    lag = time.perf_counter() - (start + ticks * period)
    for _ in range(sent):
        pending.acquire(timeout=15)
    ok = len(lat) == sent and lag < LATE_S  # on schedule, the last send is due period / n before the end
    return (float(np.percentile(np.array(lat) * 1e3, 99)) if ok else float("inf")), lag


def _step_payload(tick: int) -> bytes:
    """One blimp's step message at ``tick`` (a control and one camera's ellipse)."""
    return encode({
        "v": PROTOCOL_VERSION, "seq": tick + 1, "t": 0.25 * (tick + 1), "u": [0.1, 0.0, 0.0],
        "frames": [[0, [300.0, 200.0, 60.0, 30.0, 0.1]]],
    })  # fmt: skip


def capacity_run(
    session, n_blimps: int, seconds: float, tag: str, pid: int | None = None
) -> tuple[float, float, float]:
    """p99 latency (ms) and sender lag (s) of ``n_blimps`` each stepping at 4 Hz, and with
    ``pid`` the CPU milliseconds that process spent per step message (NaN without)."""
    rng = np.random.default_rng(2)
    clients = [EstimatorClient(session, f"{tag}-{n_blimps}-{i}") for i in range(n_blimps)]
    for c in clients:
        c.reset(rng.normal(size=12) * 0.5, np.full(12, 0.1), t=0.0)
    run = lambda: load(session, [keys.blimp_key(c.blimp, "step") for c in clients], _step_payload, seconds)  # noqa: E731
    (p99, lag), cpu_ms = _cpu_per_message(pid, n_blimps, seconds, run)
    for c in clients:
        c.close()
    return p99, lag, cpu_ms


def _cpu_per_message(pid: int | None, n_blimps: int, seconds: float, run):
    """``run()``'s result and the CPU milliseconds process ``pid`` spent meanwhile per message
    of ``n_blimps`` at 4 Hz for ``seconds`` (NaN without ``pid``)."""
    if pid is None:
        return run(), math.nan
    cpu0 = cpu_seconds(pid)
    out = run()
    return out, (cpu_seconds(pid) - cpu0) / (n_blimps * int(seconds / 0.25)) * 1e3


def cpu_per_step(models: Path, model: str, n_blimps: int, seconds: float) -> tuple[float, float, float]:
    """CPU milliseconds per step message, all threads of the receiving process, with
    ``n_blimps`` at 4 Hz: ``gpbf serve`` stepping ``model`` GP-EKF blimps, and the bare zenoh
    echo (``zenoh_echo.py``, no work) receiving the same messages, each after one uncounted
    second of the same load; and the service's p99 latency meanwhile (ms; inf: it fell behind)."""
    pids: list[int] = []
    with service_session(models, model, pids=pids) as session:
        capacity_run(session, n_blimps, 1.0, "cpu-warm")
        p99, _, served = capacity_run(session, n_blimps, seconds, "cpu", pid=pids[-1])
    with echo_session(0.0, pids=pids) as session:
        echo_keys = [f"echo/cpu{i}" for i in range(n_blimps)]
        load(session, echo_keys, _step_payload, 1.0)
        run = lambda: load(session, echo_keys, _step_payload, seconds)  # noqa: E731
        echoed = _cpu_per_message(pids[-1], n_blimps, seconds, run)[1]
    return served, echoed, p99


def ladder(run, levels: list[int], label: str) -> int:
    """The largest level whose p99 stays under 50 ms (levels tried in order until one fails)."""
    best = 0
    for n in levels:
        p99, lag = run(n)
        behind = f" (sender {lag * 1e3:.0f} ms behind its schedule)" if lag > LATE_S else ""
        print(f"  {label}, {n:4d} blimps at 4 Hz: p99 {p99:8.2f} ms{behind}")
        if p99 >= 50.0:
            break
        best = n
    return best


def capacity(models: Path, model: str, levels: list[int], seconds: float, fleet: int = 1) -> int:
    """The largest number of blimps at 4 Hz with p99 < 50 ms, served by one process or by a
    fleet of ``fleet`` processes."""
    opened = service_session(models, model) if fleet == 1 else fleet_session(models, model, fleet)
    where = "one process" if fleet == 1 else f"{fleet} processes"
    with opened as session:
        return ladder(lambda n: capacity_run(session, n, seconds, f"{model}-x{fleet}")[:2], levels,
                      f"{model:6s} GP-EKF, {where}")  # fmt: skip


def echo_capacity(levels: list[int], seconds: float) -> int:
    """The same load generator against a bare zenoh queryable that does no work: how many
    blimps at 4 Hz this machine's zenoh and Python allow at all (the sender shares the cores)."""
    with echo_session(0.0) as session:
        run = lambda n: load(session, [f"echo/b{i}" for i in range(n)], lambda _: b"y" * 150, seconds)  # noqa: E731
        return ladder(run, levels, "bare zenoh echo, no work")


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="short run (under a minute)")
    parser.add_argument("--smoke", action="store_true", help="tiny run that only checks it works (tests)")
    parser.add_argument(
        "--serve-arg", action="append", default=[], help="extra gpbf serve option (repeatable)"
    )
    args = parser.parse_args(argv)
    service_tools.SERVE_ARGS[:] = args.serve_arg
    n_rtt, seconds = (30, 1.0) if args.smoke else (60, 2.0) if args.quick else (400, 6.0)
    levels = [25] if args.smoke else [25, 50, 200] if args.quick else [25, 50, 100, 150, 200, 250, 300, 400]
    with tempfile.TemporaryDirectory() as tmp:
        models = Path(tmp)
        write_models(models)
        res: dict[str, float] = {}
        with service_session(models, "gp") as session:
            for filt in ("ekf", "ukf"):
                rtt, loc, served = round_trips(session, models, filt, n_rtt)
                res[f"{filt}_service_step_p50_ms"] = np.median(served)
                res[f"{filt}_transport_p50_ms"] = np.median(rtt - served)
                res[f"{filt}_rtt_p50_ms"], res[f"{filt}_rtt_p99_ms"] = np.median(rtt), np.percentile(rtt, 99)
                res[f"{filt}_inprocess_p50_ms"] = np.median(loc)
                res[f"{filt}_overhead_p50_ms"] = np.median(rtt) - np.median(loc)
                print(f"GP-{filt.upper()}: round trip p50 {res[f'{filt}_rtt_p50_ms']:.3f} ms, "
                      f"p99 {res[f'{filt}_rtt_p99_ms']:.3f} ms;")  # fmt: skip
                print(f"  in-process p50 {res[f'{filt}_inprocess_p50_ms']:.3f} ms; "
                      f"overhead {res[f'{filt}_overhead_p50_ms']:.3f} ms")  # fmt: skip
                step_ms = float(res[f"{filt}_service_step_p50_ms"])
                floor = echo_floor(step_ms, n_rtt)
                res[f"{filt}_zenoh_floor_ms"] = floor
                print(f"  bare zenoh query, same hand-off and work: {floor:.3f} ms over the work")
                if filt == "ekf":
                    mb = factor_mb(models)
                    cold = echo_floor(step_ms, n_rtt, mb)
                    res["zenoh_floor_streaming_ms"] = cold
                    print(f"  ... with the work reading {mb:.0f} MB as the GP step does: {cold:.3f} ms")
                print(
                    f"  service-side step p50 {step_ms:.3f} ms; round trip minus it (zenoh, queue, "
                    f"encoding) p50 {res[f'{filt}_transport_p50_ms']:.3f} ms"
                )
            # the same path with the small sparse models: how much of the overhead is the exact
            # GP's 68 MB of Cholesky factors evicting the transport's code and data from the caches
            rtt, loc, served = round_trips(session, models, "ekf", n_rtt, model="sparse")
            res["sparse_overhead_p50_ms"] = np.median(rtt) - np.median(loc)
            res["sparse_inprocess_p50_ms"] = np.median(loc)
            res["sparse_transport_p50_ms"] = np.median(rtt - served)
            print(
                f"sparse GP-EKF: round trip p50 {np.median(rtt):.3f} ms, in-process {np.median(loc):.3f} ms; "
                f"overhead {res['sparse_overhead_p50_ms']:.3f} ms"
            )
        legs = phases(models, n_rtt)
        print("GP-EKF round trip by leg (p50 ms): " + ", ".join(f"{k} {v:.3f}" for k, v in legs.items()))
        cpu_blimps = levels[min(1, len(levels) - 1)]  # 50 blimps (25 in the smoke run): both keep up
        service_cpu, echo_cpu, cpu_p99 = cpu_per_step(models, "sparse", cpu_blimps, seconds)
        print(f"CPU per step message, {cpu_blimps} blimps at 4 Hz: service (sparse GP-EKF) {service_cpu:.3f} "
              f"ms (p99 latency {cpu_p99:.2f} ms), bare zenoh echo {echo_cpu:.3f} ms")  # fmt: skip
        best_echo = echo_capacity(levels, seconds)
        best_sparse = capacity(models, "sparse", levels, seconds)
        best_exact = capacity(models, "gp", [n for n in levels if n <= 100], seconds)
        best_fleet = capacity(models, "sparse", levels, seconds, fleet=2)
        attacks = {
            **service_attacks.forged_tokens(models),
            **service_attacks.frozen_owner(models),
            **service_attacks.near_horizon(models, steps=60 if args.smoke else 240),
            "queue_bytes_max_mb": service_attacks.queue_bytes_max_mb(models),
        }
        print("hostile peer:", attacks)
    out = {
        "rtt_p50_ms": round(res["ekf_rtt_p50_ms"], 3),
        "rtt_p99_ms": round(res["ekf_rtt_p99_ms"], 3),
        "overhead_p50_ms": round(res["ekf_overhead_p50_ms"], 3),
        "ukf_rtt_p50_ms": round(res["ukf_rtt_p50_ms"], 3),
        "ukf_rtt_p99_ms": round(res["ukf_rtt_p99_ms"], 3),
        "ukf_overhead_p50_ms": round(res["ukf_overhead_p50_ms"], 3),
        "transport_p50_ms": round(res["ekf_transport_p50_ms"], 3),
        "zenoh_floor_p50_ms": round(res["ekf_zenoh_floor_ms"], 3),
        "zenoh_floor_streaming_p50_ms": round(res["zenoh_floor_streaming_ms"], 3),
        "zenoh_legs_p50_ms": round(legs["zenoh"], 3),
        "service_code_p50_ms": round(legs["service_code"], 3),
        "sparse_overhead_p50_ms": round(res["sparse_overhead_p50_ms"], 3),
        "sparse_transport_p50_ms": round(res["sparse_transport_p50_ms"], 3),
        "blimps_at_4hz": best_sparse,
        "blimps_at_4hz_model": "sparse",
        "blimps_at_4hz_exact_gp": best_exact,
        "fleet_blimps_at_4hz": best_fleet,
        "fleet_processes": 2,
        "echo_blimps_at_4hz": best_echo,
        "blimps_over_echo": round(best_sparse / best_echo, 3) if best_echo else None,
        "overhead_over_zenoh_floor": round(res["ekf_overhead_p50_ms"] / res["ekf_zenoh_floor_ms"], 3),
        "cpu_blimps_at_4hz": cpu_blimps,
        "cpu_service_p99_ms": round(cpu_p99, 3),
        "service_cpu_per_step_ms": round(service_cpu, 4),
        "echo_cpu_per_step_ms": round(echo_cpu, 4),
        "sparse_inprocess_step_ms": round(res["sparse_inprocess_p50_ms"], 4),
        "service_cpu_per_step_over_echo": round(service_cpu / echo_cpu, 3) if echo_cpu > 0 else None,
        **attacks,
    }
    out.update(limits())  # this machine's dgemm rate and read bandwidth, for the ratios
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
