"""Native batched vector env: many blimps stepped by one vectorised numpy pass.

Blimp ``i`` of ``BlimpVectorEnv(num_envs=N)`` reset with ``seed=s`` reproduces a single
:class:`~gpbf_env.blimp_env.BlimpEnv` reset with ``seed=s + i`` step for step (same
random streams, same arithmetic), including across its own autoresets: Gymnasium's
next-step autoreset (the default) or same-step autoreset (``autoreset_mode=
AutoresetMode.SAME_STEP``: an ended blimp is reset within the step that ended it, its last
observation and info in ``info["final_obs"]`` and ``info["final_info"]``, the layout
stable-baselines3's vector envs use). Its ``info`` has the keys, shapes, dtypes, ``"_key"``
masks and values that ``gym.make_vec(..., vectorization_mode="sync")`` builds from the
single envs' infos in the same mode, and ``render()`` returns the same frames.
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

from gpbf_env.core import WorldConfig, camera_lag, check_action, initial_state, observe
from gpbf_env.dynamics import make_coeffs, rk4_step
from gpbf_env.mocap import AUX_DRAWS, PoseTrack, measure
from gpbf_env.params import BlimpParams
from gpbf_env.tasks import advance_course, hover_start, sample_goals, task_reward

__all__ = ["BlimpVectorEnv"]


class BlimpVectorEnv(VectorEnv):
    """``num_envs`` independent blimps (see :class:`~gpbf_env.blimp_env.BlimpEnv`).

    Parameters
    ----------
    num_envs
        Number of blimps.
    max_episode_steps
        Truncation horizon per blimp (``None``: never truncate).
    render_mode
        ``"rgb_array"`` (``render()`` returns one frame per blimp) or None.
    autoreset_mode
        ``AutoresetMode.NEXT_STEP`` (default) or ``AutoresetMode.SAME_STEP`` (or their
        string values).
    **config
        :class:`~gpbf_env.core.WorldConfig` fields, shared by all blimps.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": ["rgb_array"],
        "render_fps": 4,
    }

    def __init__(
        self,
        num_envs: int = 1,
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        **config: Any,
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        modes = {m.value: m for m in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP)}
        mode = autoreset_mode.value if isinstance(autoreset_mode, AutoresetMode) else autoreset_mode
        if mode not in modes:
            raise ValueError(f"autoreset_mode must be one of {list(modes)}, got {autoreset_mode!r}")
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.config = WorldConfig(**config)
        self.autoreset_mode = modes[mode]
        self.metadata = {
            **self.metadata,
            "render_fps": round(1.0 / self.config.dt),
            "autoreset_mode": self.autoreset_mode,
        }
        self.max_episode_steps = max_episode_steps
        self.single_observation_space = self.config.observation_space()
        self.single_action_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        n = num_envs
        self._rngs = [seeding.np_random(None)[0] for _ in range(n)]
        self._aux = [rng.spawn(1)[0] for rng in self._rngs]  # replaced at reset
        self._params: list[BlimpParams] = [self.config.params] * n
        self._rebuild_coeffs()
        self._track = PoseTrack(n, self.config.substeps, self.config.dt, self.config.track_depth)
        self._mocap = np.zeros((n, 12))
        self._state = np.zeros((12, n))
        self._motors = np.zeros((3, n))
        self._wind = np.zeros((3, n))
        self._steps = np.zeros(n, dtype=np.int64)
        n_goals = 1 if self.config.task == "hover" else 4
        self._goals = np.zeros((n, n_goals, 4))
        self._goal_index = np.zeros(n, dtype=np.int64)
        self._finished = np.zeros(n, dtype=bool)
        self._autoreset = np.zeros(n, dtype=bool)
        # rendering only: last observation and position snapshots (T, N, 3), blimp i's
        # episode trail being ``_trail[_trail_start[i]:, i]``
        self._last_obs: dict[str, NDArray[Any]] | None = None
        self._trail: list[NDArray[np.float64]] = []
        self._trail_start = np.zeros(n, dtype=np.int64)

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
        """Reset every blimp.

        Parameters
        ----------
        seed
            ``s`` seeds blimp ``i`` with ``s + i``; a list gives one seed per blimp.
        options
            Not supported (must be empty).

        Returns
        -------
        obs
            Batched observation.
        info
            Batched info with ``"_key"`` masks, as the ``"sync"`` vector env returns.
        """
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
        if self.render_mode is not None:
            self._trail = [self._state[:3].T.copy()]
            self._trail_start[:] = 0
        return obs, self._info(None)

    def step(
        self, actions: NDArray[np.float32]
    ) -> tuple[
        dict[str, NDArray[Any]], NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_], dict[str, Any]
    ]:
        """Step every blimp; blimps that ended on the previous step are reset instead.

        Parameters
        ----------
        actions: (N, 3)
            Normalised actions.

        Returns
        -------
        obs, reward, terminated, truncated
            Batched step results (zero reward, not done for the blimps just reset).
        info
            Batched info with ``"_key"`` masks; the step-only keys are masked off for the
            blimps just reset (and absent when all were), as the ``"sync"`` vector env does.
        """
        n = self.num_envs
        a = check_action(actions, n)
        resetting = np.flatnonzero(self._autoreset)
        moving = np.flatnonzero(~self._autoreset)
        cfg = self.config
        cmd = np.clip(a, -1.0, 1.0) * self._scale
        previous = self._state[:3].T.copy()
        state, motors, knots = rk4_step(self._state, self._motors, cmd.T, self._wind, self._coeffs)
        self._track.push(knots)
        noise = np.zeros((n, cfg.noise_size - 3))
        self._state[:, moving] = state[:, moving]
        self._motors = np.where(self._autoreset, self._motors, motors)
        if moving.size:
            draws = np.stack([self._rngs[i].standard_normal(cfg.noise_size) for i in moving])
            self._advance_wind(moving, draws[:, :3])
            noise[moving] = draws[:, 3:]
        self._steps[moving] += 1
        pos, yaw = self._state[:3].T, self._state[5]
        goal = self._goals[np.arange(n), self._goal_index]
        parts = task_reward(cfg.task, pos, yaw, goal, a, cfg.weights, previous, self._finished)
        crashed = cfg.out_of_bounds(pos)
        reward = parts["alive"] + parts["distance"] + parts["heading"] + parts["control"]
        parts["success"] = parts["reached"]
        if cfg.task == "waypoint":
            bonus, self._finished, self._goal_index = advance_course(
                parts["reached"], self._finished, self._goal_index, self._goals.shape[1]
            )
            reward = reward + cfg.weights.reach_bonus * bonus
            parts["success"] = self._finished.copy()
        reward = reward - cfg.weights.crash * crashed
        terminated = crashed.copy()
        limit = self.max_episode_steps
        truncated = (self._steps >= limit) if limit is not None else np.zeros(n, dtype=bool)
        if resetting.size:
            noise[resetting] = self._reset_rows(resetting)
            reward[resetting] = 0.0
            terminated[resetting] = truncated[resetting] = crashed[resetting] = False
        obs = self._observe(np.arange(n), noise)
        stepped = ~self._autoreset
        done = terminated | truncated
        if self.autoreset_mode == AutoresetMode.SAME_STEP and done.any():
            final = self._info(parts, crashed, stepped)
            resetting = np.flatnonzero(done)
            info = self._reset_within_step(obs, final, resetting, parts, crashed)
        else:
            self._autoreset = done
            info = self._info(parts, crashed, stepped)
        if self.render_mode is not None:
            self._record_trail(resetting)
        return obs, reward, terminated, truncated, info

    def render(self) -> tuple[NDArray[np.uint8], ...] | None:
        """One ``rgb_array`` frame per blimp, as the ``"sync"`` vector env returns.

        Returns
        -------
        frames
            ``N`` (H, W, 3) uint8 images drawn by :func:`~gpbf_env.render.render_scene`,
            or None when ``render_mode`` is None.
        """
        if self.render_mode != "rgb_array":
            return None
        from gpbf_env.render import render_scene

        trail = np.stack(self._trail) if self._trail else np.zeros((0, self.num_envs, 3))
        goals = self._goals[np.arange(self.num_envs), self._goal_index]
        frames = []
        for i in range(self.num_envs):  # one image per blimp
            obs = None if self._last_obs is None else {k: v[i] for k, v in self._last_obs.items()}
            start = self._trail_start[i]
            frames.append(render_scene(self.config, self._state[:, i], obs, trail[start:, i], goals[i]))
        return tuple(frames)

    # -- helpers -----------------------------------------------------------------------
    def _reset_within_step(
        self,
        obs: dict[str, NDArray[Any]],
        final: dict[str, NDArray[Any]],
        rows: NDArray[np.int64],
        parts: dict[str, NDArray[Any]],
        crashed: NDArray[np.bool_],
    ) -> dict[str, Any]:
        """Same-step autoreset of the ended blimps ``rows``: ``obs`` is updated in place to
        their first observation; returns the step's info with ``final_obs``/``final_info``."""
        n = self.num_envs
        ended = np.zeros(n, dtype=bool)
        ended[rows] = True
        final_obs = np.full(n, None, dtype=object)
        for i in rows:  # Gymnasium's layout: one unbatched observation per ended blimp
            final_obs[i] = {key: value[i].copy() for key, value in obs.items()}
        fresh = self._observe(rows, self._reset_rows(rows))
        for key, value in fresh.items():
            obs[key][rows] = value
        info = self._info(parts, crashed, ~ended)
        info["final_obs"], info["_final_obs"] = final_obs, ended.copy()
        info["final_info"], info["_final_info"] = _masked(final, ended), ended.copy()
        return info

    def _rebuild_coeffs(self) -> None:
        cfg = self.config
        self._coeffs = make_coeffs(self._params, cfg.dt, cfg.substeps, cfg.strength)
        self._lag = np.array([camera_lag(cfg, p) for p in self._params]).T
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
            self._aux[i] = rng.spawn(1)[0]
            noise[j] = rng.standard_normal(cfg.noise_size - 3)
        if changed:
            self._rebuild_coeffs()
        self._track.reset_rows(rows, self._state[:, rows].T)
        self._motors[:, rows] = 0.0
        self._steps[rows] = 0
        self._goal_index[rows] = 0
        self._finished[rows] = False
        return noise

    def _record_trail(self, resetting: NDArray[np.int64]) -> None:
        """Append the positions to the render trails; blimps ``resetting`` start anew."""
        self._trail.append(self._state[:3].T.copy())
        self._trail_start[resetting] = len(self._trail) - 1
        drop = int(self._trail_start.min())
        if drop:  # no blimp's episode reaches back this far
            del self._trail[:drop]
            self._trail_start -= drop

    def _advance_wind(self, rows: NDArray[np.int64], z: NDArray[np.float64]) -> None:
        a, s = self._gust_a[rows], self._gust_s[rows]
        self._wind[:, rows] = a * self._wind[:, rows] + s * z.T

    def _observe(self, rows: NDArray[np.int64], noise: NDArray[np.float64]) -> dict[str, Any]:
        """Observations ``(len(rows), ...)`` of blimps ``rows``; ``noise`` is their camera noise."""
        aux = np.zeros((self.num_envs, AUX_DRAWS))
        aux[rows] = np.stack([self._aux[i].standard_normal(AUX_DRAWS) for i in rows])  # per-blimp streams
        self._mocap[rows] = measure(self._track, aux)[rows]
        frames = self.config.frame_schedule(self._steps[rows])
        pose = self._state.T[rows]
        latency, jitter = self._lag
        if self.config.strength > 0 and frames.any():  # frames show where blimps were at exposure
            lag = np.maximum(latency + jitter * aux[:, -1], 0.0)
            pose = self._track.at(lag[None, :])[0][rows]
        ell, valid = observe(self.config, pose, frames, noise, [self._rngs[i] for i in rows])
        if self.render_mode is not None:
            if self._last_obs is None or rows.size == self.num_envs:
                self._last_obs = {"ellipses": ell.copy(), "valid": valid.copy()}
            else:
                self._last_obs["ellipses"][rows], self._last_obs["valid"][rows] = ell, valid
        return {"ellipses": ell, "valid": valid}

    def _info(
        self,
        parts: dict[str, NDArray[Any]] | None,
        crashed: NDArray[np.bool_] | None = None,
        stepped: NDArray[np.bool_] | None = None,
    ) -> dict[str, NDArray[Any]]:
        """The batched info, laid out as Gymnasium's ``VectorEnv._add_info`` lays it out.

        Parameters
        ----------
        parts
            Reward components of :func:`~gpbf_env.tasks.task_reward` (None on ``reset``).
        crashed: (N,)
            Blimps that crashed this step.
        stepped: (N,)
            Blimps that stepped (the others were autoreset and have no step-only keys).

        Returns
        -------
        info
            Every key with its ``"_key"`` mask; a step-only key is zero where masked off
            and absent when no blimp stepped.
        """
        n = self.num_envs
        values: dict[str, NDArray[Any]] = {
            "state": self._state.T.copy(),
            "t": self._steps * self.config.dt,
            "goal": self._goals[np.arange(n), self._goal_index].copy(),
            "waypoint_index": self._goal_index.copy(),
            "motors": self._motors.T.copy(),
            "mocap": self._mocap.copy(),
        }
        info: dict[str, NDArray[Any]] = {}
        for key, value in values.items():
            info[key], info[f"_{key}"] = value, np.ones(n, dtype=bool)
        if parts is None or stepped is None or crashed is None or not stepped.any():
            return info
        step_only = {
            "reward_alive": parts["alive"],
            "reward_distance": parts["distance"],
            "reward_heading": parts["heading"],
            "reward_control": parts["control"],
            "distance_m": parts["distance_m"],
            "success": parts["success"],
            "crashed": crashed,
        }
        for key, value in step_only.items():
            dtype = np.bool_ if key in ("success", "crashed") else np.float64
            info[key] = np.where(stepped, np.asarray(value, dtype=dtype), dtype(0))
            info[f"_{key}"] = stepped.copy()
        return info


def _masked(info: dict[str, NDArray[Any]], rows: NDArray[np.bool_]) -> dict[str, NDArray[Any]]:
    """``info`` keeping only blimps ``rows`` (zero and masked off elsewhere), as Gymnasium
    batches the single infos of some of the envs."""
    out: dict[str, NDArray[Any]] = {}
    for key, value in info.items():
        if key.startswith("_"):
            continue
        keep = rows & info[f"_{key}"]
        shape = (-1,) + (1,) * (value.ndim - 1)
        out[key], out[f"_{key}"] = np.where(keep.reshape(shape), value, value.dtype.type(0)), keep
    return out
