"""Env throughput: single env (closed-form cameras) and the native batched env with 64 blimps,
in the clean (textbook) world and the default lab world (unmodelled physics, camera
latency, motion capture).

Targets on a 2-core machine: >= 2,000 steps/s single env, >= 20,000 aggregate steps/s
batched, in both worlds. The last output line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np
from machine import limits
from threadpoolctl import threadpool_limits

import gpbf_env  # noqa: F401


def single_env_rate(steps: int, reality: str) -> float:
    env = gym.make("gpbf_env/Blimp-v0", reality=reality)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, 3)).astype(np.float32)
    env.reset(seed=0)
    env.step(actions[0])  # warm-up: loads the compiled dynamics
    t0 = time.perf_counter()
    for a in actions:
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    return steps / (time.perf_counter() - t0)


def batched_rate(n_envs: int, steps: int, reality: str) -> float:
    venv = gym.make_vec("gpbf_env/Blimp-v0", num_envs=n_envs, reality=reality)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (steps, n_envs, 3)).astype(np.float32)
    venv.reset(seed=0)
    venv.step(actions[0])  # warm-up: loads the compiled dynamics
    t0 = time.perf_counter()
    for a in actions:
        venv.step(a)
    return steps * n_envs / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="short run (seconds)")
    args = parser.parse_args(argv)
    single_steps, batch_steps = (2_000, 200) if args.quick else (20_000, 2_000)
    with threadpool_limits(1):  # tiny arrays: BLAS threads only add overhead
        single, lab_single = (single_env_rate(single_steps, r) for r in ("clean", "lab"))
        batched, lab_batched = (batched_rate(64, batch_steps, r) for r in ("clean", "lab"))
    for name, a, b in (("single env", single, lab_single), ("batched (64)", batched, lab_batched)):
        print(f"{name:14s} clean {a:10.0f} steps/s   lab {b:10.0f} steps/s")
    result = {
        "single_env_steps_per_s": round(single, 1),
        "batched64_steps_per_s": round(batched, 1),
        "lab_single_env_steps_per_s": round(lab_single, 1),
        "lab_batched64_steps_per_s": round(lab_batched, 1),
        "single_target_ratio": round(single / 2000, 2),
        "batched_target_ratio": round(batched / 20000, 2),
        "lab_single_target_ratio": round(lab_single / 2000, 2),
        "lab_batched_target_ratio": round(lab_batched / 20000, 2),
    }
    result.update(limits())  # this machine's dgemm rate and read bandwidth, for the ratios
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()
