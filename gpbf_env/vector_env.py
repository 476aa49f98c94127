"""Native batched vector env: many blimps stepped by one vectorised numpy pass.

Blimp ``i`` of ``BlimpVectorEnv(num_envs=N)`` reset with ``seed=s`` reproduces a single
:class:`~gpbf_env.blimp_env.BlimpEnv` reset with ``seed=s + i`` step for step (same
random streams, same arithmetic), including across its own autoresets (Gymnasium's
next-step autoreset).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from numpy.typing import NDArray

from gpbf_env.core import WorldConfig, check_action, initial_state, observe
from gpbf_env.dynamics import make_coeffs, rk4_step
from gpbf_env.params import BlimpParams
from gpbf_env.tasks import hover_start, sample_goals, task_reward

__all__ = ["BlimpVectorEnv"]


class BlimpVectorEnv(VectorEnv):
    """``num_envs`` independent blimps (see :class:`~gpbf_env.blimp_env.BlimpEnv`).

    Parameters
    ----------
    num_envs
        Number of blimps.
    max_episode_steps
        Truncation horizon per blimp (``None``: never truncate).
    **config
        :class:`~gpbf_env.core.WorldConfig` fields, shared by all blimps.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": [],
    }

    def __init__(self, num_envs: int = 1, max_episode_steps: int | None = None, **config: Any):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        config.pop("render_mode", None)
        self.num_envs = num_envs
        self.config = WorldConfig(**config)
        self.max_episode_steps = max_episode_steps
        self.single_observation_space = self.config.observation_space()
        self.single_action_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        n = num_envs
        self._rngs = [seeding.np_random(None)[0] for _ in range(n)]
        self._params: list[BlimpParams] = [self.config.params] * n
        self._rebuild_coeffs()
        self._state = np.zeros((12, n))
        self._motors = tuple(np.zeros(n) for _ in range(3))
        self._wind = np.zeros((3, n))
        self._steps = np.zeros(n, dtype=np.int64)
        n_goals = 1 if self.config.task == "hover" else 4
        self._goals = np.zeros((n, n_goals, 4))
        self._goal_index = np.zeros(n, dtype=np.int64)
        self._autoreset = np.zeros(n, dtype=bool)

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
        if options:
            raise ValueError(f"BlimpVectorEnv.reset takes no options, got {sorted(options)}")
        if seed is not None:
            seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, int) else seed
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed list must have {self.num_envs} entries, got {len(seeds)}")
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        rows = np.arange(self.num_envs)
        noise = self._reset_rows(rows)
        self._autoreset[:] = False
        obs = self._observe(rows, noise)
        return obs, self._info(None)

    def step(self, actions: NDArray[np.float32]):
        n = self.num_envs
        a = check_action(actions, n)
        resetting = np.flatnonzero(self._autoreset)
        moving = np.flatnonzero(~self._autoreset)
        cfg = self.config
        cmd = np.clip(a, -1.0, 1.0) * self._scale
        state, motors = rk4_step(
            list(self._state), self._motors, list(cmd.T), list(self._wind), self._coeffs, np
        )
        noise = np.zeros((n, cfg.noise_size - 3))
        self._state[:, moving] = np.array(state)[:, moving]
        self._motors = tuple(
            np.where(self._autoreset, m0, m1) for m0, m1 in zip(self._motors, motors, strict=True)
        )
        if moving.size:
            draws = np.stack([self._rngs[i].standard_normal(cfg.noise_size) for i in moving])
            self._advance_wind(moving, draws[:, :3])
            noise[moving] = draws[:, 3:]
        self._steps[moving] += 1
        pos, yaw = self._state[:3].T, self._state[5]
        goal = self._goals[np.arange(n), self._goal_index]
        parts = task_reward(cfg.task, pos, yaw, goal, a, cfg.weights)
        crashed = cfg.out_of_bounds(pos)
        reward = parts["alive"] + parts["distance"] + parts["heading"] + parts["control"]
        terminated = crashed.copy()
        if cfg.task == "waypoint":
            reached = parts["reached"]
            reward = reward + cfg.weights.reach_bonus * reached
            self._goal_index += reached
            terminated |= self._goal_index >= self._goals.shape[1]
            np.minimum(self._goal_index, self._goals.shape[1] - 1, out=self._goal_index)
        reward = reward - cfg.weights.crash * crashed
        limit = self.max_episode_steps
        truncated = (self._steps >= limit) if limit is not None else np.zeros(n, dtype=bool)
        if resetting.size:
            noise[resetting] = self._reset_rows(resetting)
            reward[resetting] = 0.0
            terminated[resetting] = truncated[resetting] = crashed[resetting] = False
        obs = self._observe(np.arange(n), noise)
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, self._info(parts, crashed)

    # -- helpers -----------------------------------------------------------------------
    def _rebuild_coeffs(self) -> None:
        self._coeffs = make_coeffs(self._params, self.config.dt, self.config.substeps, np)
        self._scale = np.array(
            [[p.max_main_thrust, p.max_vector_angle, p.max_tail_thrust] for p in self._params]
        )
        self._gust_a = np.array([math.exp(-self.config.dt / p.gust_tau) for p in self._params])
        self._gust_s = np.array([p.gust_std for p in self._params]) * np.sqrt(1 - self._gust_a**2)

    def _reset_rows(self, rows: NDArray[np.int64]) -> NDArray[np.float64]:
        """Reset blimps ``rows`` with the single env's draw order; returns camera noise."""
        cfg = self.config
        noise = np.zeros((rows.size, cfg.noise_size - 3))
        changed = False
        for j, i in enumerate(rows):  # per-blimp random streams: one Python call per reset
            rng = self._rngs[i]
            params = cfg.draw_params(rng)
            changed |= params is not self._params[i]
            self._params[i] = params
            self._state[:, i] = initial_state(rng, cfg.room)
            self._goals[i] = sample_goals(rng, cfg.room, cfg.task, self._goals.shape[1])
            if cfg.task == "hover":
                self._state[:, i] = hover_start(rng, self._state[:, i], self._goals[i, 0])
            self._wind[:, i] = rng.normal(0.0, params.gust_std, size=3)
            noise[j] = rng.standard_normal(cfg.noise_size - 3)
        if changed:
            self._rebuild_coeffs()
        for m in self._motors:
            m[rows] = 0.0
        self._steps[rows] = 0
        self._goal_index[rows] = 0
        return noise

    def _advance_wind(self, rows: NDArray[np.int64], z: NDArray[np.float64]) -> None:
        a, s = self._gust_a[rows], self._gust_s[rows]
        self._wind[:, rows] = a * self._wind[:, rows] + s * z.T

    def _observe(self, rows: NDArray[np.int64], noise: NDArray[np.float64]) -> dict[str, Any]:
        frames = self.config.frame_schedule(self._steps)
        ell, valid = observe(self.config, self._state.T, frames, noise, self._rngs)
        return {"ellipses": ell, "valid": valid}

    def _info(self, parts: dict[str, Any] | None, crashed: Any = None) -> dict[str, Any]:
        n = self.num_envs
        info: dict[str, Any] = {
            "state": self._state.T.copy(),
            "t": self._steps * self.config.dt,
            "goal": self._goals[np.arange(n), self._goal_index].copy(),
            "waypoint_index": self._goal_index.copy(),
        }
        if parts is not None:
            info.update(
                reward_alive=parts["alive"],
                reward_distance=parts["distance"],
                reward_heading=parts["heading"],
                reward_control=parts["control"],
                distance_m=parts["distance_m"],
                success=parts["reached"],
                crashed=crashed,
            )
        return info
