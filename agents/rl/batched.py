"""Batched belief envs: ``N`` blimps in the native batched simulator, their ``N`` filters
advanced by one batched model call per step, as a stable-baselines3 ``VecEnv``.

Blimp ``i`` of ``BeliefVecEnv(variant, N)`` seeded ``s`` gives the observations, rewards,
dones and terminal observations that SB3's ``DummyVecEnv`` of ``N``
:class:`~agents.rl.wrappers.BeliefObservation` envs seeded ``s + i`` gives (the
one-at-a-time path), to rounding: the simulator is the same arithmetic
(:class:`~gpbf_env.BlimpVectorEnv` with same-step autoreset), the GP-EKF's and GP-UKF's
batched steps (``step_many``: one model call for all blimps) equal their single steps up to
the rounding of a batched GP call, and the step policy and innovation gate are the service's
(:func:`~estimator_service.filters.policy.step_many`; the PF steps each blimp with its own
generator).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode
from numpy.typing import NDArray
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from agents.rl.registry import episode_success
from agents.rl.wrappers import (
    FEATURE_BOUND,
    GATE_P,
    INIT_STD,
    belief_features_many,
    bounded,
    ellipse_features_many,
    feature_size,
)
from estimator_service.blimp import blimp_system
from estimator_service.factory import build_filter
from estimator_service.filters import GaussianBelief
from estimator_service.filters.policy import step_many
from estimator_service.service.limits import gate_for
from estimator_service.system import System
from gpbf_env import MAX_EPISODE_STEPS, BlimpVectorEnv

__all__ = ["BeliefVecEnv", "readings_many"]

FloatArray = NDArray[np.float64]


def readings_many(
    ellipses: NDArray[np.float32], valid: NDArray[Any], system: System
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """``z (N, m)`` and per-output ``valid (N, m)`` of ``N`` blimps' camera ellipses
    ``(N, C, 5)`` and flags ``(N, C)``: :func:`agents.sim.env_readings` for a batch."""
    n, c = valid.shape
    z, ok = np.zeros((n, system.obs_dim)), np.zeros((n, system.obs_dim), dtype=bool)
    seen = np.asarray(valid, dtype=bool)
    for k in range(c):  # per camera, not per blimp
        sl = system.sensor_slice(k)
        z[:, sl] = np.where(seen[:, k, None], ellipses[:, k], 0.0)
        ok[:, sl] = seen[:, k, None]
    return z, ok


class BeliefVecEnv(VecEnv):
    """SB3 vector env of ``n_envs`` blimps seen through one observation variant.

    Parameters
    ----------
    variant
        One of :data:`agents.rl.wrappers.VARIANTS`.
    n_envs
        Number of blimps.
    env_id
        ``gpbf_env/Blimp-v0`` (hover) or ``gpbf_env/BlimpWaypoint-v0``: its task and
        registered keyword arguments are used.
    models, filter, model
        As :class:`~agents.rl.wrappers.BeliefObservation` (in-process back end).
    max_episode_steps
        Truncation horizon (the registered 240 steps by default).
    **env_kwargs
        :class:`~gpbf_env.WorldConfig` fields.
    """

    def __init__(
        self,
        variant: str,
        n_envs: int,
        *,
        env_id: str = "gpbf_env/Blimp-v0",
        models: str | None = None,
        filter: str = "ekf",
        model: str = "gp",
        max_episode_steps: int = MAX_EPISODE_STEPS,
        **env_kwargs: Any,
    ) -> None:
        feature_size(variant, 0)  # refuses an unknown variant before any work
        uses_filter = variant in ("belief", "belief-param")
        if uses_filter and models is None:
            raise ValueError(f"variant {variant!r} needs a model folder (models=...)")
        kwargs = {**gym.spec(env_id).kwargs, **env_kwargs}
        self.sim = BlimpVectorEnv(n_envs, max_episode_steps, autoreset_mode=AutoresetMode.SAME_STEP, **kwargs)
        cfg = self.sim.config
        self.variant = variant
        self.system = blimp_system(cfg.n_cameras, cfg.dt, cfg.camera_rate_hz)
        model_kind = "param" if variant == "belief-param" else model
        self.filter = build_filter(filter, model_kind, models) if uses_filter else None
        size = feature_size(variant, cfg.n_cameras)
        space = spaces.Box(-FEATURE_BOUND, FEATURE_BOUND, shape=(size,), dtype=np.float32)
        self.render_mode = None
        super().__init__(n_envs, space, self.sim.single_action_space)
        self._rngs = [np.random.default_rng(i) for i in range(n_envs)]
        self._beliefs: list[Any] = [None] * n_envs
        self._last_action = np.zeros((n_envs, 3))
        self._actions = np.zeros((n_envs, 3), dtype=np.float32)

    # -- SB3 VecEnv API --------------------------------------------------------------------------
    def reset(self) -> NDArray[np.float32]:
        seeds = self._seeds
        if any(s is not None for s in seeds):
            if any(s is None for s in seeds):
                raise ValueError(f"seed every blimp or none, got seeds {seeds}")
            self._rngs = [np.random.default_rng(s) for s in seeds]
            obs, info = self.sim.reset(seed=[int(s) for s in seeds])
        else:
            obs, info = self.sim.reset()
        self._reset_seeds()
        self._reset_options()
        rows = np.arange(self.num_envs)
        self._restart(rows, info["state"])
        return self._features(obs["ellipses"], obs["valid"], info["state"], info["goal"])

    def step_async(self, actions: NDArray[Any]) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)

    def step_wait(self) -> VecEnvStepReturn:
        a = np.clip(self._actions.astype(np.float64), -1.0, 1.0)
        obs, reward, term, trunc, info = self.sim.step(self._actions)
        done = term | trunc
        ended = np.flatnonzero(done)
        ell, valid = obs["ellipses"].copy(), obs["valid"].copy()
        state, goal = info["state"].copy(), info["goal"].copy()
        if ended.size:  # the step's own view of the blimps that were just reset
            fin = info["final_info"]
            for i in ended:
                ell[i], valid[i] = info["final_obs"][i]["ellipses"], info["final_obs"][i]["valid"]
            state[ended], goal[ended] = fin["state"][ended], fin["goal"][ended]
        self._advance(a, ell, valid)
        self._last_action = a
        features = self._features(ell, valid, state, goal)
        infos: list[dict[str, Any]] = [
            {"TimeLimit.truncated": bool(trunc[i] and not term[i])} for i in range(self.num_envs)
        ]
        if ended.size:
            for i in ended:
                infos[i]["terminal_observation"] = features[i].copy()
                last = {key: fin[key][i] for key in ("success", "crashed")}
                infos[i]["is_success"] = episode_success(last)
            self._restart(ended, info["state"][ended])
            fresh = self._features(
                obs["ellipses"][ended], obs["valid"][ended], info["state"][ended], info["goal"][ended], ended
            )
            features[ended] = fresh
        return features, reward.astype(np.float32), done, infos

    def close(self) -> None:
        self.sim.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        raise AttributeError(f"BeliefVecEnv's blimps share their attributes; cannot set {attr_name!r}")

    def env_method(self, method_name: str, *args: Any, indices: VecEnvIndices = None, **kwargs: Any) -> list:
        raise AttributeError(f"BeliefVecEnv has no per-blimp envs to call {method_name!r} on")

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))

    # -- the estimates ---------------------------------------------------------------------------
    def beliefs(self) -> list[GaussianBelief] | None:
        """Each blimp's Gaussian belief (``None`` for the state and ellipse variants)."""
        if self.filter is None:
            return None
        return [self.filter.gaussian(b) for b in self._beliefs]

    def _restart(self, rows: NDArray[np.int64], states: FloatArray) -> None:
        """Blimps ``rows`` start their estimates at the (motion-capture) states ``(len(rows), 12)``."""
        self._last_action[rows] = 0.0
        if self.filter is None:
            return
        for i, mean in zip(rows, states, strict=True):  # on resets only
            g = GaussianBelief(np.array(mean, dtype=np.float64), np.diag(INIT_STD**2))
            self._beliefs[i] = self.filter.initial(g, self._rngs[i])

    def _advance(self, a: FloatArray, ellipses: NDArray[np.float32], valid: NDArray[Any]) -> None:
        """One filter step of every blimp: the batched step where the filter has one."""
        if self.filter is None:
            return
        z, ok = readings_many(ellipses, valid, self.system)
        out = step_many(self.filter, self._beliefs, a, z, ok, gate_for(GATE_P), self._rngs)
        self._beliefs = [b for b, _ in out]

    def _features(
        self,
        ellipses: NDArray[np.float32],
        valid: NDArray[Any],
        state: FloatArray,
        goal: FloatArray,
        rows: Sequence[int] | NDArray[np.int64] | None = None,
    ) -> NDArray[np.float32]:
        """Feature rows of blimps ``rows`` (all by default) from their observations."""
        rows = np.arange(self.num_envs) if rows is None else np.asarray(rows)
        if self.variant == "state":
            return bounded(belief_features_many(state, None, goal))
        if self.variant == "ellipses":
            return bounded(ellipse_features_many(ellipses, valid, self._last_action[rows], goal))
        gs = [self.filter.gaussian(self._beliefs[i]) for i in rows]
        mean = np.stack([g.mean for g in gs])
        std = np.sqrt(np.stack([np.diag(g.cov) for g in gs]))
        return bounded(belief_features_many(mean, std, goal))
