"""The simulator glue: the one module that knows both ``gpbf_env`` and the estimator's data.

:func:`collect_flight` flies a pilot (or an agent) in the blimp env and records an
estimator :class:`~estimator_service.flight.Flight` (ground truth, controls, camera
ellipses as sensor readings, the blimp's system description, the cameras' calibration and
the physical parameters the parametric model is fitted with). :func:`env_frames` and
:func:`env_readings` turn an env observation into the service's frames and the filters'
``(z, valid)``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

import gpbf_env  # noqa: F401  (registers the env)
from agents.pilots import make_pilot
from estimator_service.blimp import blimp_system
from estimator_service.flight import Flight, make_flight
from estimator_service.system import System

__all__ = ["camera_metadata", "collect_flight", "env_frames", "env_readings", "env_system"]

NO_LIMIT = 10**9  # gym.make(max_episode_steps=None) would mean "the registered default"
FloatArray = NDArray[np.float64]


def env_system(env: gym.Env) -> System:
    """The blimp description of an env (its cameras and step)."""
    cfg = env.unwrapped.config
    return blimp_system(cfg.n_cameras, cfg.dt, cfg.camera_rate_hz)


def env_frames(obs: dict[str, np.ndarray]) -> list[list[Any]]:
    """``[[camera, [cx, cy, w, h, angle]], ...]`` for the cameras marked valid (the service's
    ``frames``)."""
    return [[int(k), [float(v) for v in obs["ellipses"][k]]] for k in np.flatnonzero(obs["valid"])]


def env_readings(obs: dict[str, np.ndarray], system: System) -> tuple[FloatArray, NDArray[np.bool_]]:
    """``z (m,)`` and per-output ``valid (m,)`` of an env observation, for a filter step."""
    return system.frames({int(k): obs["ellipses"][k] for k in np.flatnonzero(obs["valid"])})


def camera_metadata(env: gym.Env) -> list[dict[str, Any]]:
    """Calibration of the env's cameras as JSON-ready dicts."""
    return [
        {
            "name": c.name,
            "position": c.position.tolist(),
            "rotation": c.rotation.tolist(),
            "focal": c.focal,
            "principal_point": list(c.principal_point),
            "size": list(c.size),
            "k1": c.k1,
            "k2": c.k2,
            "rate_hz": c.rate_hz,
            "phase_s": c.phase_s,
        }
        for c in env.unwrapped.config.cameras
    ]


def collect_flight(
    seconds: float,
    *,
    pilot: str = "scripted",
    seed: int = 0,
    env_id: str = "gpbf_env/Blimp-v0",
    env_kwargs: dict[str, Any] | None = None,
    policy: Callable[[dict[str, Any], dict[str, Any]], FloatArray] | None = None,
    progress: Callable[[int, int], None] | None = None,
    episode_seconds: float | None = None,
) -> Flight:
    """Fly for ``seconds`` of sim time and record; episodes restart after a crash (and
    after ``episode_seconds``, when given: e.g. an agent's 60 s episodes, each with a new
    goal).

    The flight's ``state`` is the env's motion-capture measurement (``info["mocap"]``),
    the ground truth the paper trained and scored on; ``exact`` is the simulator's state.

    Parameters
    ----------
    pilot
        ``scripted`` or ``random`` (ignored when ``policy`` is given).
    policy
        Optional ``policy(obs, info) -> action`` (raw observation, env info), e.g. a
        trained agent (:class:`agents.rl.AgentPolicy`); it is told of resets by
        ``info["t"] == 0``.
    progress
        Called with the number of steps done and the total after each step.
    episode_seconds
        Episode length (None: episodes end only by crashing).
    """
    env = gym.make(env_id, max_episode_steps=NO_LIMIT, **(env_kwargs or {}))
    dt = env.unwrapped.config.dt
    limit = NO_LIMIT if episode_seconds is None else max(1, round(episode_seconds / dt))
    rng = np.random.default_rng(seed)
    driver = make_pilot(pilot, rng)
    obs, info = env.reset(seed=seed)
    flown = [env.unwrapped.params.to_dict()]  # each episode's parameters (domain randomisation)
    steps = round(seconds / env.unwrapped.config.dt)
    keys = ("t", "state", "exact", "control", "ellipses", "valid", "episode")
    rows: dict[str, list[Any]] = {k: [] for k in keys}
    episode, ep_steps = 0, 0
    for k in range(steps + 1):
        action = policy(obs, info) if policy else driver.act(info["state"])
        action = np.zeros(3) if k == steps else np.asarray(action, dtype=np.float64)
        for key, val in (
            ("t", info["t"]),
            ("state", info["mocap"]),  # what the lab's motion capture measured, as in the paper
            ("exact", info["state"]),
            ("control", action),
            ("ellipses", obs["ellipses"]),
            ("valid", obs["valid"]),
            ("episode", episode),
        ):
            rows[key].append(val)
        if k == steps:
            break
        obs, _, terminated, truncated, info = env.step(action.astype(np.float32))
        ep_steps += 1
        if terminated or truncated or ep_steps >= limit:
            episode, ep_steps = episode + 1, 0
            obs, info = env.reset()
            flown.append(env.unwrapped.params.to_dict())
        if progress:
            progress(k + 1, steps)
    cfg = env.unwrapped.config
    meta = {
        "seed": seed,
        "pilot": "agent" if policy else pilot,
        "env_id": env_id,
        "dt": cfg.dt,
        "env_config": {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("params", "weights")},
        "params": flown[0],
        "episode_params": flown,
        "base_params": cfg.params.to_dict(),
        "cameras": camera_metadata(env),
    }
    system = env_system(env)
    env.close()
    ellipses = np.asarray(rows["ellipses"], dtype=np.float64)
    return make_flight(
        system,
        rows["t"], np.asarray(rows["state"]), np.asarray(rows["control"]),
        ellipses.reshape(len(ellipses), -1), np.asarray(rows["valid"], dtype=bool), rows["episode"],
        exact=np.asarray(rows["exact"]), **meta,
    )  # fmt: skip
