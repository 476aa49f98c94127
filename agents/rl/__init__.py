"""RL on filtered beliefs: the observation wrappers, the batched belief vector env, the
Gymnasium ids of the belief envs (registered on import) and SB3 training (needs the ``rl``
extra)."""

from agents.rl.batched import BeliefVecEnv
from agents.rl.registry import TASK_ENVS, agent_env_id, episode_success, register_belief_envs
from agents.rl.training import (
    AgentPolicy,
    AgentSpec,
    evaluate_agent,
    evaluate_pilot,
    load_agent,
    make_env,
    make_vec,
    train_agent,
)
from agents.rl.wrappers import INIT_STD, VARIANTS, BeliefObservation, belief_features, make_belief_env

register_belief_envs()

__all__ = [
    "INIT_STD",
    "TASK_ENVS",
    "VARIANTS",
    "AgentPolicy",
    "AgentSpec",
    "BeliefObservation",
    "BeliefVecEnv",
    "agent_env_id",
    "belief_features",
    "episode_success",
    "evaluate_agent",
    "evaluate_pilot",
    "load_agent",
    "make_belief_env",
    "make_env",
    "make_vec",
    "register_belief_envs",
    "train_agent",
]
