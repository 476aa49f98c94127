"""The RL experiment's report: ``report.md``, ``learning_curves.png`` and ``returns.png``
from ``results.json``'s data and the agents' evaluation logs (``evaluations.npz``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from agents.experiments.report_notes import write_keeping_notes
from estimator_service.provenance import provenance_line

__all__ = ["learning_curves", "write_report"]

COLOURS = {"state": "tab:green", "belief": "tab:blue", "belief-param": "tab:orange", "ellipses": "tab:red"}


def learning_curves(out: Path, task: str, variant: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Evaluation steps ``(E,)`` and mean returns ``(S, E)`` of a (task, variant)'s seeds: the
    steps of the seed evaluated least often, within the span every seed covers, each seed's
    curve interpolated linearly there (seeds may have been evaluated at intervals that share
    no step); None without logs."""
    logs = sorted((out / "agents").glob(f"{task}-{variant}-[0-9]*/evaluations.npz"))  # not belief-param
    data = [np.load(f) for f in logs]
    if not data:
        return None
    first = max(d["timesteps"][0] for d in data)
    last = min(d["timesteps"][-1] for d in data)
    steps = min((d["timesteps"] for d in data), key=len)
    steps = steps[(steps >= first) & (steps <= last)]
    rows = [np.interp(steps, d["timesteps"], d["results"].mean(axis=1)) for d in data]
    return steps, np.stack(rows)


