"""The single-blimp Gymnasium environment."""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from gpbf_env.core import WorldConfig, camera_lag, check_action, initial_state, observe
from gpbf_env.dynamics import Coeffs, make_coeffs, rk4_step
from gpbf_env.mocap import AUX_DRAWS, PoseTrack, measure
from gpbf_env.params import BlimpParams
from gpbf_env.tasks import advance_course, hover_start, sample_goals, task_reward

__all__ = ["BlimpEnv"]

ObsType = dict[str, NDArray[Any]]


class BlimpEnv(gym.Env[ObsType, NDArray[np.float32]]):
    """A micro-blimp in a lab room, seen by wall cameras that report image ellipses.

    ## Description
    A 1.7 m helium blimp (Ko & Fox 2009, Sect. 6.1) flies in a 10 x 6 x 4 m room. Its
    "true" dynamics are a 6-DOF rigid body with added mass, near-neutral buoyancy, a
    centre of gravity below the centre of buoyancy (self-righting), linear and quadratic
    drag, body and fin lift, lagged and saturated fans, and seeded wind gusts, integrated
    with fixed-step RK4. Wall cameras with barrel distortion see the envelope and report
    the ellipse fitted to its outline, each at 1 Hz and staggered. In the default
    ``reality="lab"`` world the blimp also has what the paper's parametric model leaves
    out (nonlinear and inflow-dependent fan thrust, fan imbalance, slipstream on the
    fin, the centre of gravity's inertial coupling, offsets, spin-up and servo slew) and
    the cameras have latency (:mod:`gpbf_env.reality`); ``reality="clean"`` is the
    textbook world.

    ## Action Space
    ``Box(-1, 1, (3,), float32)``: main-fan thrust (scaled to +-``max_main_thrust`` N,
    negative is reverse), main-fan vector angle (scaled to +-``max_vector_angle`` rad,
    positive tilts the thrust up), tail-fan thrust (+-``max_tail_thrust`` N, positive pushes
    the tail left, i.e. yaws right). Out-of-range actions are clipped to [-1, 1]; a wrong
    shape or a NaN/Inf raises ``ValueError``.

    ## Observation Space
    ``Dict(ellipses=Box((C, 5), float32), valid=MultiBinary(C))`` for ``C`` cameras: per
    camera ``(cx, cy, width, height, angle)`` in pixels and radians (major axis angle in
    ``(-pi/2, pi/2]``) and whether a frame arrived this step. Rows without a frame
    (no frame due, out of view, behind the camera) are zero with ``valid = 0``;
    :meth:`~gpbf_env.core.WorldConfig.frame_schedule` gives the cameras due at each step.

    ## Info
    ``reset`` and ``step`` both return ``info["state"]``, the true 12-D state ``(x, y, z,
    roll, pitch, yaw, u, v, w, p, q, r)`` (world m, rad, body m/s, body rad/s; exact),
    ``info["t"]``, the sim time (s), ``info["goal"]``, the
    current goal ``(x, y, z, yaw)``, ``info["waypoint_index"]``, its index among the
    episode's goals, ``info["motors"]``, the lagged fan outputs (N, rad, N), and
    ``info["mocap"]``, the state as the paper's 120 Hz motion capture measured it
    (:mod:`gpbf_env.mocap`: pose with 0.5 mm / 0.05 deg noise, velocities from the slope
    of a 100 ms window, so lagging about 46 ms). ``step``
    adds the reward components ``info["reward_alive" | "reward_distance" |
    "reward_heading" | "reward_control"]``, ``info["distance_m"]``, the distance to the goal
    (m), ``info["success"]`` (hover: within ``reach_radius`` of the goal; waypoint: every
    waypoint of the course reached), and
    ``info["crashed"]``. :class:`~gpbf_env.vector_env.BlimpVectorEnv` returns the same
    keys batched as the ``"sync"`` vector env does, with their ``"_key"`` masks.

    ## Rewards
    Dense, per step (components in the ``reward_*`` info entries; see
    :class:`~gpbf_env.tasks.RewardWeights`). Hover: ``1 - distance - 0.3 |yaw error| -
    0.05 |a|^2`` to the goal. Waypoint: ``1 + 10 (progress towards the current waypoint,
    m) - 0.3 |heading error to its direction| - 0.05 |a|^2``, +10 on reaching each
    waypoint; once the last is reached the blimp holds it (yaw error to its yaw) until the
    time limit, so flying on always beats crashing. -20 on a crash.

    ## Starting State
    At rest, motors off, roll and pitch ~N(0, 0.05) rad; goals drawn uniformly in the room's
    centre region. Waypoint: uniform position in the centre region, yaw uniform. Hover
    (station keeping): within 1 m of the goal on each axis, yaw within 0.5 rad of its yaw.
    ``reset(options=...)`` accepts ``state`` (12 floats), ``goal`` (x, y, z[, yaw]),
    ``randomize`` (a scale) and ``params`` (a :class:`BlimpParams`).

    ## Episode End
    Termination when the blimp leaves the room or its envelope touches the floor or the
    ceiling. Truncation by the
    registered ``max_episode_steps`` (240 steps = 60 s).

    ## Arguments
    ``task`` ("hover" | "waypoint"), ``dt``, ``substeps``, ``camera_rate_hz``,
    ``n_cameras``, ``camera_knock_deg``, ``pixel_noise``, ``camera_mode`` (``"closed_form"`` or the slow
    ``"rendered"``), ``image_noise``, ``room``, ``params``, ``randomize``, ``reality``
    (``"lab"``, the default, ``"clean"`` or ``"drafty"``) and ``reality_strength`` (all of
    :class:`~gpbf_env.core.WorldConfig`), and ``render_mode`` (``"rgb_array"`` or None).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, render_mode: str | None = None, **config: Any) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.render_mode = render_mode
        self.config = WorldConfig(**config)
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.config.dt)}
        self.action_space = spaces.Box(-1.0, 1.0, shape=(3,), dtype=np.float32)
        self.observation_space = self.config.observation_space()
        self._params: BlimpParams = self.config.params
        self._coeffs: Coeffs = self._make_coeffs(self._params)
        self._track = PoseTrack(1, self.config.substeps, self.config.dt, self.config.track_depth)
        self._aux = np.random.default_rng(0)  # replaced at reset
        self._lag = camera_lag(self.config, self._params)
        self._mocap = np.zeros(12)
        self._state, self._motors, self._wind = np.zeros(12), np.zeros(3), np.zeros(3)
        self._step = 0
        self._goals = np.zeros((1, 4))
        self._goal_index = 0
        self._last_obs: ObsType | None = None
        self._trail: list[NDArray[np.float64]] = []

    # -- gymnasium API -----------------------------------------------------------------
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[ObsType, dict[str, Any]]:
        super().reset(seed=seed)
        options = dict(options or {})
        cfg = self.config
        rng = self.np_random
        if "params" in options:
            base = options["params"]
            if not isinstance(base, BlimpParams):
                raise ValueError("options['params'] must be a BlimpParams")
            cfg = dataclasses.replace(cfg, params=base)
        if "randomize" in options:
            cfg = dataclasses.replace(cfg, randomize=float(options["randomize"]))
        params = cfg.draw_params(rng)
        state = initial_state(rng, cfg.room)
        goals = sample_goals(rng, cfg.room, cfg.task)
        if cfg.task == "hover":
            state = hover_start(rng, state, goals[0])
        if "state" in options:
            state = _vector_option(options["state"], 12, "state")
        if "goal" in options:
            g = _vector_option(options["goal"], None, "goal")
            goals = np.concatenate([g, [0.0]])[None, :4] if g.size == 3 else g.reshape(-1, 4)
        if params is not self._params:
            self._coeffs = self._make_coeffs(params)
            self._params = params
            self._lag = camera_lag(cfg, params)
        self._state, self._motors = np.array(state, dtype=np.float64), np.zeros(3)
        self._wind = rng.normal(0.0, params.gust_std, size=3)
        self._step, self._goals, self._goal_index, self._finished = 0, goals, 0, False
        self._trail = [state[:3].copy()]
        self._aux = rng.spawn(1)[0]
        self._track.reset_rows(np.array([0]), state[None, :])
        obs = self._observe(rng.standard_normal(self.config.noise_size - 3))
        return obs, self._info(None)

    def step(self, action: NDArray[np.float32]) -> tuple[ObsType, float, bool, bool, dict[str, Any]]:
        a = check_action(action)
        cfg = self.config
        cmd = cfg.map_action(a[None, :], self._params)[0]
        previous = self._state[:3].copy()
        state, motors, knots = rk4_step(self._state, self._motors, cmd, self._wind, self._coeffs)
        self._state, self._motors = state[:, 0], motors[:, 0]
        self._track.push(knots)
        noise = self.np_random.standard_normal(cfg.noise_size)
        self._advance_wind(noise[:3])
        self._step += 1
        state = np.array(self._state)
        self._trail.append(state[:3].copy())
        parts = task_reward(
            cfg.task, state[None, :3], state[None, 5], self._goals[None, self._goal_index],
            a[None, :], cfg.weights, previous[None, :], np.array([self._finished]),
        )  # fmt: skip
        crashed = bool(cfg.out_of_bounds(state[None, :3])[0])
        reward = float(parts["alive"][0] + parts["distance"][0] + parts["heading"][0] + parts["control"][0])
        success = bool(parts["reached"][0])
        if cfg.task == "waypoint":
            bonus, finished, index = advance_course(
                parts["reached"], np.array([self._finished]), np.array([self._goal_index]), len(self._goals)
            )
            reward += cfg.weights.reach_bonus * float(bonus[0])
            self._finished, self._goal_index = bool(finished[0]), int(index[0])
            success = self._finished
        if crashed:
            reward -= cfg.weights.crash
        obs = self._observe(noise[3:])
        return obs, reward, crashed, False, self._info(parts, crashed, success)

    def render(self) -> NDArray[np.uint8] | None:
        if self.render_mode != "rgb_array":
            return None
        from gpbf_env.render import render_scene

        return render_scene(
            self.config, np.array(self._state), self._last_obs, np.array(self._trail),
            self._goals[self._goal_index],
        )  # fmt: skip

    # -- helpers -----------------------------------------------------------------------
    @property
    def state(self) -> NDArray[np.float64]:
        """The true 12-D state (a copy)."""
        return np.array(self._state)

    @property
    def params(self) -> BlimpParams:
        """The physical parameters of the current episode."""
        return self._params

    def _advance_wind(self, z: NDArray[np.float64]) -> None:
        p = self._params
        a = math.exp(-self.config.dt / p.gust_tau)
        s = p.gust_std * math.sqrt(1.0 - a * a)
        self._wind = a * self._wind + s * z

    def _make_coeffs(self, params: BlimpParams) -> Coeffs:
        cfg = self.config
        return make_coeffs([params], cfg.dt, cfg.substeps, cfg.strength)

    def _observe(self, noise: NDArray[np.float64]) -> ObsType:
        aux = self._aux.standard_normal(AUX_DRAWS)
        self._mocap = measure(self._track, aux[None, :])[0]
        frames = self.config.frame_schedule(np.array([self._step]))
        pose = np.array([self._state])
        latency, jitter = self._lag
        if self.config.strength > 0 and frames.any():  # the frame shows the blimp where it was at exposure
            lag = np.array([[max(latency + jitter * aux[-1], 0.0)]])
            pose = self._track.at(lag)[0]
        ell, valid = observe(self.config, pose, frames, noise[None, :], [self.np_random])
        self._last_obs = {"ellipses": ell[0], "valid": valid[0]}
        return {"ellipses": ell[0].copy(), "valid": valid[0].copy()}

    def _info(
        self, parts: dict[str, Any] | None, crashed: bool = False, success: bool = False
    ) -> dict[str, Any]:
        info: dict[str, Any] = {
            "state": np.array(self._state),
            "t": self._step * self.config.dt,
            "goal": self._goals[self._goal_index].copy(),
            "waypoint_index": self._goal_index,
            "motors": np.array(self._motors),
            "mocap": self._mocap.copy(),
        }
        if parts is not None:
            info.update(
                reward_alive=float(parts["alive"][0]),
                reward_distance=float(parts["distance"][0]),
                reward_heading=float(parts["heading"][0]),
                reward_control=float(parts["control"][0]),
                distance_m=float(parts["distance_m"][0]),
                success=success,
                crashed=crashed,
            )
        return info


def _vector_option(value: object, size: int | None, name: str) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64).ravel()
    if size is not None and arr.size != size:
        raise ValueError(f"options['{name}'] must have {size} values, got {arr.size}")
    if size is None and arr.size not in (3, 4) and arr.size % 4 != 0:
        raise ValueError(f"options['{name}'] must be (x, y, z[, yaw]) rows, got {arr.size} values")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"options['{name}'] must be finite")
    return arr
