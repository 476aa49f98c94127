"""``gpbf``: fly, record, train and track from the command line.

Subcommands
-----------
collect   fly a pilot for N minutes in the simulator and record the flight (.npz)
train     fit parametric, GP, EGP, heteroscedastic and sparse models from flights
track     run a filter with a model kind over a recorded flight; RMS, log-likelihood, plot
serve     run the estimator as a zenoh network service (same as python -m estimator_service)
router    run a zenoh router for a fleet of services on several machines
train-agent   train a PPO or SAC agent on a chosen observation variant (state, belief, ...)
eval-agent    run a saved agent: return, task success, belief tracking error
reproduce     the paper's experiments (Tables 5-10, Figs. 3-5) with a markdown report
gap-sweep     where learned models start to pay: gains over Param against the reality gap
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from estimator_service.cli import add_train_track, run
from estimator_service.cli_args import (
    Parser,
    add_calibration_options,
    add_filter_options,
    add_quiet,
    calibration_options,
    checked_float,
    checked_int,
    model_kind,
    package_version,
    seed,
)
from estimator_service.files import json_text
from estimator_service.progress import ProgressBar

if TYPE_CHECKING:
    from agents.rl import AgentSpec

__all__ = ["main"]


def _collect(args: argparse.Namespace) -> int:
    from agents.sim import collect_flight
    from estimator_service.flight import save_flight

    policy = None
    if args.agent is not None:
        from agents.rl import AgentPolicy

        policy = AgentPolicy(args.agent)
    with ProgressBar(f"collect ({args.pilot})", enabled=not args.quiet) as bar:
        flight = collect_flight(
            args.minutes * 60, policy=policy, pilot=args.pilot, seed=args.seed, env_id=args.env,
            env_kwargs=world_kwargs(args), progress=lambda k, total: bar.update_to(k, total),
        )  # fmt: skip
    path = save_flight(flight, args.out)
    frames = flight.valid.sum(axis=0).tolist()
    episodes = flight.episode.max() + 1
    print(f"wrote {path}: {len(flight)} rows, {episodes} episode(s), frames per camera {frames}")
    return 0


def _train_agent(args: argparse.Namespace) -> int:
    from agents.rl import AgentSpec, evaluate_agent

    if args.pf_update is not None:
        raise ValueError("--pf-update: train-agent's particle filters take the model kind's update rule")

    spec = AgentSpec(
        args.algo,
        args.obs,
        args.task,
        args.filter,
        model_kind(args),
        str(args.models) if args.models else None,
        args.seed,
    )
    with _threads(args.threads):
        path = _train(args, spec)
    print(f"wrote {path}, {args.out / 'learning_curve.png'} and {args.out / 'run.json'}")
    print(json_text({"agent": str(path), **evaluate_agent(path, episodes=args.eval_episodes)}))
    return 0


@contextmanager
def _threads(n: int | None) -> Iterator[None]:
    """Torch's and the BLAS libraries' threads set to ``n`` meanwhile (None: as they are)."""
    if n is None:
        yield
        return
    import torch
    from threadpoolctl import threadpool_limits

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        with threadpool_limits(n):
            yield
    finally:
        torch.set_num_threads(before)


def _train(args: argparse.Namespace, spec: AgentSpec) -> Path:
    from agents.rl import train_agent

    return train_agent(
        spec,
        args.timesteps,
        args.out,
        n_envs=args.n_envs,
        eval_freq=args.eval_freq,
        progress_bar=not args.quiet,
        hyperparams=args.hyperparams,
        tensorboard=args.tensorboard,
        eval_episodes=args.curve_episodes,
        checkpoint_freq=args.checkpoint_freq,
        resume=args.resume,
        command=["gpbf", *sys.argv[1:]],
    )


def _eval_agent(args: argparse.Namespace) -> int:
    from agents.rl import evaluate_agent

    bar = ProgressBar("evaluate", args.episodes, unit="episode", enabled=not args.quiet)
    with _threads(args.threads), bar:
        result = evaluate_agent(
            args.agent, episodes=args.episodes, seed=args.seed, on_episode=bar.update_to, models=args.models
        )
    print(json_text(result))
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from agents.experiments.reproduce import ReproduceSettings, reproduce

    s = ReproduceSettings.quick() if args.quick else ReproduceSettings()
    s = replace(s, seed=args.seed, reality=args.reality, reality_strength=args.reality_strength)
    s = replace(s, **calibration_options(args))
    reproduce(args.out, s, progress=not args.quiet, jobs=args.jobs)
    print(f"wrote {args.out / 'report.md'}")
    return 0


def _gap_sweep(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from agents.experiments.gap_sweep import gap_sweep
    from agents.experiments.reproduce import ReproduceSettings

    s = ReproduceSettings.quick() if args.quick else ReproduceSettings()
    s = replace(s, seed=args.seed, **calibration_options(args))
    gap_sweep(args.out, s, tuple(args.strengths), progress=not args.quiet, jobs=args.jobs)
    print(f"wrote {args.out / 'gap_sweep.md'}")
    return 0


ENV_IDS = ("gpbf_env/Blimp-v0", "gpbf_env/BlimpWaypoint-v0")


def add_world_options(p: argparse.ArgumentParser) -> None:
    """``--reality`` and ``--reality-strength``: the simulated world (gpbf_env.reality)."""
    from gpbf_env.reality import MAX_STRENGTH, PRESETS

    p.add_argument(
        "--reality", choices=sorted(PRESETS), default="lab",
        help="simulated world: lab (unmodelled physics, camera latency), clean (the textbook model) "
        "or drafty (lab with stronger gusts)",
    )  # fmt: skip
    p.add_argument(
        "--reality-strength", type=checked_float(0.0, MAX_STRENGTH), default=None,
        help="scale on every unmodelled effect (0: the clean world; default: the preset's)",
    )  # fmt: skip


def add_jobs_option(p: argparse.ArgumentParser) -> None:
    """``--jobs``: worker processes for an experiment's independent units."""
    from agents.experiments.parallel import MAX_JOBS

    p.add_argument(
        "--jobs", type=checked_int(1, MAX_JOBS), default=1,
        help="worker processes for the independent folds and runs (each with one BLAS thread; "
        "up to one per core); the results do not depend on it",
    )  # fmt: skip


