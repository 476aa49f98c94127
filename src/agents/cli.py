"""``gpbf``: fly, record, train and track from the command line.

Subcommands
-----------
collect   fly a pilot for N minutes in the simulator and record the flight (.npz)
train     fit parametric, GP, EGP, heteroscedastic and sparse models from flights
track     run a filter with a model kind over a recorded flight; RMS, log-likelihood, plot
serve     run the estimator as a zenoh network service (same as python -m estimator_service)
train-agent   train a PPO or SAC agent on a chosen observation variant (state, belief, ...)
eval-agent    run a saved agent: return, task success, belief tracking error
reproduce     the paper's experiments (Tables 5-10, Fig. 4, consistency) with a markdown report
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

__all__ = ["main"]


def _collect(args: argparse.Namespace) -> int:
    from agents.recorder import collect_flight, save_flight

    steps = round(args.minutes * 60 / 0.25)
    with tqdm(total=steps, desc=f"collect ({args.pilot})", unit="step", disable=args.quiet) as bar:
        policy = None
        if args.agent is not None:
            from agents.rl import AgentPolicy

            policy = AgentPolicy(args.agent)
        flight = collect_flight(
            args.minutes * 60,
            policy=policy,
            pilot=args.pilot,
            seed=args.seed,
            env_id=args.env,
            progress=lambda k: bar.update(k - bar.n),
        )
    path = save_flight(flight, args.out)
    frames = flight.valid.sum(axis=0).tolist()
    episodes = flight.episode.max() + 1
    print(f"wrote {path}: {len(flight)} rows, {episodes} episode(s), frames per camera {frames}")
    return 0


def _train(args: argparse.Namespace) -> int:
    from agents.recorder import load_flight
    from agents.training import TrainSettings, train_models

    flights = [load_flight(p) for p in args.flights]
    settings = TrainSettings(
        args.points,
        args.pseudo,
        args.restarts,
        args.max_iter,
        args.hetero_iterations,
        sparse_iter=args.sparse_iter,
        hyper_points=args.hyper_points or None,
        calibration_seconds=args.calibration_seconds,
    )
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    bars: dict[str, tqdm] = {}

    def progress(kind: str, p) -> None:
        if args.quiet:
            return
        bar = bars.setdefault(kind, tqdm(desc=f"train {kind}", unit="it"))
        if p is None:
            bar.close()
            return
        bar.update(1)
        bar.set_postfix(output=p.output, restart=p.restart, nll=f"{p.objective:.4g}")

    timings = train_models(
        flights,
        args.out,
        kinds=["param", *kinds],
        settings=settings,
        seed=args.seed,
        on_progress=progress,
    )
    print(
        json.dumps({"models": str(args.out), "train_seconds": {k: round(v, 1) for k, v in timings.items()}})
    )
    return 0


def _track(args: argparse.Namespace) -> int:
    from agents.plots import plot_tracking
    from agents.recorder import load_flight
    from agents.tracking import track_flight
    from estimator_service.factory import build_filter

    flight = load_flight(args.flight)
    opts = {"n_particles": args.particles} if args.filter == "pf" else {}
    filt = build_filter(args.filter, args.model, args.models, **opts)
    with tqdm(total=len(flight) - 1, desc=f"track {args.filter}/{args.model}", disable=args.quiet) as bar:
        result = track_flight(
            filt,
            flight,
            rng=np.random.default_rng(args.seed),
            on_step=lambda k: bar.update(k - bar.n),
        )
    scores = result.scores()
    for name, value in scores.items():
        print(f"{name:>20s}: {value:.4g}")
    if args.plot:
        plot_tracking(result, Path(args.plot), title=f"GP-BayesFilter {args.filter.upper()} / {args.model}")
        print(f"wrote {args.plot}")
    print(json.dumps({k: round(v, 4) for k, v in scores.items()}))
    return 0


def _train_agent(args: argparse.Namespace) -> int:
    from agents.rl import AgentSpec, evaluate_agent, train_agent

    spec = AgentSpec(
        args.algo,
        args.obs,
        args.task,
        args.filter,
        args.model,
        str(args.models) if args.models else None,
        args.seed,
    )
    path = train_agent(
        spec,
        args.timesteps,
        args.out,
        n_envs=args.n_envs,
        eval_freq=args.eval_freq,
        progress_bar=not args.quiet,
    )
    print(f"wrote {path} and {args.out / 'learning_curve.png'}")
    print(json.dumps({"agent": str(path), **evaluate_agent(path, episodes=args.eval_episodes)}))
    return 0


def _eval_agent(args: argparse.Namespace) -> int:
    from agents.rl import evaluate_agent

    with tqdm(total=args.episodes, desc="evaluate", unit="episode", disable=args.quiet) as bar:
        result = evaluate_agent(
            args.agent, episodes=args.episodes, seed=args.seed, on_episode=lambda k: bar.update(k - bar.n)
        )
    print(json.dumps(result))
    return 0


def _reproduce(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from agents.reproduce import ReproduceSettings, reproduce

    s = ReproduceSettings.quick() if args.quick else ReproduceSettings()
    s = replace(s, seed=args.seed)
    reproduce(args.out, s, progress=not args.quiet)
    print(f"wrote {args.out / 'report.md'}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="gpbf", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("serve", help="run the estimator service (see 'gpbf serve --help')", add_help=False)

    c = sub.add_parser("collect", help="fly a pilot and record a flight")
    c.add_argument("--minutes", type=float, default=5.0, help="simulated flight time in minutes (default 5)")
    c.add_argument(
        "--pilot",
        choices=("scripted", "random"),
        default="scripted",
        help="scripted: manoeuvres like the paper's human pilot; random: random excitation",
    )
    c.add_argument("--seed", type=int, default=0, help="seed of the env and the pilot")
    c.add_argument("--env", default="gpbf_env/Blimp-v0", help="Gymnasium env id")
    c.add_argument("--out", type=Path, default=Path("out/flights/flight.npz"), help="output .npz file")
    c.add_argument(
        "--agent",
        type=Path,
        default=None,
        help="fly a trained agent (model.zip from 'gpbf train-agent') instead of the pilot",
    )
    c.set_defaults(func=_collect)

    t = sub.add_parser("train", help="fit every model kind from recorded flights")
    t.add_argument("flights", nargs="+", type=Path, help="flight .npz files")
    t.add_argument("--out", type=Path, default=Path("out/models"), help="model folder to write")
    t.add_argument(
        "--kinds",
        default="gp,egp,hetgp,sparse",
        help="comma-separated GP kinds (param is always fitted)",
    )
    t.add_argument(
        "--points",
        type=int,
        default=900,
        help="training points per GP after subsampling (paper: 900)",
    )
    t.add_argument("--pseudo", type=int, default=50, help="pseudo-inputs of the sparse GPs (paper: 50)")
    t.add_argument("--restarts", type=int, default=2, help="optimiser restarts per exact GP output")
    t.add_argument("--max-iter", type=int, default=100, help="L-BFGS-B iterations per restart")
    t.add_argument("--hetero-iterations", type=int, default=2, help="EM rounds of the heteroscedastic GPs")
    t.add_argument(
        "--sparse-iter", type=int, default=120, help="L-BFGS-B iterations of each sparse GP output"
    )
    t.add_argument(
        "--hyper-points",
        type=int,
        default=300,
        help="exact GPs learn hyperparameters on this many random points, then polish them on "
        "all (0: on all points from the start)",
    )
    t.add_argument(
        "--calibration-seconds",
        type=float,
        default=60.0,
        help="noise calibration on the first flight's first SECONDS (at most a quarter of it): "
        "their camera frames are kept out of the observation models and scale each output's "
        "variance, then the process-noise scale is chosen there (0: no calibration)",
    )
    t.add_argument("--seed", type=int, default=0, help="seed of the subsampling and restarts")
    t.set_defaults(func=_train)

    k = sub.add_parser("track", help="run a filter over a flight and score it")
    k.add_argument("flight", type=Path, help="flight .npz file")
    k.add_argument("--models", type=Path, default=Path("out/models"), help="model folder from 'gpbf train'")
    k.add_argument("--filter", choices=("ukf", "ekf", "pf"), default="ukf", help="Bayes filter")
    k.add_argument(
        "--model",
        choices=("param", "gp", "egp", "hetgp", "sparse"),
        default="gp",
        help="model kind",
    )
    k.add_argument("--particles", type=int, default=2000, help="particles of the PF")
    k.add_argument("--seed", type=int, default=0, help="seed of the particle filter")
    k.add_argument("--plot", type=Path, default=None, help="PNG of estimate vs truth with 3-sigma bands")
    k.set_defaults(func=_track)

    a = sub.add_parser("train-agent", help="train an SB3 agent on beliefs")
    a.add_argument("--algo", choices=("ppo", "sac"), default="ppo", help="stable-baselines3 algorithm")
    a.add_argument(
        "--obs",
        choices=("state", "belief", "belief-param", "ellipses"),
        default="belief",
        help="observation: true state, GP belief, parametric belief, or raw ellipses",
    )
    a.add_argument("--task", choices=("hover", "waypoint"), default="hover", help="flight task")
    a.add_argument("--filter", choices=("ukf", "ekf", "pf"), default="ekf", help="filter of belief variants")
    a.add_argument(
        "--model",
        choices=("gp", "egp", "hetgp", "sparse"),
        default="gp",
        help="GP model kind of the 'belief' variant",
    )
    a.add_argument("--models", type=Path, default=None, help="model folder (needed for belief variants)")
    a.add_argument("--timesteps", type=int, default=50_000, help="training environment steps")
    a.add_argument("--n-envs", type=int, default=1, help="parallel envs, each with its own filter")
    a.add_argument("--eval-freq", type=int, default=5000, help="steps between evaluations")
    a.add_argument("--eval-episodes", type=int, default=5, help="episodes of the final evaluation")
    a.add_argument("--seed", type=int, default=0, help="seed of the agent and the envs")
    a.add_argument("--out", type=Path, default=Path("out/agent"), help="output folder")
    a.set_defaults(func=_train_agent)

    e = sub.add_parser("eval-agent", help="evaluate a saved agent")
    e.add_argument("agent", type=Path, help="model.zip (with agent.json beside it)")
    e.add_argument("--episodes", type=int, default=10, help="evaluation episodes")
    e.add_argument("--seed", type=int, default=1000, help="seed of the first episode")
    e.set_defaults(func=_eval_agent)

    r = sub.add_parser("reproduce", help="run the paper's experiments and write a report")
    r.add_argument(
        "--out", type=Path, default=Path("out/reproduce"), help="output folder (report.md, figures)"
    )
    r.add_argument("--quick", action="store_true", help="small sizes: a few minutes instead of under an hour")
    r.add_argument("--seed", type=int, default=0, help="seed of the flight and the training")
    r.set_defaults(func=_reproduce)

    for s in (c, t, k, a, e, r):
        s.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["serve"]:  # the service has its own parser and lifecycle
        from estimator_service.service.server import main as serve

        return serve(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ValueError, FileNotFoundError) as exc:
        print(f"gpbf {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
