"""Gymnasium ids of the belief envs, so that rl-zoo3 and ``gymnasium.make`` can build them.

``import agents.rl`` registers one id per task and observation variant, e.g.
``gpbf_agents/BlimpBelief-v0`` (hover, GP-EKF belief) or
``gpbf_agents/BlimpWaypointEllipses-v0``; keyword arguments of ``gymnasium.make`` (or
rl-zoo3's ``--env-kwargs``) reach :func:`~agents.rl.wrappers.make_belief_env`, so the
belief variants take ``models="<folder>"``::

    python -m rl_zoo3.train --algo sac --env gpbf_agents/BlimpBelief-v0 --gym-packages agents.rl \\
        --conf-file hyperparams/sac.yml --env-kwargs models:"'models'"
"""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

__all__ = ["TASK_ENVS", "agent_env_id", "episode_success", "register_belief_envs"]

TASK_ENVS = {"hover": "gpbf_env/Blimp-v0", "waypoint": "gpbf_env/BlimpWaypoint-v0"}
_TASK_NAMES = {"hover": "Blimp", "waypoint": "BlimpWaypoint"}
_VARIANT_NAMES = {"state": "State", "belief": "Belief", "belief-param": "BeliefParam", "ellipses": "Ellipses"}


def agent_env_id(task: str, variant: str) -> str:
    """The registered id of a task seen through an observation variant."""
    if task not in TASK_ENVS:
        raise ValueError(f"task must be one of {sorted(TASK_ENVS)}, got {task!r}")
    if variant not in _VARIANT_NAMES:
        raise ValueError(f"variant must be one of {tuple(_VARIANT_NAMES)}, got {variant!r}")
    return f"gpbf_agents/{_TASK_NAMES[task]}{_VARIANT_NAMES[variant]}-v0"


def episode_success(last_info: dict) -> bool:
    """Whether an episode that just ended succeeded: uncrashed, and (hover) within the
    reach radius of its goal at the end or (waypoint) with every waypoint reached, as the
    env's last ``info["success"]`` says."""
    return bool(last_info.get("success")) and not bool(last_info.get("crashed"))


def register_belief_envs() -> None:
    """Register every (task, variant) id (idempotent)."""
    for task, base in TASK_ENVS.items():
        for variant in _VARIANT_NAMES:
            env_id = agent_env_id(task, variant)
            if env_id not in registry:
                register(
                    id=env_id,
                    entry_point="agents.rl.wrappers:make_belief_env",
                    kwargs={"variant": variant, "env_id": base},
                )
