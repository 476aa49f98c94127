"""``make demo``: the whole pipeline, end to end.

1. Fly the simulator for a minute and draw what the cameras saw: ``camera_views.png`` (both
   camera images rendered the slow way, with the closed-form ellipse and the one found by
   background subtraction) and ``trajectory.png``.
2. Collect a training flight with the scripted pilot and train parametric and enhanced-GP
   models (small defaults, progress bars).
3. Start ``gpbf serve`` as a separate process, fly a new flight whose controls and camera
   frames go to it through the zenoh bridge in lock-step, print the tracking error of the
   GP filter vs the parametric filter, plot the beliefs (``service_tracking.png``) and shut
   the service down cleanly.
"""

from __future__ import annotations

import argparse
import signal
from pathlib import Path

import gymnasium as gym
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Ellipse

import gpbf_env
from agents.pilots import WaypointPilot, make_pilot
from agents.sim import collect_flight, env_frames
from estimator_service.angles import wrap_angle
from estimator_service.blimp import blimp_system
from estimator_service.flight import save_flight
from estimator_service.plots import continuous, save_figure
from estimator_service.progress import ProgressBar
from estimator_service.service.client import EstimatorClient, free_port, open_session, services, spawn_service
from estimator_service.tracking import group_rms
from estimator_service.training import TrainSettings
from estimator_service.work import train_with_progress
from gpbf_env.camera import euler_to_matrix, outline_ellipses
from gpbf_env.imaging import fit_ellipse_image, render_frame

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
        for ell, style in (  # the fit wide underneath, the closed form dashed on top
            (fitted, {"color": "cyan", "lw": 3.0, "label": "image fit", "zorder": 2}),
            (closed[0, k] if visible[0, k] else None,
             {"color": "red", "lw": 1.2, "ls": "--", "label": "closed form", "zorder": 3}),
        ):  # fmt: skip
            if ell is None:
                continue
            cx, cy, w, h, ang = ell
            ax.add_patch(Ellipse((cx, cy), w, h, angle=np.degrees(ang), fill=False, **style))
        ax.set_title(f"{cam.name}: 640x480, barrel distortion")
        ax.legend(loc="lower right", fontsize=8)
        ax.set_axis_off()
    fig.tight_layout()
    save_figure(fig, path)


def plot_trajectory(log: dict[str, np.ndarray], path: Path) -> None:
    """3-D and top-down flight path."""
    cfg = gpbf_env.WorldConfig(task="waypoint")
    p, g = log["state"][:, :3], log["goal"]
    fig = plt.figure(figsize=(12, 5))
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax3.plot(*p.T, lw=1.2, label="blimp")
    ax3.scatter(*np.unique(g[:, :3], axis=0).T, color="green", marker="x", s=60, label="waypoints")
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
    for j, cam in enumerate(cfg.cameras):
        ax.plot(*cam.position[:2], "ks", label="cameras" if j == 0 else "_nolegend_")
        ax.annotate(cam.name, cam.position[:2])
    ax.set(xlim=(0, cfg.room[0]), ylim=(0, cfg.room[1]), xlabel="x (m)", ylabel="y (m)", aspect="equal")
    ax.set_title("top-down")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def fly_through_service(
    port: int, seconds: float, seed: int, kinds: tuple[str, ...]
) -> dict[str, np.ndarray]:
    """Fly a new flight; every step goes to one lock-step service session per model kind."""
    env = gym.make("gpbf_env/Blimp-v0", max_episode_steps=10**9)
    pilot = make_pilot("scripted", np.random.default_rng(seed))
    obs, info = env.reset(seed=seed)
    session = open_session([f"tcp/127.0.0.1:{port}"])
    print(f"estimator services alive: {services(session)}")
    clients = {k: EstimatorClient(session, f"demo-{k}") for k in kinds}
    std = np.repeat([0.05, 0.035, 0.05, 0.035], 3)
    for k, c in clients.items():
        c.reset(info["state"], std, t=info["t"], filter="ukf", model=k)
    truth, est = [], {k: [] for k in kinds}
    dt = env.unwrapped.config.dt
    steps = round(seconds / dt)
    with ProgressBar("fly via zenoh service", steps) as bar:
        for _ in range(steps):
            bar.advance()
            action = pilot.act(info["state"])
            obs, _, terminated, _, info = env.step(action)
            if terminated:
                where = "left the room, or touched the floor or ceiling"
                bar.stop(f"the blimp crashed ({where}) at t = {info['t']:.1f} s")
                break
            frames = env_frames(obs)
            for k, c in clients.items():
                b = c.step(action, frames, info["t"])
                est[k].append((b["mean"], np.diag(b["cov"])))
            truth.append(info["state"])
    for c in clients.values():
        c.close()
    session.close()
    return {
        "truth": np.array(truth),
        "dt": np.array(dt),
        **{k: np.array([m for m, _ in v]) for k, v in est.items()},
        **{f"{k}_var": np.array([v for _, v in e]) for k, e in est.items()},
    }


