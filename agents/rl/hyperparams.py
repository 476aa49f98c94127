"""Tuned hyperparameters, one file per algorithm in rl-zoo3's format (``hyperparams/*.yml``).

The files are read by rl-zoo3 (``--conf-file hyperparams/ppo.yml``) and by
:func:`~agents.rl.training.train_agent`, which takes the entry of the agent's registered id
(:func:`~agents.rl.registry.agent_env_id`). Only the keys that both can honour are
accepted here: the algorithm's keyword arguments, ``policy``, ``n_envs``, ``n_timesteps``
and ``normalize`` (SB3's ``VecNormalize``, which both apply and save beside the agent as
``vecnormalize.pkl``), with rl-zoo3's ``"lin_<x>"`` linear schedules for
``learning_rate``, ``clip_range`` and ``clip_range_vf``; a wrapper key would change what
the agent sees in one of the two and not the other, so it is refused with its name.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["HYPERPARAMS_DIR", "Hyperparams", "LinearSchedule", "load_hyperparams"]

HYPERPARAMS_DIR = Path(__file__).with_name("hyperparams")
NORMALIZE_BOTH = {"norm_obs": True, "norm_reward": True}  # rl-zoo3's `normalize: true`
MAX_FILE_BYTES = 1_000_000  # the committed files are about 1.3 kB; a bound on what is parsed
_REFUSED = ("env_wrapper", "frame_stack", "vec_env_wrapper", "callback", "monitor_kwargs")
SCHEDULED = ("learning_rate", "clip_range", "clip_range_vf")  # keys rl-zoo3 reads "lin_<x>" in
LINEAR_PREFIX = "lin_"


@dataclass(frozen=True)
class Hyperparams:
    """One file entry: ``n_envs``, ``n_timesteps``, ``policy``, the algorithm's kwargs and
    ``normalize``: keyword arguments of SB3's ``VecNormalize`` (``norm_obs``,
    ``norm_reward``) or None (rl-zoo3's ``normalize: true`` is both)."""

    n_envs: int
    n_timesteps: int
    policy: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    normalize: dict[str, bool] | None = None


def load_hyperparams(algo: str, env_id: str, path: str | Path | None = None) -> Hyperparams:
    """The entry for ``env_id`` in ``path`` (default ``hyperparams/<algo>.yml``).

    Raises
    ------
    FileNotFoundError, ValueError
        No such file; not YAML, no entry for ``env_id``, or an entry with a refused or
        malformed key (named in the message).
    """
    import yaml

    file = Path(path) if path is not None else HYPERPARAMS_DIR / f"{algo}.yml"
    if not file.is_file():
        raise FileNotFoundError(f"hyperparameter file {str(file)!r} does not exist")
    if file.stat().st_size > MAX_FILE_BYTES:
        raise ValueError(f"hyperparameter file {str(file)!r} is over {MAX_FILE_BYTES} bytes")
    try:
        entries = yaml.safe_load(file.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ValueError(f"hyperparameter file {str(file)!r} is not YAML ({type(exc).__name__})") from None
    if not isinstance(entries, dict) or env_id not in entries:
        got = f"entries {sorted(map(str, entries))}" if isinstance(entries, dict) else "no mapping of env ids"
        raise ValueError(f"hyperparameter file {str(file)!r} has no entry for {env_id!r} ({got})")
    if not isinstance(entries[env_id], dict):
        raise ValueError(f"{file.name}[{env_id}]: expected a mapping of hyperparameters")
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
    normalize = _normalize(entry.pop("normalize", False), f"{file.name}[{env_id}]")
    for key in SCHEDULED:
        if key in entry:
            entry[key] = _schedule(entry[key], f"{file.name}[{env_id}].{key}")
    return Hyperparams(int(n_envs), int(n_timesteps), str(policy), entry, normalize)


@dataclass(frozen=True)
class LinearSchedule:
    """rl-zoo3's ``lin_<start>``: ``start`` at the first update, falling linearly to 0.

    SB3 calls it with the remaining progress (1 at the start of training, 0 at the end).
    A class, not a closure, so that a saved agent's schedule pickles by name.
    """

    start: float

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.start


def _schedule(value: object, where: str) -> float | LinearSchedule | None:
    """A positive number as is, rl-zoo3's ``"lin_<positive number>"`` as a
    :class:`LinearSchedule`, or ``null`` where SB3 takes None (``clip_range_vf``: no clipping)."""
    if value is None and where.endswith(".clip_range_vf"):
        return None
    linear = isinstance(value, str) and value.startswith(LINEAR_PREFIX)
    number = value[len(LINEAR_PREFIX) :] if linear else value
    try:
        start = math.nan if isinstance(number, bool) else float(number)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        start = math.nan
    if math.isfinite(start) and start > 0 and (linear or not isinstance(value, str)):
        return LinearSchedule(start) if linear else start
    expected = f"a positive number or '{LINEAR_PREFIX}<positive number>'"
    raise ValueError(f"{where} must be {expected}, got {value!r}")


def _normalize(value: object, where: str) -> dict[str, bool] | None:
    """rl-zoo3's ``normalize``: false, true (observations and rewards) or a mapping of
    ``norm_obs`` / ``norm_reward`` to booleans (no code strings)."""
    if value is False:
        return None
    value = {} if value is True else value
    if not isinstance(value, dict) or not set(value) <= set(NORMALIZE_BOTH):
        raise ValueError(f"{where}: normalize must be true, false or a mapping of {sorted(NORMALIZE_BOTH)}")
    if not all(isinstance(v, bool) for v in value.values()):
        raise ValueError(f"{where}: normalize's values must be true or false")
    return {**NORMALIZE_BOTH, **value}
