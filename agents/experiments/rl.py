"""What filtering is worth: RL agents on the four observation variants, hover and waypoint.

``python -m agents.experiments.rl --out docs/results/rl`` trains one agent per (task,
variant, seed) with the committed hyperparameters (``hyperparams/<algo>.yml``, in the
batched belief env), evaluates each and the hand-written
:class:`~agents.pilots.WaypointPilot` on the same held-out episodes, and writes
``results.json`` (per task and variant: success rate and mean return; the pilot's; the
share of the ellipse-to-state gap the GP-belief agent closes; each target's verdict),
``report.md``, ``learning_curves.png`` (mean and spread over seeds) and ``returns.png``.
``--agent-data`` adds the agent-data loop (:mod:`agents.experiments.agent_data`).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agents.experiments.rl_schedule import AGENT_THREADS, CURVE_EPISODES, curve_freq
from agents.rl import AgentSpec, evaluate_agent, evaluate_pilot, train_agent
from agents.rl.registry import TASK_ENVS
from agents.rl.wrappers import VARIANTS
from agents.sim import collect_flight
from estimator_service.cli import guarded
from estimator_service.cli_args import Parser, checked_int
from estimator_service.files import atomic_write_text, json_text
from estimator_service.progress import ProgressBar
from estimator_service.provenance import code_version, named_argv, provenance
from estimator_service.training import TrainSettings
from estimator_service.work import train_with_progress

__all__ = [
    "RLSettings",
    "agent_weights",
    "gap_closed",
    "main",
    "report_existing",
    "run",
    "summarise",
]

EVAL_SEED = 5000  # the held-out episodes every agent and the pilot fly
# Progress weights (docs/measurements.md#progress-weights): an agent's training cost over a
# true-state agent's of the same budget (the filter variants step a filter too), and an agent
# a resumed run finds trained (its result.json read back), as a share of a training's cost.
FILTER_VARIANT_COST = 1.4
KEPT_AGENT_COST = 0.004


@dataclass(frozen=True)
class RLSettings:
    """One experiment: budget (None: the hyperparameter file's), seeds, tasks, variants."""

    algo: str = "ppo"
    timesteps: int | None = None
    seeds: int = 3
    episodes: int = 20
    tasks: tuple[str, ...] = ("hover", "waypoint")
    variants: tuple[str, ...] = VARIANTS
    points: int = 600
    model: str = "sparse"
    jobs: int = 2
    tensorboard: bool = False


Record = tuple[list[str], str]  # an experiment's command line and code version


def _job(task: str, variant: str, seed: int, models: Path, out: Path, cfg: RLSettings, rec: Record) -> dict:
    """Train and evaluate one agent (in a worker process, one BLAS/torch thread); the result
    is also written to the agent's folder so an interrupted experiment resumes there.
    ``rec``: the experiment's command line and code version, for the agent's ``run.json``
    (a worker's own command line is the process pool's, and the checkout may have moved)."""
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(AGENT_THREADS)
    folder, done = _agent_folder(out, task, variant, seed), _result(out, task, variant, seed)
    if done.exists():
        return json.loads(done.read_text())
    with threadpool_limits(AGENT_THREADS):
        spec = AgentSpec(cfg.algo, variant, task, "ekf", cfg.model, str(models), seed)
        path = train_agent(
            spec,
            cfg.timesteps,
            folder,
            eval_freq=curve_freq(cfg.timesteps),
            eval_episodes=CURVE_EPISODES,
            progress_bar=False,
            tensorboard=out / "tensorboard" if cfg.tensorboard else None,
            command=rec[0],
            code=rec[1],
        )
        res = evaluate_agent(path, episodes=cfg.episodes, seed=EVAL_SEED)
    atomic_write_text(done, json_text(res))
    return res


def _models(out: Path, cfg: RLSettings) -> Path:
    """The belief variants' models (trained once on a 10-minute scripted flight)."""
    models = out / "models"
    if not (models / "parametric.npz").exists() or not (models / f"prediction_{cfg.model}.npz").exists():
        flight = collect_flight(600, seed=123)
        kinds = sorted({"param", cfg.model})
        train_with_progress(
            "train belief models", [flight], models, kinds=kinds, settings=TrainSettings(n_points=cfg.points)
        )
    return models


def _agent_folder(out: Path, task: str, variant: str, seed: int) -> Path:
    return out / "agents" / f"{task}-{variant}-{seed}"


def _result(out: Path, task: str, variant: str, seed: int) -> Path:
    """An agent's evaluation, written last: its presence marks the agent trained (resume)."""
    return _agent_folder(out, task, variant, seed) / "result.json"


def _agents(cfg: RLSettings) -> list[tuple[str, str, int]]:
    """Every (task, variant, seed) of the experiment, in training order."""
    return [(t, v, s) for t in cfg.tasks for v in cfg.variants for s in range(cfg.seeds)]


def agent_weights(out: Path, todo: list[tuple[str, str, int]]) -> list[float]:
    """Each agent's estimated cost for the progress line, in true-state agents of this
    run's budget: ``KEPT_AGENT_COST`` for one already trained under ``out`` (resume),
    ``FILTER_VARIANT_COST`` for the belief variants, 1 for the others.

    Returns
    -------
    weights: (len(todo),)
    """
    return [
        KEPT_AGENT_COST
        if _result(out, t, v, s).exists()
        else FILTER_VARIANT_COST
        if v.startswith("belief")
        else 1.0
        for t, v, s in todo
    ]


def run(out: Path, cfg: RLSettings) -> dict[str, Any]:
    """Train every (task, variant, seed) agent, ``cfg.jobs`` at a time, evaluate them and the
    pilot, and write ``results.json`` and the report (agents already holding
    ``result.json`` are not trained again: resume)."""
    from agents.experiments.rl_report import write_report

    start, code = time.monotonic(), code_version()  # the code that trains, not the checkout at the end
    out.mkdir(parents=True, exist_ok=True)
    models = _models(out, cfg)
    todo = _agents(cfg)
    weights = agent_weights(out, todo)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=max(1, cfg.jobs), mp_context=ctx) as pool:
        record = (named_argv(), code)
        futures = {pool.submit(_job, *k, models, out, cfg, record): i for i, k in enumerate(todo)}
        kept = [i for i, w in enumerate(weights) if w == KEPT_AGENT_COST]  # trained before this run
        with ProgressBar("train agents", unit="agent", weights=weights, done=kept) as bar:
            for fut in as_completed(futures):
                bar.advance(index=futures[fut])
    runs: dict[str, dict[str, list[dict]]] = {}
    for (task, variant, _), fut in zip(todo, futures, strict=True):  # dicts keep submission order
        runs.setdefault(task, {}).setdefault(variant, []).append(fut.result())
    pilot = {task: evaluate_pilot(task, cfg.episodes, EVAL_SEED) for task in cfg.tasks}
    data = {**summarise(runs, pilot, cfg), "provenance": provenance(time.monotonic() - start, code=code)}
    atomic_write_text(out / "results.json", json_text(data, indent=2))
    write_report(out, data)
    return data