def plot_service_tracking(log: dict[str, np.ndarray], kinds: tuple[str, ...], path: Path) -> None:
    save_figure(service_tracking_figure(log, kinds), path)


def service_tracking_figure(log: dict[str, np.ndarray], kinds: tuple[str, ...]) -> plt.Figure:
    """x, y and yaw of the truth and each kind's belief with its 3-sigma band; the yaw drawn
    without its wrap at +-pi, each belief beside the truth by its wrapped error."""
    t = np.arange(len(log["truth"])) * float(log["dt"])
    periods = blimp_system().state_periods
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for ax, (i, label) in zip(axes, ((0, "x (m)"), (1, "y (m)"), (5, "yaw (rad)")), strict=True):
        truth = continuous(log["truth"][:, i], periods[i])
        ax.plot(t, truth, "k", lw=1.2, label="truth")
        for k, color in zip(kinds, ("tab:red", "tab:blue"), strict=False):
            m = truth + wrap_angle(log[k][:, i] - log["truth"][:, i], periods[i])
            sd = np.sqrt(log[f"{k}_var"][:, i])
            ax.plot(t, m, color=color, lw=0.9, ls="--", label=f"UKF / {k}")
            ax.fill_between(t, m - 3 * sd, m + 3 * sd, color=color, alpha=0.15, lw=0, label=f"3 sigma / {k}")
        ax.set_ylabel(label)
        ax.legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle("beliefs from the zenoh estimator service (lock-step), 3-sigma bands")
    fig.tight_layout()
    return fig


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    parser.add_argument("--train-minutes", type=float, default=8.0, help="training flight (sim minutes)")
    parser.add_argument("--fly-seconds", type=float, default=120.0, help="tracked flight (sim seconds)")
    parser.add_argument("--points", type=int, default=400, help="GP training points (paper: 900)")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    # 1. the simulator and its cameras
    log = fly(60.0, args.seed)
    views, traj = args.out / "camera_views.png", args.out / "trajectory.png"
    plot_camera_views(log["state"][len(log["state"]) // 2], views, args.seed)
    plot_trajectory(log, traj)
    # 2. a training flight and the models
    with ProgressBar("collect training flight") as bar:
        flight = collect_flight(args.train_minutes * 60, seed=args.seed, progress=bar.update_to)
    save_flight(flight, args.out / "training_flight.npz")
    models = args.out / "models"
    kinds = ("param", "egp")
    settings = TrainSettings(n_points=args.points, n_pseudo=30, restarts=1, max_iter=40)
    train_with_progress("train models", [flight], models, kinds=kinds, settings=settings, seed=args.seed)
    # 3. the estimator as a separate process, fed through the bridge
    port = free_port()
    proc, ready = spawn_service(models, port, "--filter", "ukf", "--model", "egp")
    print(ready)
    kinds = ("egp", "param")
    try:
        fl = fly_through_service(port, args.fly_seconds, args.seed + 1, kinds)
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=30)
    print(f"estimator service shut down cleanly (exit code {code}): {proc.stdout.read().strip()}")
    system = blimp_system()
    scores = {k: group_rms(system.state_error(fl[k], fl["truth"]), system.groups) for k in kinds}
    print(f"tracking RMS over {len(fl['truth'])} steps (UKF):")
    for name in (g.name for g in system.groups):
        gp, par = scores["egp"][name], scores["param"][name]
        gain = 100 * (1 - gp / par)
        print(f"  {name:>20s}: GP (EGP) {gp:8.2f}   parametric {par:8.2f}   improvement {gain:5.1f}%")
    plot = args.out / "service_tracking.png"
    plot_service_tracking(fl, kinds, plot)
    for p in (views, traj, plot):
        print(f"wrote {p}")
    return 0 if code == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
