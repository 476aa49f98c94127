"""Flight tasks: goal sampling and dense rewards, vectorised over blimps."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gpbf_env.dynamics import wrap_angle

__all__ = [
    "HOVER_START_RADIUS",
    "TASKS",
    "RewardWeights",
    "advance_course",
    "hover_start",
    "sample_goals",
    "task_reward",
]

TASKS = ("hover", "waypoint")
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the dense rewards.

    Hover pays ``alive - (d + w_h |yaw err| + w_u |a|^2)`` per step. Waypoint pays
    ``alive + w_p (d_prev - d) - w_h |heading err| - w_u |a|^2`` per step: progress
    towards the current waypoint instead of its distance, ``reach_bonus`` per waypoint,
    and the course's last waypoint is then held (yaw error to its yaw) until the time
    limit. The progress term is an undiscounted potential difference (potential ``-w_p d``,
    Ng, Harada & Russell 1999), so it sums to ``w_p (d_0 - d_end)`` per waypoint whatever
    the path and cannot outweigh the alive bonus: flying on always beats crashing. The
    earlier waypoint reward, ``alive - d`` per step with termination at the last
    waypoint, was negative on most of a 1.5-3.5 m leg, so crashing early was optimal and
    the PPO state agent learnt exactly that (return -57.6 against the pilot's -236, no
    waypoint reached; ``docs/results/rl``). Holding instead of terminating removes the
    opposite trap: ending the episode forfeits the alive bonus, which made stopping short
    of the last waypoint pay.

    Attributes
    ----------
    alive
        Paid every step the blimp is still flying. With it, ending an episode early by
        crashing never beats flying on (without it, agents learn to crash quickly).
    heading
        Per radian of heading error.
    control
        Per unit squared normalised action.
    reach_bonus
        Paid once when a waypoint is reached (waypoint task).
    crash
        Paid once on termination (leaving the room, floor or ceiling).
    reach_radius
        Distance (m) at which a waypoint counts as reached, and hover counts as on target.
    progress
        Per metre of progress towards the current waypoint (waypoint task). At the
        pilot's cruise of about 0.4 m/s (0.1 m per 0.25 s step) it pays about as much as
        ``alive``; a 2.5 m leg is worth 2.5 reach bonuses. Fixed before any training.
    """

    alive: float = 1.0
    heading: float = 0.3
    control: float = 0.05
    reach_bonus: float = 10.0
    crash: float = 20.0
    reach_radius: float = 0.5
    progress: float = 10.0


def sample_goals(
    rng: np.random.Generator, room: tuple[float, float, float], task: str, n_waypoints: int = 4
) -> FloatArray:
    """Goals ``(W, 4)``: position (m) and yaw (rad); one row for hover, ``n_waypoints`` else."""
    lx, ly, lz = room
    n = 1 if task == "hover" else n_waypoints
    lo = np.array([2.0, 1.5, 1.2])
    hi = np.array([lx - 2.0, ly - 1.5, lz - 1.5])
    pos = rng.uniform(lo, hi, size=(n, 3))
    yaw = rng.uniform(-math.pi, math.pi, size=(n, 1))
    return np.concatenate([pos, yaw], axis=1)


HOVER_START_RADIUS = 1.0
"""Hover episodes start at most this far (m, per axis) from the goal."""


def hover_start(rng: np.random.Generator, state: FloatArray, goal: FloatArray) -> FloatArray:
    """Move a start ``state (12,)`` next to a hover ``goal (4,)``: station keeping, not travel.

    The position is drawn uniformly within :data:`HOVER_START_RADIUS` of the goal on each
    axis and the yaw within 0.5 rad of the goal yaw; the rest of ``state`` is kept.
    """
    out = np.array(state, dtype=np.float64)
    out[:3] = goal[:3] + rng.uniform(-HOVER_START_RADIUS, HOVER_START_RADIUS, size=3)
    out[5] = float(wrap_angle(np.array(goal[3] + rng.uniform(-0.5, 0.5))))
    return out


def task_reward(
    task: str,
    position: FloatArray,
    yaw: FloatArray,
    goal: FloatArray,
    action: FloatArray,
    weights: RewardWeights,
    previous: FloatArray | None = None,
    holding: NDArray[np.bool_] | None = None,
) -> dict[str, FloatArray]:
    """Reward components for ``N`` blimps (see :class:`RewardWeights`).

    Parameters
    ----------
    task
        ``"hover"`` (hold the goal position and yaw) or ``"waypoint"`` (fly to the goal,
        nose towards it).
    position: (N, 3)
    yaw: (N,)
    goal: (N, 4)
        Current goal (position, yaw) of each blimp.
    action: (N, 3)
        Normalised action.
    previous: (N, 3)
        Position one step earlier (waypoint task: the progress term; required there).
    holding: (N,)
        Waypoint task: the course is complete and its last waypoint is held (yaw error to
        the goal yaw, as in hover). None: no blimp is holding.

    Returns
    -------
    dict with ``alive`` (the per-step bonus), ``distance`` (hover: minus the distance;
    waypoint: the progress), ``heading``, ``control`` (the negative dense terms), all
    (N,), ``distance_m`` and ``reached`` (bool, within ``reach_radius``).
    """
    delta = goal[:, :3] - position
    dist = np.sqrt(np.sum(delta * delta, axis=1))
    if task == "hover":
        target_yaw = goal[:, 3]
        distance = -dist
    else:
        if previous is None:
            raise ValueError("task_reward: the waypoint task needs the previous positions")
        before = np.sqrt(np.sum((goal[:, :3] - previous) ** 2, axis=1))
        distance = weights.progress * (before - dist)
        target_yaw = np.arctan2(delta[:, 1], delta[:, 0])
        if holding is not None:
            target_yaw = np.where(holding, goal[:, 3], target_yaw)
    heading_err = np.abs(wrap_angle(yaw - target_yaw))
    return {
        "alive": np.full(dist.shape, weights.alive),
        "distance": distance,
        "heading": -weights.heading * heading_err,
        "control": -weights.control * np.sum(action * action, axis=1),
        "distance_m": dist,
        "reached": dist < weights.reach_radius,
    }


def advance_course(
    reached: NDArray[np.bool_], finished: NDArray[np.bool_], goal_index: NDArray[np.int64], n_goals: int
) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.int64]]:
    """The waypoint course after a step, for ``N`` blimps.

    Parameters
    ----------
    reached: (N,)
        Within the reach radius of the current waypoint this step.
    finished: (N,)
        Every waypoint already reached (the last one is being held).
    goal_index: (N,)
        Index of the current waypoint.
    n_goals
        Waypoints in the course.

    Returns
    -------
    bonus: (N,)
        A waypoint was reached for the first time (pays ``reach_bonus``).
    finished, goal_index: (N,)
        The course after the step (the index stays at the last waypoint).
    """
    bonus = reached & ~finished
    finished = finished | (bonus & (goal_index + 1 >= n_goals))
    return bonus, finished, np.minimum(goal_index + bonus, n_goals - 1)
