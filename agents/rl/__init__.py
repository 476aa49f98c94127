"""RL on filtered beliefs: the observation wrappers and SB3 training (needs the ``rl`` extra)."""

from agents.rl.training import (
    AgentPolicy,
    AgentSpec,
    evaluate_agent,
    load_agent,
    make_env,
    make_vec,
    train_agent,
)
from agents.rl.wrappers import INIT_STD, VARIANTS, BeliefObservation, belief_features, make_belief_env

__all__ = [
    "INIT_STD",
    "VARIANTS",
    "AgentPolicy",
    "AgentSpec",
    "BeliefObservation",
    "belief_features",
    "evaluate_agent",
    "load_agent",
    "make_belief_env",
    "make_env",
    "make_vec",
    "train_agent",
]
