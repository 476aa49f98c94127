"""PPO training throughput on beliefs vs on the true state, in one run.

Models come from a short scripted flight (``--quick``: 3 minutes, 300 GP points; full:
10 minutes, 900 points, the paper's size). Throughput is environment steps per second of
``PPO.learn`` on one core: one env stepped through the single-env wrapper (in-process
GP-EKF for the belief variant; target belief >= 0.5x state), and 16 envs in the batched
belief env with the committed PPO hyperparameters (native batched simulator, one batched
GP-EKF step for all blimps; target ``batched_belief_to_state_ratio`` >= 0.8 with the exact
GP). Where the filter's time goes is set against the machine: ``variance_floor_ms`` is the
exact GPs' variance flops (``n^2`` per query and output, each GP with its own ``n``) at the
one-core dgemm rate, ``variance_read_floor_ms`` the inverse-factor blocks a batched step
reads (``variance_read_mb``) at the read bandwidth. The last output line is one JSON object.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time

from machine import dgemm_gflops, limits
from threadpoolctl import threadpool_limits

from agents.rl import AgentSpec, agent_env_id, make_vec
from agents.rl.hyperparams import load_hyperparams
from agents.sim import collect_flight
from estimator_service.gp import ExactGP
from estimator_service.training import TrainSettings, train_models

BATCHED_ENVS = 16
WARM_UP = 20  # env steps before the timed ones


def throughput(spec: AgentSpec, steps: int, n_envs: int = 1, smoke: bool = False) -> float:
    """Environment steps per second of ``PPO.learn`` on one core (one torch and BLAS thread,
    as the RL experiment trains each agent): one env through the single-env wrapper, or
    ``n_envs`` > 1 in the batched belief env with the committed ``hyperparams/ppo.yml``."""
    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(1)
    if n_envs > 1:
        kw = dict(load_hyperparams("ppo", agent_env_id(spec.task, spec.variant)).kwargs)
        if smoke:
            kw.update(n_steps=16, batch_size=32, n_epochs=1)
    else:
        kw = {"n_steps": 256, "batch_size": 64, "n_epochs": 4}
    with threadpool_limits(1):
        venv = make_vec(spec, n_envs, batched=n_envs > 1)
        agent = PPO("MlpPolicy", venv, seed=0, device="cpu", verbose=0, **kw)
        agent.learn(kw["n_steps"] * n_envs)  # warm-up (first rollout, torch initialisation)
        t0 = time.perf_counter()
        agent.learn(steps, reset_num_timesteps=False)
        rate = steps / (time.perf_counter() - t0)
        venv.close()
    return rate


def env_step_ms(variant: str, models: str, n_envs: int, steps: int) -> float:
    """Milliseconds per step of the batched env alone (random actions, one core): the part of
    PPO's step that the filter adds to, without the learner."""
    import numpy as np

    from agents.rl.batched import BeliefVecEnv

    with threadpool_limits(1):
        env = BeliefVecEnv(variant, n_envs, models=models if variant != "state" else None)
        env.seed(0)
        env.reset()
        actions = np.random.default_rng(0).uniform(-1, 1, (steps + WARM_UP, n_envs, 3)).astype(np.float32)
        for k, a in enumerate(actions):
            if k == WARM_UP:
                t0 = time.perf_counter()
            env.step_async(a)
            env.step_wait()
        env.close()
    return 1e3 * (time.perf_counter() - t0) / steps


def exact_gps(obj: object, depth: int = 0) -> list[ExactGP]:
    """The exact GPs inside a filter (its models, their GPs, stacked parts), found by walking
    its dataclass fields."""
    if isinstance(obj, ExactGP):
        return [obj]
    if depth > 6:
        return []
    if isinstance(obj, (tuple, list)):
        return [g for o in obj for g in exact_gps(o, depth + 1)]
    if dataclasses.is_dataclass(obj):
        return [g for f in dataclasses.fields(obj) for g in exact_gps(getattr(obj, f.name), depth + 1)]
    return []


