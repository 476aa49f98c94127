"""Tuned hyperparameters, one file per algorithm in rl-zoo3's format (``hyperparams/*.yml``).

The files are read by rl-zoo3 (``--conf-file hyperparams/ppo.yml``) and by
:func:`~agents.rl.training.train_agent`, which takes the entry of the agent's registered id
(:func:`~agents.rl.registry.agent_env_id`). Only the keys that both can honour are
accepted here: the algorithm's keyword arguments, ``policy``, ``n_envs`` and
``n_timesteps``; a wrapper or normalisation key would change what the agent sees in one
of the two and not the other, so it is refused with its name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["HYPERPARAMS_DIR", "Hyperparams", "load_hyperparams"]

HYPERPARAMS_DIR = Path(__file__).with_name("hyperparams")
MAX_FILE_BYTES = 1_000_000  # the committed files are about 1.3 kB; a bound on what is parsed
_REFUSED = ("normalize", "env_wrapper", "frame_stack", "vec_env_wrapper", "callback", "monitor_kwargs")


@dataclass(frozen=True)
class Hyperparams:
    """One file entry: ``n_envs``, ``n_timesteps``, ``policy`` and the algorithm's kwargs."""

    n_envs: int
    n_timesteps: int
    policy: str
    kwargs: dict[str, Any] = field(default_factory=dict)


def load_hyperparams(algo: str, env_id: str, path: str | Path | None = None) -> Hyperparams:
    """The entry for ``env_id`` in ``path`` (default ``hyperparams/<algo>.yml``).

    Raises
    ------
    FileNotFoundError, KeyError, ValueError
        No such file, no entry for ``env_id``, or an entry with a refused or malformed key
        (named in the message).
    """
    import yaml

    file = Path(path) if path is not None else HYPERPARAMS_DIR / f"{algo}.yml"
    if not file.is_file():
        raise FileNotFoundError(f"hyperparameter file {str(file)!r} does not exist")
    if file.stat().st_size > MAX_FILE_BYTES:
        raise ValueError(f"hyperparameter file {str(file)!r} is over {MAX_FILE_BYTES} bytes")
    entries = yaml.safe_load(file.read_text())
    if not isinstance(entries, dict) or env_id not in entries:
        raise KeyError(f"{file.name}: no entry for {env_id!r}")
    entry = dict(entries[env_id])
    for key in _REFUSED:
        if key in entry:
            raise ValueError(f"{file.name}[{env_id}]: key {key!r} is not supported by train_agent")
    n_envs, n_timesteps = entry.pop("n_envs", 1), entry.pop("n_timesteps", 1_000_000)
    policy = entry.pop("policy", "MlpPolicy")
    for key, value, kind in (("n_envs", n_envs, int), ("n_timesteps", n_timesteps, (int, float))):
        if not isinstance(value, kind) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{file.name}[{env_id}]: {key} must be a positive number, got {value!r}")
    if not isinstance(entry.get("policy_kwargs", {}), dict):
        raise ValueError(f"{file.name}[{env_id}]: policy_kwargs must be a mapping (no code strings)")
    return Hyperparams(int(n_envs), int(n_timesteps), str(policy), entry)
