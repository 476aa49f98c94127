"""``make demo``: fly the blimp with a scripted pilot and plot what the cameras saw.

Writes ``camera_views.png`` (both camera images rendered the slow way, with the
closed-form ellipse and the ellipse found by background subtraction drawn on top) and
``trajectory.png`` (3-D and top-down flight path with the waypoints).
"""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Ellipse

import gpbf_env
from agents.pilots import WaypointPilot
from gpbf_env.camera import euler_to_matrix, fit_ellipse_image, outline_ellipses, render_frame

__all__ = ["fly", "main"]


def fly(seconds: float = 60.0, seed: int = 0) -> dict[str, np.ndarray]:
    """Fly the waypoint task with :class:`WaypointPilot`; returns the logged arrays."""
    env = gym.make("gpbf_env/BlimpWaypoint-v0", max_episode_steps=10**9)
    pilot = WaypointPilot()
    obs, info = env.reset(seed=seed)
    steps = round(seconds / env.unwrapped.config.dt)
    states, goals, valid, reward = [info["state"]], [info["goal"]], [obs["valid"]], 0.0
    for _ in range(steps):
        obs, r, terminated, truncated, info = env.step(pilot.act(info["state"], info["goal"]))
        states.append(info["state"])
        goals.append(info["goal"])
        valid.append(obs["valid"])
        reward += r
        if terminated or truncated:
            obs, info = env.reset()
    env.close()
    return {
        "state": np.array(states),
        "goal": np.array(goals),
        "valid": np.array(valid),
        "return": np.array(reward),
    }


def _save(fig: plt.Figure, path: Path) -> None:
    """Write the figure atomically (temp file in the same folder, then rename)."""
    fd, tmp = tempfile.mkstemp(suffix=".png", dir=path.parent)
    os.close(fd)
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def plot_camera_views(state: np.ndarray, path: Path, seed: int = 0) -> None:
    """Both camera images of ``state (12,)`` with closed-form and image-fitted ellipses."""
    cfg = gpbf_env.WorldConfig()
    rot = euler_to_matrix(state[None, 3:6])
    closed, visible = outline_ellipses(cfg.cameras, state[None, :3], rot, cfg.semi_axes)
    rng = np.random.default_rng(seed)
    fig, axes = plt.subplots(1, len(cfg.cameras), figsize=(6 * len(cfg.cameras), 4.2))
    for k, (ax, cam) in enumerate(zip(np.atleast_1d(axes), cfg.cameras, strict=True)):
        frame = render_frame(cam, state[:3], rot[0], cfg.semi_axes, rng)
        ax.imshow(frame, cmap="gray", vmin=0, vmax=255)
        fitted = fit_ellipse_image(cam, frame)
        for ell, color, label in (
            (closed[0, k], "red", "closed form"),
            (fitted, "cyan", "image fit"),
        ):
            if ell is None or (color == "red" and not visible[0, k]):
                continue
            cx, cy, w, h, ang = ell
            ax.add_patch(
                Ellipse(
                    (cx, cy),
                    w,
                    h,
                    angle=np.degrees(ang),
                    fill=False,
                    color=color,
                    lw=1.5,
                    label=label,
                )
            )
        ax.set_title(f"{cam.name}: 640x480, barrel distortion")
        ax.legend(loc="lower right", fontsize=8)
        ax.set_axis_off()
    fig.tight_layout()
    _save(fig, path)


def plot_trajectory(log: dict[str, np.ndarray], path: Path) -> None:
    """3-D and top-down flight path."""
    cfg = gpbf_env.WorldConfig(task="waypoint")
    p, g = log["state"][:, :3], log["goal"]
    fig = plt.figure(figsize=(12, 5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax3.plot(*p.T, lw=1.2)
    ax3.scatter(*np.unique(g[:, :3], axis=0).T, color="green", marker="x", s=60)
    ax3.set(
        xlim=(0, cfg.room[0]),
        ylim=(0, cfg.room[1]),
        zlim=(0, cfg.room[2]),
        xlabel="x (m)",
        ylabel="y (m)",
        zlabel="z (m)",
    )
    ax3.set_title("flight path (3-D)")
    ax = fig.add_subplot(1, 2, 2)
    ax.plot(p[:, 0], p[:, 1], lw=1.2, label="blimp")
    ax.scatter(*np.unique(g[:, :2], axis=0).T, color="green", marker="x", s=60, label="waypoints")
    for cam in cfg.cameras:
        ax.plot(*cam.position[:2], "ks")
        ax.annotate(cam.name, cam.position[:2])
    ax.set(xlim=(0, cfg.room[0]), ylim=(0, cfg.room[1]), xlabel="x (m)", ylabel="y (m)", aspect="equal")
    ax.set_title("top-down")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    parser.add_argument("--seconds", type=float, default=60.0, help="simulated flight time (s)")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    log = fly(args.seconds, args.seed)
    views, traj = args.out / "camera_views.png", args.out / "trajectory.png"
    plot_camera_views(log["state"][len(log["state"]) // 2], views, args.seed)
    plot_trajectory(log, traj)
    frac = log["valid"].mean(axis=0)
    print(
        f"flew {args.seconds:.0f} s: return {float(log['return']):.1f}, "
        f"camera frames per step {np.round(frac, 2).tolist()}"
    )
    print(f"wrote {views}")
    print(f"wrote {traj}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