def report_existing(out: Path, cfg: RLSettings) -> dict[str, Any]:
    """``results.json`` and the report from the agents already trained under ``out`` (those
    with ``result.json``; the others are left out and named in the report's meta)."""
    from agents.experiments.rl_report import write_report

    runs: dict[str, dict[str, list[dict]]] = {}
    missing = []
    for task, variant, seed in _agents(cfg):
        done = _result(out, task, variant, seed)
        if done.exists():
            runs.setdefault(task, {}).setdefault(variant, []).append(json.loads(done.read_text()))
        else:
            missing.append(f"{task}-{variant}-{seed}")
    if not runs:
        raise ValueError(f"--out {out}: no trained agent to report (no agents/*/result.json)")
    pilot = {task: evaluate_pilot(task, cfg.episodes, EVAL_SEED) for task in runs}
    data = summarise(runs, pilot, cfg)
    data["meta"]["not_trained"] = missing
    earlier = out / "results.json"  # the training run's record and settings stay with its agents
    if earlier.is_file() and "provenance" in (before := json.loads(earlier.read_text())):
        data["provenance"] = before["provenance"]
        data["meta"].update({k: v for k, v in before.get("meta", {}).items() if k in ("jobs", "tensorboard")})
    atomic_write_text(out / "results.json", json_text(data, indent=2))
    write_report(out, data)
    return data


def _nan(v: float | None) -> float:
    """A figure read back from JSON (None: not measured) as a float (NaN)."""
    return math.nan if v is None else v


def gap_closed(by_variant: dict[str, dict[str, float]], key: str = "mean_return") -> float:
    """Share of the ellipse-to-state gap the GP-belief agent closes (1: as good as the state)."""
    state, ell, belief = (by_variant[v][key] for v in ("state", "ellipses", "belief"))
    return float((belief - ell) / (state - ell)) if state != ell else float("nan")