def variance_cost(models: str) -> tuple[int, int]:
    """The GP-EKF's exact-GP predictive variances: flops for one query (``|L^-1 k|^2`` costs
    ``n^2`` per output, a triangle of multiply-adds) and the bytes of inverse-factor blocks a
    batched step reads once, summed over the prediction GP and each camera's observation GP,
    each with its own ``n``."""
    from estimator_service.factory import build_filter

    gps = exact_gps(build_filter("ekf", "gp", models))
    return sum(g.alpha.shape[1] ** 2 * g.output_dim for g in gps), sum(g.inverse_blocks().nbytes for g in gps)


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="short run (about a minute)")
    parser.add_argument("--smoke", action="store_true", help="tiny run that only checks it works (tests)")
    args = parser.parse_args(argv)
    minutes, points, steps = (1, 60, 256) if args.smoke else (3, 300, 2048) if args.quick else (10, 900, 8192)
    with tempfile.TemporaryDirectory() as tmp:
        flight = collect_flight(minutes * 60, seed=0)
        # no noise calibration: it changes no filter's cost per step, and would dominate the run
        settings = TrainSettings(
            n_points=points, n_pseudo=50, restarts=1, max_iter=20, calibration_seconds=0.0
        )
        train_models([flight], tmp, kinds=["param", "gp", "sparse"], settings=settings)
        rates = {
            name: throughput(AgentSpec(variant=v, model=m, models=tmp), steps)
            for name, v, m in (
                ("state", "state", "gp"),
                ("belief", "belief", "gp"),
                ("belief_sparse", "belief", "sparse"),
            )
        }
        n_batched, b_steps = (2, steps) if args.smoke else (BATCHED_ENVS, max(steps, 8192))  # 2 rollouts
        batched = {
            name: throughput(AgentSpec(variant=v, model="gp", models=tmp), b_steps, n_batched, args.smoke)
            for name, v in (("state", "state"), ("belief", "belief"))
        }
        env_ms = {v: env_step_ms(v, tmp, n_batched, 50 if args.smoke else 400) for v in ("state", "belief")}
        flops, nbytes = variance_cost(tmp)
    for name, r in rates.items():
        print(f"PPO on {name:14s}: {r:8.1f} env steps/s")
    for name, r in batched.items():
        print(f"PPO on {name:14s}: {r:8.1f} env steps/s ({n_batched} envs, batched)")
    out = {
        "state_steps_per_s": round(rates["state"], 1),
        "belief_steps_per_s": round(rates["belief"], 1),
        "belief_to_state_ratio": round(rates["belief"] / rates["state"], 3),
        "belief_sparse_steps_per_s": round(rates["belief_sparse"], 1),
        "belief_sparse_to_state_ratio": round(rates["belief_sparse"] / rates["state"], 3),
        "batched_state_steps_per_s": round(batched["state"], 1),
        "batched_belief_steps_per_s": round(batched["belief"], 1),
        "batched_belief_to_state_ratio": round(batched["belief"] / batched["state"], 3),
        "batched_envs": n_batched,
        "gp_points": points,
    }
    out.update(limits())  # this machine's dgemm rate and read bandwidth, for the ratios
    # where the batched belief step's time goes, against the machine's flop limit
    state_ms = 1e3 * n_batched / batched["state"]  # one PPO step of all envs, learner included
    with threadpool_limits(1):  # the envs step on one core
        one_core = round(dgemm_gflops(), 1)
    floor = 1e3 * n_batched * flops / (one_core * 1e9)  # ms
    out.update({
        "batched_env_state_ms": round(env_ms["state"], 3),
        "batched_env_belief_ms": round(env_ms["belief"], 3),
        "filter_ms": round(env_ms["belief"] - env_ms["state"], 3),
        "dgemm_gflops_one_core": one_core,
        "variance_floor_ms": round(floor, 3),
        "variance_read_mb": round(nbytes / 1e6, 2),  # read once per batched step, from memory when cold
        "variance_read_floor_ms": round(1e3 * nbytes / (out["read_gbs"] * 1e9), 3),
        "filter_to_floor_ratio": round((env_ms["belief"] - env_ms["state"]) / floor, 1),
        "ratio_at_floor": round(state_ms / (state_ms + floor), 3),
    })  # fmt: skip
    print(
        f"filter per batched step {out['filter_ms']:.2f} ms, {out['filter_to_floor_ratio']}x the exact-GP "
        f"variances' flop floor ({floor:.2f} ms at {one_core} GFLOP/s, one core): at the floor the "
        f"batched ratio would be {out['ratio_at_floor']}"
    )
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
