"""gpbf_env: a Gymnasium micro-blimp simulator with camera-ellipse observations.

``import gpbf_env`` registers ``gpbf_env/Blimp-v0`` (hover task) and
``gpbf_env/BlimpWaypoint-v0`` with Gymnasium, each with a native batched
``vector_entry_point``.
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

from gpbf_env.blimp_env import BlimpEnv
from gpbf_env.core import STATE_NAMES, WorldConfig
from gpbf_env.params import BlimpParams
from gpbf_env.vector_env import BlimpVectorEnv

__all__ = [
    "STATE_NAMES",
    "BlimpEnv",
    "BlimpParams",
    "BlimpVectorEnv",
    "WorldConfig",
    "register_envs",
]

MAX_EPISODE_STEPS = 240  # 60 s at 4 Hz


def register_envs() -> None:
    """Register the blimp environments with Gymnasium (idempotent)."""
    for env_id, task in (("gpbf_env/Blimp-v0", "hover"), ("gpbf_env/BlimpWaypoint-v0", "waypoint")):
        if env_id in registry:
            continue
        register(
            id=env_id,
            entry_point="gpbf_env.blimp_env:BlimpEnv",
            vector_entry_point="gpbf_env.vector_env:BlimpVectorEnv",
            max_episode_steps=MAX_EPISODE_STEPS,
            kwargs={"task": task},
        )


register_envs()
