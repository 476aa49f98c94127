"""Scripted pilots that fly the blimp from its (true or estimated) state."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["WaypointPilot"]


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


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
    """

    k_yaw: float = 2.0
    k_yaw_rate: float = 1.0
    k_dist: float = 0.6
    k_speed: float = 1.0
    k_alt: float = 1.5
    k_climb: float = 2.5

    def act(self, state: NDArray[np.float64], target: NDArray[np.float64]) -> NDArray[np.float32]:
        """Normalised action ``(3,)`` that steers ``state (12,)`` towards ``target (3,)``."""
        dx, dy, dz = target[:3] - state[:3]
        yaw, u, r = state[5], state[6], state[11]
        yaw_err = _wrap(yaw - math.atan2(dy, dx))
        dist = math.hypot(dx, dy)
        climb = -math.sin(state[4]) * u + state[8]  # approx. world vertical speed
        fwd = float(
            np.clip(
                self.k_dist * dist * max(math.cos(yaw_err), 0.0) ** 4 - self.k_speed * u, -0.6, 1.0
            )
        )
        up = float(np.clip(self.k_alt * dz - self.k_climb * climb, -1.0, 1.0))
        mag = min(math.hypot(fwd, up), 1.0)
        if fwd >= 0:
            thrust, angle = mag, math.atan2(up, fwd)
        else:
            thrust, angle = -mag, math.atan2(-up, -fwd)
        tail = float(np.clip(self.k_yaw * yaw_err + self.k_yaw_rate * r, -1.0, 1.0))
        return np.array([thrust, angle / (math.pi / 2), tail], dtype=np.float32)
