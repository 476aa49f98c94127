""" "What filtering is worth": PPO on the four observation variants, hover and waypoint tasks.

``python -m agents.experiment_rl --out docs/results/rl`` trains one agent per (task,
variant, seed) at a fixed budget, evaluates each on the same held-out episodes, and writes
``report.md`` (a table of returns and success rates) and ``returns.png``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from tqdm import tqdm

from agents.recorder import collect_flight
from agents.rl import AgentSpec, evaluate_agent, train_agent
from agents.training import TrainSettings, train_models
from agents.wrappers import VARIANTS

__all__ = ["main", "run"]


def run(
    out: Path, timesteps: int, seeds: int, episodes: int, tasks: tuple[str, ...], points: int, n_envs: int = 4
) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    models = out / "models"
    if not (models / "parametric.npz").exists():
        flight = collect_flight(600, seed=123)
        train_models(
            [flight],
            models,
            kinds=["param", "gp"],
            settings=TrainSettings(n_points=points, restarts=1, max_iter=60),
        )
    results: dict[str, dict[str, list[dict]]] = {}
    jobs = [(t, v, s) for t in tasks for v in VARIANTS for s in range(seeds)]
    for task, variant, seed in tqdm(jobs, desc="train agents", unit="agent"):
        spec = AgentSpec("ppo", variant, task, "ekf", "gp", str(models), seed)
        folder = out / "agents" / f"{task}-{variant}-{seed}"
        path = train_agent(
            spec, timesteps, folder, n_envs=n_envs, eval_freq=max(timesteps // 5, 1000), progress_bar=False
        )
        res = evaluate_agent(path, episodes=episodes, seed=5000)
        results.setdefault(task, {}).setdefault(variant, []).append(res)
    (out / "results.json").write_text(json.dumps(results, indent=2))
    write_report(out, results, timesteps, seeds, episodes)
    return results


def write_report(out: Path, results: dict, timesteps: int, seeds: int, episodes: int) -> None:
    import matplotlib.pyplot as plt

    from agents.plots import save_figure

    lines = [
        "# What filtering is worth to a learned controller",
        "",
        f"PPO, {timesteps} environment steps per agent, {seeds} seed(s), each agent evaluated on the same "
        f"{episodes} held-out episodes (deterministic policy). Observations: `state` = true state (upper "
        "bound), `belief` = GP-EKF belief (mean + log std), `belief-param` = parametric EKF belief, "
        "`ellipses` = raw camera ellipses + last action. Every variant also sees the goal.",
        "",
        "| task | observation | mean return | +- (across seeds) | success rate | belief position RMS (mm) |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    fig, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 4), squeeze=False)
    for ax, (task, by_var) in zip(axes[0], results.items(), strict=True):
        means, errs = [], []
        for variant in VARIANTS:
            runs = by_var.get(variant, [])
            r = np.array([x["mean_return"] for x in runs])
            succ = np.mean([x["success_rate"] for x in runs])
            rms = (
                np.nanmean([x["belief_position_rms_mm"] for x in runs])
                if variant.startswith("belief")
                else np.nan
            )
            lines.append(
                f"| {task} | {variant} | {r.mean():.1f} | {r.std():.1f} | {succ:.2f} | "
                f"{'-' if np.isnan(rms) else f'{rms:.0f}'} |"
            )
            means.append(r.mean())
            errs.append(r.std())
        ax.bar(VARIANTS, means, yerr=errs, color=["tab:green", "tab:blue", "tab:orange", "tab:red"])
        ax.set(title=task, ylabel="evaluation return")
        ax.tick_params(axis="x", rotation=20)
    fig.tight_layout()
    save_figure(fig, out / "returns.png")
    lines += ["", "![returns](returns.png)", ""]
    (out / "report.md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", type=Path, default=Path("docs/results/rl"), help="output folder")
    p.add_argument(
        "--timesteps", type=int, default=500_000, help="PPO steps per agent (hover needs several 100k)"
    )
    p.add_argument("--n-envs", type=int, default=4, help="environments per PPO rollout")
    p.add_argument("--seeds", type=int, default=3, help="seeds per (task, variant)")
    p.add_argument("--episodes", type=int, default=10, help="evaluation episodes per agent")
    p.add_argument("--tasks", default="hover,waypoint", help="comma-separated tasks")
    p.add_argument("--points", type=int, default=600, help="GP training points")
    a = p.parse_args(argv)
    run(a.out, a.timesteps, a.seeds, a.episodes, tuple(a.tasks.split(",")), a.points, a.n_envs)
    print(f"wrote {a.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
