"""How the RL experiment trains each agent: its learning-curve schedule and the ``gpbf
train-agent`` command that trains an agent the same way (shared by the experiment and its
report, so neither imports the other)."""

from __future__ import annotations

from agents.rl import AgentSpec

__all__ = [
    "AGENT_THREADS",
    "CURVE_EPISODES",
    "CURVE_POINTS",
    "DEFAULT_BUDGET",
    "curve_freq",
    "eval_command",
    "train_command",
]

CURVE_POINTS = 10  # evaluations during training
CURVE_EPISODES = 8  # episodes of each of them
DEFAULT_BUDGET = 1_000_000  # the hyperparameter files' n_timesteps
#: torch and BLAS threads each agent trains and is evaluated with (a belief agent's returns
#: depend on the thread count in the last digits)
AGENT_THREADS = 1


def curve_freq(timesteps: int | None) -> int:
    """Steps between the learning curve's evaluations: ``CURVE_POINTS`` over the budget."""
    return max((timesteps or DEFAULT_BUDGET) // CURVE_POINTS, 1000)


def train_command(spec: AgentSpec, timesteps: int | None, models: str, out: str) -> list[str]:
    """The ``gpbf train-agent`` command that trains ``spec``'s agent as the RL experiment does
    (same seed, hyperparameters, learning-curve schedule and checkpoints; the experiment's
    ``_job``), with the model folder ``models`` (belief variants only: the others fly no
    filter) and output folder ``out`` as shown."""
    beliefs = ["--filter", spec.filter, "--model", spec.model, "--models", models]  # the filter's
    return [
        "gpbf", "train-agent", "--algo", spec.algo, "--obs", spec.variant, "--task", spec.task,
        *(beliefs if spec.variant.startswith("belief") else []), "--seed", str(spec.seed),
        *(["--timesteps", str(timesteps)] if timesteps else []),
        "--eval-freq", str(curve_freq(timesteps)), "--curve-episodes", str(CURVE_EPISODES),
        "--threads", str(AGENT_THREADS),
        "--out", out,
    ]  # fmt: skip


def eval_command(model: str, episodes: int, seed: int) -> list[str]:
    """The ``gpbf eval-agent`` command that flies the agent saved as ``model`` (as shown) on
    ``episodes`` episodes from ``seed`` as the RL experiment evaluated it."""
    return [
        "gpbf", "eval-agent", model, "--episodes", str(episodes), "--seed", str(seed),
        "--threads", str(AGENT_THREADS),
    ]  # fmt: skip
