"""Gymnasium wrappers that hand an agent the filtered belief instead of the true state.

One argument selects the observation variant:

* ``state`` - the true state (the upper bound a perfect estimator would give);
* ``belief`` - the GP filter's belief (mean and per-dimension log standard deviation);
* ``belief-param`` - the same from the parametric filter;
* ``ellipses`` - the raw camera ellipses, valid flags and the last action (the naive baseline).

Every variant also carries the task's goal (relative to the believed position for the
state/belief variants, in its heading frame; absolute for ``ellipses``). Features are scaled to order one and
returned as a fixed ``Box(-10, 10, float32)``. Two back ends run the filter: ``inprocess`` (fast, for
training) and ``service`` (the zenoh estimator service through the bridge, lock-step).
"""

from __future__ import annotations

import uuid
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from numpy.typing import NDArray

from agents.rl.registry import episode_success
from agents.sim import env_frames, env_readings, env_system
from estimator_service.factory import build_filter
from estimator_service.filters import GaussianBelief
from estimator_service.service.limits import Limits, gated_step

GATE_P = Limits().gate_p  # the in-process back end gates as the service does: the same beliefs

__all__ = ["INIT_STD", "VARIANTS", "BeliefObservation", "belief_features", "make_belief_env"]

VARIANTS = ("state", "belief", "belief-param", "ellipses")
INIT_STD = np.repeat([0.05, 0.035, 0.05, 0.035], 3)  # mocap-initialised belief at reset
ROOM_CENTRE = np.array([5.0, 3.0, 2.0])
ROOM_HALF = np.array([5.0, 3.0, 2.0])
FloatArray = NDArray[np.float64]
FEATURE_BOUND = 10.0  # features are scaled to order one; clipped here
ELLIPSE_SCALE = np.array([640.0, 480.0, 200.0, 200.0, 1.0])  # pixels, pixels, pixels, pixels, rad


def _goal_features(mean: FloatArray, goal: FloatArray) -> FloatArray:
    """Goal offset ``(N, 5)`` in the heading frame (forward, left, up; metres, clipped to
    +-3) and sine/cosine of the yaw error, for ``mean (N, 12)`` and ``goal (N, 4)``: what a
    pilot steers by."""
    dx, dy, dz = (goal[:, :3] - mean[:, :3]).T
    c, s = np.cos(mean[:, 5]), np.sin(mean[:, 5])
    rel = np.clip(np.stack([c * dx + s * dy, -s * dx + c * dy, dz], axis=1), -3.0, 3.0)
    dyaw = goal[:, 3] - mean[:, 5]
    return np.concatenate([rel, np.sin(dyaw)[:, None], np.cos(dyaw)[:, None]], axis=1)


def belief_features_many(mean: FloatArray, std: FloatArray | None, goal: FloatArray) -> FloatArray:
    """:func:`belief_features` of ``N`` estimates: ``mean, std: (N, 12)``, ``goal: (N, 4)``
    -> ``(N, 18)`` (``(N, 30)`` with ``std``)."""
    pos = (mean[:, :3] - ROOM_CENTRE) / ROOM_HALF
    yaw = mean[:, 5:6]
    parts = [pos, mean[:, 3:5], np.sin(yaw), np.cos(yaw), mean[:, 6:12], _goal_features(mean, goal)]
    if std is not None:
        parts.append(np.clip(np.log(np.maximum(std, 1e-12)), -8.0, 2.0) / 4.0)
    return np.concatenate(parts, axis=1)


def belief_features(mean: FloatArray, std: FloatArray | None, goal: FloatArray) -> FloatArray:
    """Scaled features of a state estimate: position, roll/pitch, sin/cos yaw, velocities,
    optional log standard deviations (clipped to [-8, 2]) and the goal relative to it."""
    return belief_features_many(mean[None], None if std is None else std[None], goal[None])[0]


