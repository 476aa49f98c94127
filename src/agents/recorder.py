"""Flight recordings: fly a pilot (or an agent) and store ground truth, controls and ellipses.

On-disk format: a single NumPy ``.npz`` (``allow_pickle=False``), chosen over parquet
because every field is a dense float array (``state (N, 12)``, ``ellipses (N, C, 5)``)
that ``.npz`` stores exactly, with no extra dependency and one file per flight. Keys:

=============  ===========  =================================================================
``t``          (N,)         sim time of each row (s)
``state``      (N, 12)      true state (motion capture) at that time
``control``    (N, 3)       normalised action applied from this row to the next (0 on the last)
``ellipses``   (N, C, 5)    camera ellipses observed at this row (0 where not valid)
``valid``      (N, C)       whether camera k delivered an ellipse at this row
``episode``    (N,)         episode index; rows of different episodes are not transitions
``metadata``   ()           JSON: format, version, seed, pilot, dt, env config, cameras
=============  ===========  =================================================================

Files are written to a temporary name and renamed, so a crash never leaves half a file.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import NDArray

import gpbf_env  # noqa: F401  (registers the env)
from agents.pilots import make_pilot
from estimator_service.gp.io import atomic_savez

__all__ = ["FLIGHT_FORMAT_VERSION", "Flight", "collect_flight", "load_flight", "save_flight"]

FLIGHT_FORMAT_VERSION = 1
NO_LIMIT = 10**9  # gym.make(max_episode_steps=None) would mean "the registered default"
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Flight:
    """One recorded flight (see the module docstring for the fields)."""

    t: FloatArray
    state: FloatArray
    control: FloatArray
    ellipses: FloatArray
    valid: NDArray[np.bool_]
    episode: NDArray[np.int64]
    metadata: dict[str, Any]

    def __len__(self) -> int:
        return len(self.t)

    @property
    def n_cameras(self) -> int:
        return self.valid.shape[1]

    def transition_rows(self) -> NDArray[np.intp]:
        """Rows ``k`` whose successor ``k + 1`` belongs to the same episode."""
        return np.flatnonzero(self.episode[:-1] == self.episode[1:])

    def transitions(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``x_k (T, 12)``, ``u_k (T, 3)``, ``x_{k+1} (T, 12)`` within episodes."""
        k = self.transition_rows()
        return self.state[k], self.control[k], self.state[k + 1]

    def select(self, rows: NDArray[np.intp]) -> Flight:
        """The rows ``rows`` (sorted) as a new flight."""
        return Flight(
            self.t[rows],
            self.state[rows],
            self.control[rows],
            self.ellipses[rows],
            self.valid[rows],
            self.episode[rows],
            self.metadata,
        )


def camera_metadata(env: gym.Env) -> list[dict[str, Any]]:
    """Calibration of the env's cameras as JSON-ready dicts."""
    return [
        {
            "name": c.name,
            "position": c.position.tolist(),
            "rotation": c.rotation.tolist(),
            "focal": c.focal,
            "principal_point": list(c.principal_point),
            "size": list(c.size),
            "k1": c.k1,
            "k2": c.k2,
            "rate_hz": c.rate_hz,
            "phase_s": c.phase_s,
        }
        for c in env.unwrapped.config.cameras
    ]