def world_kwargs(args: argparse.Namespace) -> dict[str, object]:
    """Env keyword arguments of the world options."""
    out: dict[str, object] = {"reality": args.reality}
    if args.reality_strength is not None:
        out["reality_strength"] = args.reality_strength
    return out


def missing_extra(command: str) -> str | None:
    """The extra ``command`` needs and this install lacks, or None."""
    if command not in NEEDS:
        return None
    extra, module, _ = NEEDS[command]
    try:
        found = importlib.util.find_spec(module) is not None
    except ImportError:
        found = False
    return None if found else extra


def _needs_line(command: str, extra: str) -> str:
    return f"gpbf {command}: needs the '{extra}' extra; install it with: pip install 'gpbf[{extra}]'"


def build_parser() -> Parser:
    p = Parser(prog="gpbf", description=__doc__)
    p.add_argument("--version", action="version", version=f"gpbf {package_version()}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)
    sub.add_parser("serve", help="run the estimator service (see 'gpbf serve --help')", add_help=False)
    sub.add_parser("router", help="run a zenoh router for a fleet (see 'gpbf router --help')", add_help=False)
    add_train_track(sub)
    for command, (_, _, add) in NEEDS.items():
        extra = missing_extra(command)
        if extra is None:
            add(sub)
        else:  # listed in --help; main() answers with the install line before parsing
            sub.add_parser(command, help=f"(needs: pip install 'gpbf[{extra}]')", add_help=False)
    return p


def _add_collect(sub) -> None:
    c = sub.add_parser("collect", help="fly a pilot in the simulator and record a flight")
    c.add_argument(
        "--minutes", type=checked_float(0.1, 10_000), default=5.0, help="simulated flight time (min)"
    )
    c.add_argument(
        "--pilot", choices=("scripted", "random"), default="scripted",
        help="scripted: manoeuvres like the paper's human pilot; random: random excitation",
    )  # fmt: skip
    c.add_argument("--seed", type=seed, default=0, help="seed of the env and the pilot")
    c.add_argument("--env", choices=ENV_IDS, default=ENV_IDS[0], help="Gymnasium env id")
    c.add_argument("--out", type=Path, default=Path("out/flights/flight.npz"), help="output .npz file")
    c.add_argument(
        "--agent", type=Path, default=None, help="fly a trained agent (model.zip) instead of the pilot"
    )
    add_world_options(c)
    add_quiet(c)
    c.set_defaults(func=_collect)


def _add_train_agent(sub) -> None:
    a = sub.add_parser("train-agent", help="train an SB3 agent on beliefs")
    a.add_argument("--algo", choices=("ppo", "sac"), default="ppo", help="stable-baselines3 algorithm")
    a.add_argument(
        "--obs", choices=("state", "belief", "belief-param", "ellipses"), default="belief",
        help="observation: true state, GP belief, parametric belief, or raw ellipses",
    )  # fmt: skip
    a.add_argument("--task", choices=("hover", "waypoint"), default="hover", help="flight task")
    add_filter_options(a)
    a.add_argument(
        "--timesteps", type=checked_int(1, 10**9), default=None,
        help="training environment steps (default: the hyperparameter file's n_timesteps)",
    )  # fmt: skip
    a.add_argument(
        "--n-envs", type=checked_int(1, 256), default=None,
        help="blimps stepped together, each with its own filter (default: the hyperparameter file's)",
    )  # fmt: skip
    a.add_argument(
        "--hyperparams", type=Path, default=None,
        help="rl-zoo3-format hyperparameter file (default: hyperparams/<algo>.yml)",
    )  # fmt: skip
    a.add_argument(
        "--tensorboard", type=Path, default=None, help="write SB3's TensorBoard logs to this folder"
    )
    a.add_argument("--eval-freq", type=checked_int(1, 10**9), default=5000, help="steps between evaluations")
    a.add_argument(
        "--curve-episodes", type=checked_int(1, 10_000), default=3,
        help="episodes of each periodic evaluation (the learning curve; the RL experiment uses 8)",
    )  # fmt: skip
    a.add_argument(
        "--checkpoint-freq", type=checked_int(1, 10**9), default=None,
        help="steps between checkpoints (default: 5 x --eval-freq); the newest keeps its replay buffer",
    )  # fmt: skip
    a.add_argument(
        "--resume", action="store_true",
        help="continue the run in --out from its newest checkpoint to --timesteps in all",
    )  # fmt: skip
    a.add_argument(
        "--eval-episodes", type=checked_int(1, 10_000), default=5, help="episodes of the final evaluation"
    )
    a.add_argument("--seed", type=seed, default=0, help="seed of the agent and the envs")
    _add_threads(a, "the agent depends on it: the RL experiment trains each agent on 1")
    a.add_argument("--out", type=Path, default=Path("out/agent"), help="output folder")
    add_quiet(a)
    a.set_defaults(func=_train_agent)


def _add_threads(parser: argparse.ArgumentParser, why: str) -> None:
    parser.add_argument(
        "--threads", type=checked_int(1, 256), default=None,
        help=f"torch and BLAS threads (default: the libraries'); {why}",
    )  # fmt: skip


def _add_eval_agent(sub) -> None:
    e = sub.add_parser("eval-agent", help="evaluate a saved agent")
    e.add_argument("agent", type=Path, help="model.zip (with agent.json beside it)")
    e.add_argument("--episodes", type=checked_int(1, 100_000), default=10, help="evaluation episodes")
    e.add_argument("--seed", type=seed, default=1000, help="seed of the first episode")
    e.add_argument(
        "--models", type=Path, default=None, help="model folder (default: the one the agent names)"
    )
    _add_threads(
        e, "belief agents' returns depend on it in the last digits; the RL experiment evaluates on 1"
    )
    add_quiet(e)
    e.set_defaults(func=_eval_agent)


def _add_reproduce(sub) -> None:
    r = sub.add_parser(
        "reproduce", help="run the paper's experiments and write a report",
        description="Run the paper's experiments and write a report. Resumable: run the same command "
        "again and the models and Fig. 3 runs already complete in --out are kept.",
    )  # fmt: skip
    r.add_argument(
        "--out", type=Path, default=Path("out/reproduce"), help="output folder (report.md, figures)"
    )
    r.add_argument(
        "--quick",
        action="store_true",
        help="small sizes (4-minute flight, 150 GP points, 2 folds): 1-3 minutes on 2 cores, "
        "against 15-25 at the paper's sizes",
    )
    r.add_argument("--seed", type=seed, default=0, help="seed of the flight and the training")
    add_world_options(r)
    add_calibration_options(r)
    add_jobs_option(r)
    add_quiet(r)
    r.set_defaults(func=_reproduce)


def _add_gap_sweep(sub) -> None:
    g = sub.add_parser(
        "gap-sweep", help="GP and EGP gains over Param against the reality strength",
        description="GP and EGP gains over Param against the reality strength. Resumable like reproduce.",
    )  # fmt: skip
    g.add_argument("--out", type=Path, default=Path("out/gap_sweep"), help="output folder")
    g.add_argument("--quick", action="store_true", help="the reproduction's quick sizes")
    g.add_argument("--seed", type=seed, default=0, help="seed of the flights and the training")
    g.add_argument(
        "--strengths", type=checked_float(0.0, 4.0), nargs="+", default=[0.0, 0.5, 1.0, 2.0],
        help="reality strengths to compare",
    )  # fmt: skip
    add_calibration_options(g)
    add_jobs_option(g)
    add_quiet(g)
    g.set_defaults(func=_gap_sweep)


#: the commands that need more than the estimator: the extra to install, a module of it, and
#: the function that adds the command's parser
NEEDS = {
    "collect": ("sim", "gymnasium", _add_collect),
    "train-agent": ("rl", "stable_baselines3", _add_train_agent),
    "eval-agent": ("rl", "stable_baselines3", _add_eval_agent),
    "reproduce": ("sim", "gymnasium", _add_reproduce),
    "gap-sweep": ("sim", "gymnasium", _add_gap_sweep),
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["router"]:
        from estimator_service.service.router import main as router

        return router(argv[1:])
    if argv[:1] == ["serve"]:  # the service has its own parser and lifecycle
        from estimator_service.service.server import main as serve

        return serve(argv[1:])
    extra = missing_extra(argv[0]) if argv else None
    if extra is not None:
        print(_needs_line(argv[0], extra), file=sys.stderr)
        return 2
    return run(build_parser().parse_args(argv), "gpbf")


if __name__ == "__main__":
    raise SystemExit(main())