def _figures(out: Path, data: dict[str, Any]) -> None:
    import matplotlib.pyplot as plt

    from estimator_service.plots import save_figure

    tasks = list(data["results"])
    fig, axes = plt.subplots(1, len(tasks), figsize=(5.5 * len(tasks), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        for variant in data["results"][task]:
            curve = learning_curves(out, task, variant)
            if curve is None:
                continue
            steps, r = curve
            ax.plot(steps, r.mean(axis=0), color=COLOURS.get(variant), label=variant)
            ax.fill_between(steps, r.min(axis=0), r.max(axis=0), color=COLOURS.get(variant), alpha=0.2)
        ax.axhline(data["pilot"][task]["mean_return"], color="k", ls="--", label="WaypointPilot")
        ax.set(title=task, xlabel="environment steps", ylabel="evaluation return (mean, min-max over seeds)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, out / "learning_curves.png")
    fig, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 4), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        by_var = data["results"][task]
        names = list(by_var)
        ax.bar(
            names,
            [by_var[v]["mean_return"] for v in names],
            yerr=[by_var[v]["return_spread_across_seeds"] for v in names],
            color=[COLOURS.get(v) for v in names],
        )
        ax.axhline(data["pilot"][task]["mean_return"], color="k", ls="--")
        ax.set(title=task, ylabel="evaluation return")
        ax.tick_params(axis="x", rotation=20)
    fig.tight_layout()
    save_figure(fig, out / "returns.png")


def _published_lines(out: Path, meta: dict[str, Any]) -> list[str]:
    """Per agent whose ``model.zip`` is in ``out/agents``: the command that evaluates it on
    the report's episodes and what it gave here (a row is the mean of its seeds' lines)."""
    from agents.experiments.rl_schedule import eval_command

    agents = sorted((out / "agents").glob("*/model.zip"))
    if not agents:
        return []
    lines = ["", "The command that flies each agent (its `model.zip` in `agents/` beside this report) on "
             "these episodes, and what it gave here (a row of the table is the mean over its seeds):", "",
             "| agent | command | success rate | mean return |", "| --- | --- | ---: | ---: |"]  # fmt: skip
    for model in agents:
        done = model.parent / "result.json"
        res = json.loads(done.read_text()) if done.exists() else {}
        cmd = " ".join(eval_command(_shown(model), meta["episodes"], meta["eval_seed"]))
        figures = (f"{res['success_rate']:.2f} | {res['mean_return']:.1f}" if "mean_return" in res
                   else "- | -")  # fmt: skip
        lines.append(f"| {model.parent.name} | `{cmd}` | {figures} |")
    lines += ["", "The command that trains each agent again as this run did (same seed, hyperparameters, "
              "learning-curve evaluations and checkpoints; `--out` any new folder):", ""]  # fmt: skip
    lines += [f"- {model.parent.name}: `{' '.join(_train_command(model.parent, meta))}`" for model in agents]
    return lines


def _train_command(folder: Path, meta: dict[str, Any]) -> list[str]:
    """``gpbf train-agent ...`` for the agent saved in ``folder`` (its ``agent.json``)."""
    from agents.experiments.rl_schedule import train_command
    from agents.rl import AgentSpec

    spec = AgentSpec(**json.loads((folder / "agent.json").read_text()))
    models = _shown((folder / spec.models).resolve()) if spec.models else "models"
    return train_command(spec, meta["timesteps"], models, f"out/{folder.name}")


def _shown(path: Path) -> str:
    """``path`` relative to the working folder where it lies below it (no machine's paths in a
    report written from the repository root), else as given."""
    try:
        return path.resolve().relative_to(Path.cwd().resolve()).as_posix()
    except ValueError:
        return path.as_posix()


def write_report(out: Path, data: dict[str, Any]) -> None:
    """``report.md`` with the results table, the gap closed, the targets and the figures."""
    meta = data["meta"]
    budget = meta["timesteps"] or "the hyperparameter file's"
    lines = [
        "# What filtering is worth to a learned controller",
        "",
        *([provenance_line(data["provenance"]), ""] if "provenance" in data else []),
        f"{meta['algo'].upper()} with `hyperparams/{meta['algo']}.yml`, {budget} environment steps per "
        "agent, "
        f"{meta['seeds']} seed(s), each agent evaluated on the same {meta['episodes']} held-out episodes "
        f"(deterministic policy), world: {meta['world']}. Observations: `state` = true state (upper bound), "
        f"`belief` = GP-EKF belief (mean + log std; {meta['model']} GP models, {meta['points']} points of a "
        "10-minute scripted flight, cross-fitted noise calibration), `belief-param` = parametric EKF belief, "
        "`ellipses` = raw camera ellipses + last action. Every variant also sees the goal. The hand-written "
        "`WaypointPilot` flies the same episodes on the true state.",
        "",
        "| task | observation | success rate | mean return | +- (across seeds) | belief position RMS (mm) |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for task, by_var in data["results"].items():
        p = data["pilot"][task]
        pilot = f"{p['success_rate']:.2f} | {p['mean_return']:.1f}"
        lines.append(f"| {task} | WaypointPilot (true state) | {pilot} | - | - |")
        for variant, r in by_var.items():
            rms = r["belief_position_rms_mm"]
            lines.append(
                f"| {task} | {variant} | {r['success_rate']:.2f} | {r['mean_return']:.1f} | "
                f"{r['return_spread_across_seeds']:.1f} | {'-' if rms is None else f'{rms:.0f}'} |"
            )
    if meta.get("not_trained"):
        lines += ["", f"Not trained: {', '.join(meta['not_trained'])}."]
    if data["gap_closed"]:
        lines += ["", "Gap closed by the GP-belief agent (ellipses -> state, on mean return): "]
        lines += [f"- {task}: {g:.2f}" for task, g in data["gap_closed"].items()]
    if data["targets"]:
        lines += ["", "Targets (fixed before the runs): "]
        lines += [f"- `{name}`: {'met' if ok else 'NOT met'}" for name, ok in data["targets"].items()]
    lines += _published_lines(out, meta)
    agent_data = out / "agent_data.json"
    if agent_data.exists():
        from agents.experiments.agent_data import agent_data_lines

        lines += ["", *agent_data_lines(json.loads(agent_data.read_text()))]
    lines += ["", "![learning curves](learning_curves.png)", "", "![returns](returns.png)", ""]
    _figures(out, data)
    write_keeping_notes(out / "report.md", lines)
