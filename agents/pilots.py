"""Pilots that fly the blimp from its (true or estimated) state.

* :class:`WaypointPilot` - a PD pilot: nose to the target, fly there, hold its altitude.
* :class:`ScriptedPilot` - flies like the paper's human pilot (Sect. 6.2): a seeded random
  sequence of manoeuvres (slow and fast forward flight, turns both ways in place and in
  flight, climbs and descents, stops with reverse thrust, hovering), exercising the full
  range of the main fans, and steering back to the room's centre near the walls.
* :class:`RandomExcitationPilot` - random actions held for random durations (system
  identification style), with the same wall avoidance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from estimator_service.angles import wrap_angle

__all__ = ["PILOTS", "RandomExcitationPilot", "ScriptedPilot", "WaypointPilot", "make_pilot"]

Action = NDArray[np.float32]
ROOM = (10.0, 6.0, 4.0)
MARGIN = 1.6  # metres from a wall at which pilots turn back to the centre


@dataclass(frozen=True)
class WaypointPilot:
    """A PD pilot: point the nose at the target, fly towards it, hold its altitude.

    Attributes
    ----------
    k_yaw, k_yaw_rate
        Tail-fan gains on yaw error (rad) and yaw rate (rad/s).
    k_dist, k_speed
        Forward force per metre of distance and per m/s of forward speed.
    k_alt, k_climb
        Vertical force per metre of altitude error and per m/s of climb rate.
    max_forward
        Cap on the normalised forward force (speed of the approach).
    """

    k_yaw: float = 2.0
    k_yaw_rate: float = 1.0
    k_dist: float = 0.6
    k_speed: float = 1.0
    k_alt: float = 1.5
    k_climb: float = 2.5
    max_forward: float = 1.0

    def act(self, state: NDArray[np.float64], target: NDArray[np.float64]) -> Action:
        """Normalised action ``(3,)`` that steers ``state (12,)`` towards ``target (3,)``."""
        dx, dy, dz = target[:3] - state[:3]
        yaw_err = float(wrap_angle(state[5] - math.atan2(dy, dx)))
        fwd = self.k_dist * math.hypot(dx, dy) * max(math.cos(yaw_err), 0.0) ** 4
        return self.compose(state, fwd, dz, yaw_err)

    def compose(self, state: NDArray[np.float64], fwd: float, dz: float, yaw_err: float) -> Action:
        """Action from a desired forward force, altitude error and yaw error."""
        u, r = state[6], state[11]
        climb = -math.sin(state[4]) * u + state[8]  # approx. world vertical speed
        fwd = float(np.clip(fwd - self.k_speed * u, -0.6, self.max_forward))
        up = float(np.clip(self.k_alt * dz - self.k_climb * climb, -1.0, 1.0))
        mag = min(math.hypot(fwd, up), 1.0)
        if fwd >= 0:
            thrust, angle = mag, math.atan2(up, fwd)
        else:
            thrust, angle = -mag, math.atan2(-up, -fwd)
        tail = float(np.clip(self.k_yaw * yaw_err + self.k_yaw_rate * r, -1.0, 1.0))
        return np.array([thrust, angle / (math.pi / 2), tail], dtype=np.float32)


def _near_wall(state: NDArray[np.float64], margin: float = MARGIN) -> bool:
    x, y, z = state[:3]
    return x < margin or x > ROOM[0] - margin or y < margin or y > ROOM[1] - margin or z < 0.9 or z > 3.1


MANOEUVRES = (
    "cruise_slow",
    "cruise_fast",
    "turn_left",
    "turn_right",
    "climb",
    "descend",
    "stop",
    "hover",
)


@dataclass
class ScriptedPilot:
    """A seeded manoeuvre sequence like the paper's human pilot.

    Each manoeuvre lasts 2-8 s. Near a wall, floor or ceiling the pilot flies back towards
    the room's centre first. Call :meth:`reset` with a generator at the start of a flight.
    """

    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    dt: float = 0.25
    name: str = "scripted"
    _pd: WaypointPilot = field(default_factory=WaypointPilot)
    _kind: str = "hover"
    _left: int = 0
    _target: NDArray[np.float64] = field(default_factory=lambda: np.array([5.0, 3.0, 2.0]))
    _level: float = 0.5

    def reset(self, rng: np.random.Generator) -> None:
        self.rng, self._left = rng, 0

    def _next(self, state: NDArray[np.float64]) -> None:
        self._kind = str(self.rng.choice(MANOEUVRES))
        self._left = int(self.rng.integers(round(2 / self.dt), round(8 / self.dt)))
        self._level = float(self.rng.uniform(0.3, 1.0))
        lo, hi = np.array([2.2, 1.8, 1.2]), np.array([ROOM[0] - 2.2, ROOM[1] - 1.8, ROOM[2] - 1.2])
        self._target = self.rng.uniform(lo, hi)
        if self._kind in ("climb", "descend"):
            self._target = state[:3] + np.array([0, 0, 1.0 if self._kind == "climb" else -1.0])
            self._target[2] = float(np.clip(self._target[2], 1.1, ROOM[2] - 1.1))

    def act(self, state: NDArray[np.float64]) -> Action:
        """Normalised action ``(3,)`` for the true (or estimated) state ``(12,)``."""
        if _near_wall(state) and self._kind not in ("cruise_slow", "cruise_fast"):
            self._kind, self._left = "cruise_slow", round(4 / self.dt)
            self._target = np.array([ROOM[0] / 2, ROOM[1] / 2, 2.0])
        if self._left <= 0:
            self._next(state)
        self._left -= 1
        pd, k = self._pd, self._kind
        if k in ("cruise_slow", "cruise_fast"):
            fast = 1.0 if k == "cruise_fast" else 0.45
            pilot = WaypointPilot(max_forward=fast * self._level + 0.2)
            return pilot.act(state, self._target)
        if k in ("turn_left", "turn_right"):
            sign = 1.0 if k == "turn_right" else -1.0  # positive tail yaws right
            a = pd.compose(state, 0.3 * self._level, self._target[2] - state[2], 0.0)
            a[2] = sign * self._level
            return a
        if k in ("climb", "descend"):
            return pd.compose(state, 0.2, self._target[2] - state[2], 0.0)
        if k == "stop":
            return pd.compose(state, -0.6 * self._level, 0.0, 0.0)
        return pd.compose(state, 0.0, self._target[2] - state[2], 0.0)


@dataclass
class RandomExcitationPilot:
    """Uniform random actions held for 0.5-3 s; flies to the centre near walls."""

    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    dt: float = 0.25
    name: str = "random"
    _action: Action = field(default_factory=lambda: np.zeros(3, dtype=np.float32))
    _left: int = 0

    def reset(self, rng: np.random.Generator) -> None:
        self.rng, self._left = rng, 0

    def act(self, state: NDArray[np.float64]) -> Action:
        if _near_wall(state, MARGIN - 0.3):
            return WaypointPilot(max_forward=0.6).act(state, np.array([ROOM[0] / 2, ROOM[1] / 2, 2.0]))
        if self._left <= 0:
            self._action = self.rng.uniform(-1, 1, 3).astype(np.float32)
            self._left = int(self.rng.integers(2, 12))
        self._left -= 1
        return self._action.copy()


PILOTS = {"scripted": ScriptedPilot, "random": RandomExcitationPilot}


def make_pilot(name: str, rng: np.random.Generator) -> ScriptedPilot | RandomExcitationPilot:
    """A pilot by name (``scripted`` or ``random``) using ``rng``."""
    if name not in PILOTS:
        raise ValueError(f"pilot must be one of {sorted(PILOTS)}, got {name!r}")
    return PILOTS[name](rng=rng)
