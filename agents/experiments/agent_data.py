"""The agent-data loop (beyond the paper): do learned models follow an agent's flying?

A trained agent flies differently from the scripted pilot its belief models were trained
on. :func:`agent_data_loop` flies the agent (``gpbf collect --agent``'s recorder, 60 s
episodes each with a new goal), trains the models again on the scripted flight plus the
agent's flights, and tracks held-out agent flights with both model sets (GP-EKF and the
parametric EKF), writing ``agent_data.json`` and its table.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from agents.rl import AgentPolicy, load_agent
from agents.rl.registry import TASK_ENVS
from agents.rl.training import agent_folder
from agents.sim import collect_flight
from estimator_service.factory import build_filter
from estimator_service.files import atomic_write_text, json_text
from estimator_service.flight import Flight
from estimator_service.tracking import GROUPS, score, track_flight
from estimator_service.training import TrainSettings
from estimator_service.work import train_with_progress

__all__ = ["agent_data_lines", "agent_data_loop"]

EPISODE_SECONDS = 60.0  # the agents' episodes
KEYS = (*GROUPS, "within3", "failed")


def _episodes(flight: Flight) -> list[slice]:
    """Row ranges of the flight's episodes longer than 10 steps."""
    starts = np.flatnonzero(np.diff(flight.episode, prepend=-1))
    ends = [*starts[1:], len(flight)]
    return [slice(int(a), int(b)) for a, b in zip(starts, ends, strict=True) if b - a > 10]


def track_episodes(models: Path, kind: str, flight: Flight) -> dict[str, float]:
    """GP-EKF (or parametric EKF) tracking scores averaged over the flight's episodes."""
    filt = build_filter("ekf", kind, models)
    scores = [score(track_flight(filt, flight, rows=rows)) for rows in _episodes(flight)]
    return {k: float(np.mean([s[k] for s in scores])) for k in KEYS}


def agent_data_loop(
    out: Path, agent: Path, *, scripted_minutes: float = 10, agent_minutes: float = 5,
    heldout_minutes: float = 5, seed: int = 0, settings: TrainSettings | None = None,
) -> dict[str, Any]:  # fmt: skip
    """Train on scripted vs scripted + agent flights, track held-out agent flights with each.

    ``settings``: the models' training (default: 600 points, the default calibration)."""
    settings = TrainSettings(n_points=600) if settings is None else settings
    _, spec = load_agent(agent)
    env_id = TASK_ENVS[spec.task]
    policy = AgentPolicy(agent)
    scripted = collect_flight(scripted_minutes * 60, seed=seed + 123)
    fly = {"env_id": env_id, "policy": policy, "episode_seconds": EPISODE_SECONDS}
    flown = collect_flight(agent_minutes * 60, seed=seed + 301, **fly)
    heldout = collect_flight(heldout_minutes * 60, seed=seed + 302, **fly)
    table: dict[str, dict[str, dict[str, float]]] = {}
    for name, flights in (("scripted", [scripted]), ("scripted+agent", [scripted, flown])):
        folder = out / "agent_data" / name
        if not (folder / "prediction_gp.npz").exists():
            train_with_progress(
                f"agent data: {name} models", flights, folder, kinds=["param", "gp"], settings=settings
            )
        table[name] = {kind: track_episodes(folder, kind, heldout) for kind in ("gp", "param")}
    data = {
        "agent": _label(agent, out),
        "task": spec.task,
        "minutes": {"scripted": scripted_minutes, "agent": agent_minutes, "heldout": heldout_minutes},
        "points": settings.n_points,
        "heldout_episodes": len(_episodes(heldout)),
        "tracking": table,
    }
    atomic_write_text(out / "agent_data.json", json_text(data, indent=2))
    return data


def _label(agent: Path, out: Path) -> str:
    """The agent's folder, relative to ``out`` when inside it (a committed report names no
    machine's paths)."""
    folder = agent_folder(agent)
    try:
        return folder.resolve().relative_to(Path(out).resolve()).as_posix()
    except ValueError:
        return folder.as_posix()


def agent_data_lines(data: dict[str, Any]) -> list[str]:
    """The report's agent-data table (RMS per state group, paper units)."""
    m = data["minutes"]
    lines = [
        "## The agent-data loop",
        "",
        f"The {data['task']} agent `{agent_folder(data['agent']).name}` flew {m['agent']} min (training) and "
        f"{m['heldout']} min ({data['heldout_episodes']} held-out episodes); models trained on the "
        f"{m['scripted']}-min scripted flight alone or with the agent's flight ({data['points']} GP points), "
        "tracking the held-out agent episodes with the EKF:",
        "",
        "| training data | model | " + " | ".join(KEYS) + " |",
        "| --- | --- | " + " | ".join("---:" for _ in KEYS) + " |",
    ]
    for name, by_kind in data["tracking"].items():
        for kind, s in by_kind.items():
            lines.append(f"| {name} | {kind} | " + " | ".join(f"{s[k]:.3g}" for k in KEYS) + " |")
    return lines