def ellipse_features_many(
    ellipses: NDArray[np.float32], valid: NDArray[Any], last_action: FloatArray, goal: FloatArray
) -> FloatArray:
    """The ``ellipses`` variant's features ``(N, 6 C + 7)``: scaled ellipses ``(N, C, 5)``,
    valid flags ``(N, C)``, the last action ``(N, 3)`` and the absolute goal ``(N, 4)``."""
    n = ellipses.shape[0]
    ell = ellipses.astype(np.float64) / ELLIPSE_SCALE
    g = np.concatenate([(goal[:, :3] - ROOM_CENTRE) / ROOM_HALF, goal[:, 3:4] / np.pi], axis=1)
    return np.concatenate([ell.reshape(n, -1), valid.astype(np.float64), last_action, g], axis=1)


def bounded(features: FloatArray) -> NDArray[np.float32]:
    """Features as the observation space holds them: finite, clipped, float32."""
    f = np.nan_to_num(features, nan=0.0, posinf=FEATURE_BOUND, neginf=-FEATURE_BOUND)
    return np.clip(f, -FEATURE_BOUND, FEATURE_BOUND).astype(np.float32)


def feature_size(variant: str, n_cameras: int) -> int:
    """Length of a ``variant``'s feature vector with ``n_cameras`` cameras."""
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    return {"state": 18, "belief": 30, "belief-param": 30, "ellipses": 6 * n_cameras + 3 + 4}[variant]


class BeliefObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Replace a ``gpbf_env`` observation by the chosen variant's features.

    Parameters
    ----------
    env
        A ``gpbf_env`` blimp env.
    variant
        One of :data:`VARIANTS`.
    models
        Model folder (``gpbf train``); needed for ``belief`` and ``belief-param``.
    filter, model
        Filter kind and GP model kind of the ``belief`` variant (``belief-param`` uses the
        parametric models).
    backend
        ``inprocess`` or ``service``.
    client
        The ``service`` back end's way to the service: a zenoh endpoint string (e.g.
        ``"tcp/127.0.0.1:7447"``) or a list of them, for which the wrapper opens (and
        closes) its own zenoh session: picklable, so the env works in SB3's
        ``SubprocVecEnv``; or a live ``zenoh.Session`` shared by the caller (in-process
        vector envs only).
    """

    def __init__(
        self,
        env: gym.Env,
        variant: str = "belief",
        *,
        models: str | None = None,
        filter: str = "ekf",
        model: str = "gp",
        backend: str = "inprocess",
        client: Any = None,
        seed: int = 0,
    ) -> None:
        # a live zenoh session cannot be copied; endpoints are recorded
        endpoints = [client] if isinstance(client, str) else client if isinstance(client, list) else None
        gym.utils.RecordConstructorArgs.__init__(
            self, variant=variant, models=models, filter=filter, model=model, backend=backend, seed=seed,
            client=endpoints,
        )  # fmt: skip
        gym.Wrapper.__init__(self, env)
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        if backend not in ("inprocess", "service"):
            raise ValueError(f"backend must be 'inprocess' or 'service', got {backend!r}")
        self.variant, self.backend = variant, backend
        self.filter_kind, self.model_kind = filter, ("param" if variant == "belief-param" else model)
        uses_filter = variant in ("belief", "belief-param")
        if uses_filter and models is None:
            raise ValueError(f"variant {variant!r} needs a model folder (models=...)")
        self._filter = None
        if uses_filter and backend == "inprocess":
            self._filter = build_filter(filter, self.model_kind, models)
        self._client = None
        if uses_filter and backend == "service":
            from estimator_service.service.client import EstimatorClient

            if client is None:
                raise ValueError("the service back end needs client= (an endpoint or a zenoh session)")
            self._own_session = None
            if endpoints is not None:
                from estimator_service.service.client import open_session

                client = self._own_session = open_session(endpoints)
            self._client = EstimatorClient(client, f"env-{uuid.uuid4().hex[:12]}")
        self._rng = np.random.default_rng(seed)
        self._system = env_system(env)
        size = feature_size(variant, env.observation_space["ellipses"].shape[0])
        self.observation_space = spaces.Box(-FEATURE_BOUND, FEATURE_BOUND, shape=(size,), dtype=np.float32)
        self._belief: Any = None
        self.last_action = np.zeros(3)

    # -- the estimate --------------------------------------------------------------------------------
    def reset_belief(self, info: dict[str, Any]) -> None:
        """Start the estimate at the (motion-capture) state in ``info``."""
        mean, t = info["state"], float(info["t"])
        if self._client is not None:
            self._remote = self._client.reset(
                mean, INIT_STD, t=t, filter=self.filter_kind, model=self.model_kind
            )
        elif self._filter is not None:
            g = GaussianBelief(mean.copy(), np.diag(INIT_STD**2))
            self._belief = self._filter.initial(g, self._rng)

    def advance_belief(self, action: FloatArray, obs: dict[str, Any], info: dict[str, Any]) -> None:
        """One filter step with the applied ``action`` and the raw observation ``obs``."""
        if self._client is not None:
            self._remote = self._client.step(action, env_frames(obs), float(info["t"]))
        elif self._filter is not None:
            z, valid = env_readings(obs, self._system)
            self._belief, _ = gated_step(self._filter, self._belief, action, z, valid, self._rng, GATE_P)

    def belief(self) -> GaussianBelief | None:
        """The current Gaussian belief (``None`` for the state and ellipse variants)."""
        if self._client is not None:
            return GaussianBelief(self._remote["mean"], self._remote["cov"])
        if self._filter is None:
            return None
        return self._filter.gaussian(self._belief)

    def features(self, obs: dict[str, Any], info: dict[str, Any]) -> NDArray[np.float32]:
        """The variant's feature vector for a raw observation and its ``info``."""
        goal = np.asarray(info["goal"], dtype=np.float64)
        if self.variant == "state":
            f = belief_features(info["state"], None, goal)
        elif self.variant == "ellipses":
            ell, valid = obs["ellipses"][None], obs["valid"][None]
            f = ellipse_features_many(ell, valid, self.last_action[None], goal[None])[0]
        else:
            b = self.belief()
            f = belief_features(b.mean, np.sqrt(np.diag(b.cov)), goal)
        return bounded(f)

    # -- gymnasium API -------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        obs, info = self.env.reset(seed=seed, options=options)
        self.last_action = np.zeros(3)
        self.reset_belief(info)
        return self.features(obs, info), info

    def step(self, action):
        a = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        obs, reward, terminated, truncated, info = self.env.step(np.asarray(action, dtype=np.float32))
        self.advance_belief(a, obs, info)
        self.last_action = a
        b = self.belief()
        if b is not None:
            info = {**info, "belief_mean": b.mean, "belief_std": np.sqrt(np.diag(b.cov))}
        if terminated or truncated:  # SB3's EvalCallback and Monitor read it
            info = {**info, "is_success": episode_success(info)}
        return self.features(obs, info), reward, terminated, truncated, info

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            if self._own_session is not None:
                self._own_session.close()
            self._client = None
        super().close()


def make_belief_env(
    variant: str,
    *,
    env_id: str = "gpbf_env/Blimp-v0",
    models: str | None = None,
    filter: str = "ekf",
    model: str = "gp",
    backend: str = "inprocess",
    client: Any = None,
    seed: int = 0,
    **env_kwargs: Any,
) -> BeliefObservation:
    """``gymnasium.make(env_id)`` wrapped in :class:`BeliefObservation`."""
    import gpbf_env  # noqa: F401  (registers the env)

    env = gym.make(env_id, **env_kwargs)
    return BeliefObservation(
        env, variant, models=models, filter=filter, model=model, backend=backend, client=client, seed=seed
    )