def collect_flight(
    seconds: float,
    *,
    pilot: str = "scripted",
    seed: int = 0,
    env_id: str = "gpbf_env/Blimp-v0",
    env_kwargs: dict[str, Any] | None = None,
    policy: Callable[[dict[str, Any], dict[str, Any]], FloatArray] | None = None,
    progress: Callable[[int], None] | None = None,
) -> Flight:
    """Fly for ``seconds`` of sim time and record; episodes restart after a crash.

    Parameters
    ----------
    pilot
        ``scripted`` or ``random`` (ignored when ``policy`` is given).
    policy
        Optional ``policy(obs, info) -> action`` (raw observation, env info), e.g. a
        trained agent (:class:`agents.rl.AgentPolicy`); it is told of resets by
        ``info["t"] == 0``.
    progress
        Called with the number of steps done after each step.
    """
    env = gym.make(env_id, max_episode_steps=NO_LIMIT, **(env_kwargs or {}))
    rng = np.random.default_rng(seed)
    driver = make_pilot(pilot, rng)
    obs, info = env.reset(seed=seed)
    steps = round(seconds / env.unwrapped.config.dt)
    rows: dict[str, list[Any]] = {k: [] for k in ("t", "state", "control", "ellipses", "valid", "episode")}
    episode = 0
    for k in range(steps + 1):
        action = policy(obs, info) if policy else driver.act(info["state"])
        action = np.zeros(3) if k == steps else np.asarray(action, dtype=np.float64)
        for key, val in (
            ("t", info["t"]),
            ("state", info["state"]),
            ("control", action),
            ("ellipses", obs["ellipses"]),
            ("valid", obs["valid"]),
            ("episode", episode),
        ):
            rows[key].append(val)
        if k == steps:
            break
        obs, _, terminated, truncated, info = env.step(action.astype(np.float32))
        if terminated or truncated:
            episode += 1
            obs, info = env.reset()
        if progress:
            progress(k + 1)
    cfg = env.unwrapped.config
    meta = {
        "format": "gpbf-flight",
        "version": FLIGHT_FORMAT_VERSION,
        "seed": seed,
        "pilot": "agent" if policy else pilot,
        "env_id": env_id,
        "dt": cfg.dt,
        "env_config": {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("params", "weights")},
        "params": cfg.params.to_dict(),
        "cameras": camera_metadata(env),
    }
    env.close()
    return Flight(
        np.asarray(rows["t"], dtype=np.float64),
        np.asarray(rows["state"]),
        np.asarray(rows["control"]),
        np.asarray(rows["ellipses"], dtype=np.float64),
        np.asarray(rows["valid"], dtype=bool),
        np.asarray(rows["episode"], dtype=np.int64),
        meta,
    )


def save_flight(flight: Flight, path: str | os.PathLike[str]) -> Path:
    """Write ``flight`` to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_savez(
        path,
        t=flight.t,
        state=flight.state,
        control=flight.control,
        ellipses=flight.ellipses,
        valid=flight.valid,
        episode=flight.episode,
        metadata=np.array(json.dumps(flight.metadata)),
    )


def load_flight(path: str | os.PathLike[str]) -> Flight:
    """Read a flight; raises ``ValueError`` naming the problem for a malformed file."""
    where = f"flight file {os.fspath(path)!r}"
    try:
        with np.load(path, allow_pickle=False) as d:
            data = {k: d[k] for k in d.files}
    except FileNotFoundError:
        raise
    except Exception as exc:
        raise ValueError(f"{where}: unreadable or truncated ({exc})") from exc
    need = ("t", "state", "control", "ellipses", "valid", "episode", "metadata")
    missing = [k for k in need if k not in data]
    if missing:
        raise ValueError(f"{where}: missing {missing}")
    meta = json.loads(str(data["metadata"]))
    if meta.get("format") != "gpbf-flight" or meta.get("version") != FLIGHT_FORMAT_VERSION:
        raise ValueError(f"{where}: not a version-{FLIGHT_FORMAT_VERSION} gpbf flight")
    n = len(data["t"])
    shapes = {"state": (n, 12), "control": (n, 3)}
    for key, shape in shapes.items():
        if data[key].shape != shape:
            raise ValueError(f"{where}: '{key}' has shape {data[key].shape}, expected {shape}")
    c = data["valid"].shape[1] if data["valid"].ndim == 2 else -1
    if data["ellipses"].shape != (n, c, 5) or data["valid"].shape != (n, c):
        raise ValueError(
            f"{where}: 'ellipses'/'valid' shapes {data['ellipses'].shape}, {data['valid'].shape}"
        )
    return Flight(
        data["t"],
        data["state"],
        data["control"],
        data["ellipses"],
        data["valid"].astype(bool),
        data["episode"].astype(np.int64),
        meta,
    )
