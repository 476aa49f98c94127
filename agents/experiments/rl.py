""" "What filtering is worth": PPO on the four observation variants, hover and waypoint tasks.

``python -m agents.experiments.rl --out docs/results/rl`` trains one agent per (task,
variant, seed) at a fixed budget, evaluates each on the same held-out episodes, and writes
``report.md`` (a table of returns and success rates) and ``returns.png``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from agents.rl import AgentSpec, evaluate_agent, train_agent
from agents.rl.wrappers import VARIANTS
from agents.sim import collect_flight
from estimator_service.files import atomic_write_text
from estimator_service.progress import ProgressBar
from estimator_service.training import TrainSettings, train_models

__all__ = ["main", "run"]


def _job(task: str, variant: str, seed: int, model: str, models: Path, out: Path, cfg: dict) -> dict:
    """Train and evaluate one agent (in a worker process, one BLAS/torch thread); the result
    is also written to the agent's folder so an interrupted experiment resumes there."""
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    folder = out / "agents" / f"{task}-{variant}-{seed}"
    done = folder / "result.json"
    if done.exists():
        return json.loads(done.read_text())
    with threadpool_limits(1):
        spec = AgentSpec("ppo", variant, task, "ekf", model, str(models), seed)
        path = train_agent(
            spec,
            cfg["timesteps"],
            folder,
            n_envs=cfg["n_envs"],
            eval_freq=max(cfg["timesteps"] // 6, 1000),
            progress_bar=False,
        )
        res = evaluate_agent(path, episodes=cfg["episodes"], seed=5000)
    atomic_write_text(done, json.dumps(res))
    return res


def run(
    out: Path,
    timesteps: int,
    seeds: int,
    episodes: int,
    tasks: tuple[str, ...],
    points: int,
    n_envs: int = 4,
    model: str = "sparse",
    jobs: int = 2,
) -> dict:
    """Train every (task, variant, seed) agent, ``jobs`` at a time, and write the report.

    Agents whose folder already holds ``result.json`` are not trained again (resume).
    """
    out.mkdir(parents=True, exist_ok=True)
    models = out / "models"
    if not (models / "parametric.npz").exists() or not (models / f"prediction_{model}.npz").exists():
        flight = collect_flight(600, seed=123)
        train_models(
            [flight],
            models,
            kinds=sorted({"param", model}),
            settings=TrainSettings(n_points=points, restarts=1, max_iter=60),
        )
    cfg = {"timesteps": timesteps, "n_envs": n_envs, "episodes": episodes}
    todo = [(t, v, s) for t in tasks for v in VARIANTS for s in range(seeds)]
    results: dict[str, dict[str, list[dict]]] = {}
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=max(1, jobs), mp_context=ctx) as pool:
        futures = [pool.submit(_job, t, v, s, model, models, out, cfg) for t, v, s in todo]
        with ProgressBar("train agents", len(futures), unit="agent") as bar:
            for _ in as_completed(futures):
                bar.advance()
    for (task, variant, _), fut in zip(todo, futures, strict=True):
        results.setdefault(task, {}).setdefault(variant, []).append(fut.result())
    meta = {"timesteps": timesteps, "seeds": seeds, "episodes": episodes, "model": model, "points": points}
    atomic_write_text(out / "results.json", json.dumps({"meta": meta, "results": results}, indent=2))
    write_report(out, results, meta)
    return results


def write_report(out: Path, results: dict, meta: dict) -> None:
    import matplotlib.pyplot as plt

    from estimator_service.plots import save_figure

    lines = [
        "# What filtering is worth to a learned controller",
        "",
        f"PPO, {meta['timesteps']} environment steps per agent, {meta['seeds']} seed(s), each agent "
        f"evaluated on the same {meta['episodes']} held-out episodes (deterministic policy). Observations: "
        f"`state` = true state (upper bound), `belief` = GP-EKF belief (mean + log std; {meta['model']} GP "
        f"models trained on {meta['points']} points of a 10-minute scripted flight), `belief-param` = "
        "parametric EKF belief, "
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
    atomic_write_text(out / "report.md", "\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", type=Path, default=Path("docs/results/rl"), help="output folder")
    p.add_argument(
        "--timesteps", type=int, default=300_000, help="PPO steps per agent (hover is learned by ~250k)"
    )
    p.add_argument("--n-envs", type=int, default=4, help="environments per PPO rollout")
    p.add_argument("--seeds", type=int, default=3, help="seeds per (task, variant)")
    p.add_argument("--episodes", type=int, default=10, help="evaluation episodes per agent")
    p.add_argument("--tasks", default="hover,waypoint", help="comma-separated tasks")
    p.add_argument("--points", type=int, default=600, help="GP training points")
    p.add_argument(
        "--model",
        default="sparse",
        choices=("gp", "egp", "sparse"),
        help="GP model kind of the belief variant (sparse: 50 pseudo-inputs, ~3x the exact GP's env steps/s)",
    )
    p.add_argument("--jobs", type=int, default=2, help="agents trained at once (one core each)")
    a = p.parse_args(argv)
    tasks = tuple(a.tasks.split(","))
    run(a.out, a.timesteps, a.seeds, a.episodes, tasks, a.points, a.n_envs, a.model, a.jobs)
    print(f"wrote {a.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