def summarise(
    runs: dict[str, dict[str, list[dict]]], pilot: dict[str, dict], cfg: RLSettings
) -> dict[str, Any]:
    """``results.json``: per task and variant the seeds' mean success rate and return (and the
    runs), the pilot's figures, the gap closed and the issue's targets."""
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for task, by_variant in runs.items():
        for variant, rs in by_variant.items():
            r = np.array([x["mean_return"] for x in rs])
            results.setdefault(task, {})[variant] = {
                "success_rate": float(np.mean([x["success_rate"] for x in rs])),
                "mean_return": float(r.mean()),
                "return_spread_across_seeds": float(r.std()),
                "belief_position_rms_mm": float(np.nanmean([_nan(x["belief_position_rms_mm"]) for x in rs]))
                if variant.startswith("belief")
                else None,
                "runs": rs,
            }
    targets: dict[str, Any] = {}
    if "hover" in results and "state" in results["hover"]:
        targets["hover_state_success_ge_0.9"] = results["hover"]["state"]["success_rate"] >= 0.9
    if "waypoint" in results and "state" in results["waypoint"]:
        targets["waypoint_state_beats_pilot"] = (
            results["waypoint"]["state"]["mean_return"] > pilot["waypoint"]["mean_return"]
        )
    gaps = {}
    for task, by_variant in results.items():
        if {"state", "ellipses", "belief"} <= set(by_variant):
            gaps[task] = gap_closed(by_variant)
            targets[f"{task}_belief_closes_0.8_of_gap"] = gaps[task] >= 0.8
    meta = {**asdict(cfg), "eval_seed": EVAL_SEED, "world": "lab (the default)"}
    return {"meta": meta, "pilot": pilot, "results": results, "gap_closed": gaps, "targets": targets}


def main(argv: list[str] | None = None) -> int:
    p = Parser(prog="python -m agents.experiments.rl", description=__doc__.strip())
    p.add_argument(
        "--out", type=Path, default=Path("out/rl"),
        help="output folder (the committed results: docs/results/rl, sac_hover, sac_waypoint)",
    )  # fmt: skip
    p.add_argument("--algo", choices=("ppo", "sac"), default="ppo", help="stable-baselines3 algorithm")
    p.add_argument(
        "--timesteps",
        type=checked_int(1, 10**9),
        default=None,
        help="steps per agent (default: the hyperparameter file's)",
    )
    p.add_argument("--seeds", type=checked_int(1, 100), default=3, help="seeds per (task, variant)")
    p.add_argument(
        "--episodes", type=checked_int(1, 10_000), default=20, help="evaluation episodes per agent"
    )
    p.add_argument("--tasks", default="hover,waypoint", help="comma-separated tasks")
    p.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated observation variants")
    p.add_argument("--points", type=checked_int(10, 5000), default=600, help="GP training points")
    p.add_argument(
        "--model", default="sparse", choices=("gp", "egp", "sparse"),
        help="GP model kind of the belief variant (sparse: 50 pseudo-inputs)",
    )  # fmt: skip
    p.add_argument(
        "--jobs", type=checked_int(1, 64), default=2, help="agents trained at once (one core each)"
    )
    p.add_argument("--tensorboard", action="store_true", help="SB3 TensorBoard logs under <out>/tensorboard")
    p.add_argument(
        "--agent-data", action="store_true", help="also run the agent-data loop (hover state agent)"
    )
    p.add_argument(
        "--report-only", action="store_true",
        help="train nothing: results and report from the agents already under --out",
    )  # fmt: skip
    a = p.parse_args(argv)
    for field, names, known in (("--tasks", a.tasks, TASK_ENVS), ("--variants", a.variants, VARIANTS)):
        unknown = sorted(set(names.split(",")) - set(known))
        if unknown:
            p.error(f"{field}: unknown {unknown}; choose from {sorted(known)}")
    cfg = RLSettings(
        a.algo, a.timesteps, a.seeds, a.episodes, tuple(a.tasks.split(",")), tuple(a.variants.split(",")),
        a.points, a.model, a.jobs, a.tensorboard,
    )  # fmt: skip
    if guarded(p.prog, a, lambda: _check(a, cfg)) != 0:  # a mistake is one line; a failure mid-run
        return 2  # keeps its traceback
    return _main(a, cfg)


def _check(a: argparse.Namespace, cfg: RLSettings) -> int:
    """Before any work: ``--report-only`` needs a trained agent under ``--out``."""
    if a.report_only and not _trained(a.out, cfg):
        raise ValueError(f"--out {a.out}: no trained agent to report (no agents/*/result.json)")
    return 0


def _trained(out: Path, cfg: RLSettings) -> list[tuple[str, str, int]]:
    """The (task, variant, seed) of ``cfg`` whose agent under ``out`` holds ``result.json``."""
    return [k for k in _agents(cfg) if _result(out, *k).exists()]


def _main(a: argparse.Namespace, cfg: RLSettings) -> int:
    if a.report_only:
        report_existing(a.out, cfg)
    else:
        run(a.out, cfg)
    if a.agent_data:
        from agents.experiments.agent_data import agent_data_loop

        agent_data_loop(a.out, a.out / "agents" / "hover-state-0" / "model.zip")
    print(f"wrote {a.out / 'report.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
