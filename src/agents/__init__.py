"""agents: pilots and policies that fly the blimp, belief wrappers, and RL training."""

from agents.pilots import WaypointPilot

__all__ = ["WaypointPilot"]
