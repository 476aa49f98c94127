"""The estimator's commands, usable on any robot's logs: ``train``, ``track``, ``serve``.

``python -m estimator_service train|track|serve ...`` runs them without the simulator;
``gpbf`` offers the same commands (and the simulator's and agents' ones) with the same
options. A log is a flight file (``.npz``), a CSV file of one row per step, a CSV event
log (``--events``) or a ROS bag (``--topics MAPPING.json``), the last three described by
``--system`` (``docs/your-robot.md``; event logs and bags are aligned to the steps by
:func:`estimator_service.events.align`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from estimator_service.cli_args import (
    Parser,
    add_calibration_options,
    add_filter_options,
    add_quiet,
    calibration_options,
    checked_float,
    checked_int,
    filter_options,
    model_kind,
    package_version,
    seed,
)
from estimator_service.files import json_text
from estimator_service.progress import ProgressBar

__all__ = ["add_train_track", "main", "run_track", "run_train"]

USER_ERRORS = (ValueError, OSError)  # a bad value; a file or folder missing, unwritable, in the way


def _system(args: argparse.Namespace):
    if args.system is None:
        return None
    from estimator_service.system import System

    return System.from_json(
        Path(args.system).read_text(encoding="utf-8"), f"system file {str(args.system)!r}"
    )


def _read_log(path: Path, args: argparse.Namespace):
    """The flight of one log under the command's log options (see the module docstring)."""
    from estimator_service.flight import FlightError, load_log

    system = _system(args)
    if not (args.events or args.topics):
        return load_log(path, system)
    from estimator_service.events import align, load_event_csv

    if system is None:
        raise FlightError(f"{str(path)!r}: an event log or ROS bag needs a system description (--system)")
    if args.topics:
        from estimator_service.rosbag import load_rosbag

        log = load_rosbag(path, system, args.topics)
    else:
        log = load_event_csv(path, system)
    flight, report = align(log, control=args.control_rule, control_delay=args.control_delay)
    if not args.quiet:
        print(f"{path}: {report}", file=sys.stderr)
    return flight


def add_log_options(p: argparse.ArgumentParser) -> None:
    """How logs are read: ``--system``, ``--events``, ``--topics``, the control rule and delay."""
    p.add_argument("--system", type=Path, default=None, help="system description JSON (needed but for .npz)")
    p.add_argument("--events", action="store_true", help="CSV logs are event logs (t, stream, values...)")
    p.add_argument(
        "--topics", type=Path, default=None, help="logs are ROS bags read by this topic mapping JSON"
    )
    p.add_argument(
        "--control-rule", choices=("mean", "hold"), default="mean",
        help="event logs and bags: a step's control is the mean of the commands acting in it, or the last",
    )  # fmt: skip
    p.add_argument(
        "--control-delay", type=checked_float(0.0, 60.0), default=None,
        help="event logs and bags: seconds from a command to its effect (default: the description's)",
    )  # fmt: skip


def run_train(args: argparse.Namespace) -> int:
    from estimator_service.training import TrainSettings, available_kinds
    from estimator_service.work import train_with_progress

    flights = [_read_log(p, args) for p in args.logs]
    settings = TrainSettings(
        args.points, args.pseudo, args.restarts, args.max_iter, args.hetero_iterations,
        sparse_iter=args.sparse_iter, hyper_points=args.hyper_points or None,
        calibration_seconds=args.calibration_seconds, **calibration_options(args),
    )  # fmt: skip
    avail = available_kinds(flights[0].system)
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()] if args.kinds else list(avail)
    if "param" in avail and "param" not in kinds:
        kinds.insert(0, "param")
    timings = train_with_progress(
        "train", flights, args.out, kinds=kinds, settings=settings, seed=args.seed, enabled=not args.quiet
    )
    from estimator_service.models.calibration import calibration_choices

    seconds = {k: round(v, 1) for k, v in timings.items()}
    print(
        json_text(
            {"models": str(args.out), "train_seconds": seconds, "calibration": calibration_choices(args.out)}
        )
    )
    return 0


def run_track(args: argparse.Namespace) -> int:
    from estimator_service.factory import build_filter
    from estimator_service.tracking import track_flight

    options = filter_options(args)  # an option mistake before any file is read
    flight = _read_log(args.log, args)
    args.model = model_kind(args)
    filt = build_filter(args.filter, args.model, args.models, **options)
    with ProgressBar(f"track {args.filter}/{args.model}", len(flight) - 1, enabled=not args.quiet) as bar:
        result = track_flight(filt, flight, rng=np.random.default_rng(args.seed), on_step=bar.update_to)
    scores = result.scores()
    for name, value in scores.items():
        print(f"{name:>20s}: {value:.4g}")
    if args.plot:
        from estimator_service.plots import (
            normalised_path,
            plot_normalised,
            plot_reliability,
            plot_tracking,
            reliability_path,
        )

        title = f"GP-BayesFilter {args.filter.upper()} / {args.model}"
        plot_tracking(result, args.plot, title=title)
        plot_normalised(result, normalised_path(args.plot), title=f"{title}: normalised errors")
        plot_reliability({title: result}, reliability_path(args.plot), title=f"{title}: reliability")
        print(f"wrote {args.plot}, {normalised_path(args.plot)} and {reliability_path(args.plot)}")
    print(json_text({k: round(v, 4) for k, v in scores.items()}))
    return 0


def add_train_track(sub: argparse._SubParsersAction) -> None:
    """The ``train`` and ``track`` subcommands (shared by ``gpbf``)."""
    from estimator_service.training import TrainSettings

    d = TrainSettings()  # the defaults have one owner
    t = sub.add_parser("train", help="fit every model kind from logs", description=run_train.__doc__)
    t.add_argument("logs", nargs="+", type=Path, help="flight .npz, CSV or event logs, or ROS bags")
    add_log_options(t)
    t.add_argument(
        "--out", type=Path, default=Path("out/models"), help="model folder to write (replaced whole)"
    )
    t.add_argument("--kinds", default="", help="comma-separated GP kinds (default: all the system can train)")
    t.add_argument(
        "--points", type=checked_int(2, 100_000), default=d.n_points, help="training points per GP"
    )
    t.add_argument(
        "--pseudo", type=checked_int(1, 10_000), default=d.n_pseudo, help="pseudo-inputs of the sparse GPs"
    )
    t.add_argument(
        "--restarts", type=checked_int(1, 100), default=d.restarts, help="optimiser restarts per exact GP"
    )
    t.add_argument(
        "--max-iter", type=checked_int(1, 100_000), default=d.max_iter, help="L-BFGS-B iterations per restart"
    )
    t.add_argument(
        "--hetero-iterations",
        type=checked_int(1, 100),
        default=d.hetero_iterations,
        help="EM rounds of the hetGPs",
    )
    t.add_argument(
        "--sparse-iter", type=checked_int(1, 100_000), default=d.sparse_iter, help="iterations per sparse GP"
    )
    t.add_argument(
        "--hyper-points", type=checked_int(0, 100_000), default=d.hyper_points or 0,
        help="exact GPs learn hyperparameters on this many random points, then polish on all (0: all)",
    )  # fmt: skip
    t.add_argument(
        "--calibration-seconds", type=checked_float(0.0, 1e6), default=d.calibration_seconds,
        help="noise calibration on blocks of SECONDS of the first log (at most a quarter each; 0: none)",
    )  # fmt: skip
    add_calibration_options(t)
    t.add_argument("--seed", type=seed, default=0, help="seed of the subsampling and restarts")
    add_quiet(t)
    t.set_defaults(func=run_train)

    k = sub.add_parser("track", help="run a filter over a log and score it")
    k.add_argument("log", type=Path, help="flight .npz, CSV or event log, or ROS bag")
    add_log_options(k)
    add_filter_options(k)
    k.add_argument("--seed", type=seed, default=0, help="seed of the particle filter")
    k.add_argument(
        "--plot", type=Path, default=None,
        help="PNG of estimate vs truth with 3-sigma bands (and <name>_normalised.png: error/sd per group)",
    )  # fmt: skip
    add_quiet(k)
    k.set_defaults(func=run_track)


def build_parser(prog: str = "python -m estimator_service") -> Parser:
    p = Parser(prog=prog, description=__doc__)
    p.add_argument("--version", action="version", version=f"gpbf {package_version()}")
    sub = p.add_subparsers(dest="command", required=True, parser_class=Parser)
    sub.add_parser("serve", help="run the estimator service (see 'serve --help')", add_help=False)
    sub.add_parser("router", help="run a zenoh router for a fleet (see 'router --help')", add_help=False)
    add_train_track(sub)
    return p


def run(args: argparse.Namespace, prog: str) -> int:
    """Run a parsed command; a user's mistake (bad file, bad value) is one line, exit code 2."""
    return guarded(f"{prog} {args.command}", args, lambda: args.func(args))


def guarded(prog: str, args: argparse.Namespace, work: Callable[[], int]) -> int:
    """Check ``args``' output paths, then run ``work``; a user's mistake (``USER_ERRORS``)
    is one line naming ``prog``, and exit code 2."""
    try:
        _check_outputs(args)
        return int(work())
    except USER_ERRORS as exc:
        print(f"{prog}: error: {_said(exc)}", file=sys.stderr)
        return 2


OUTPUT_OPTIONS = ("out", "plot")  # the options that name a file or folder a command writes


def _check_outputs(args: argparse.Namespace) -> None:
    """Before any work: every output path's nearest existing ancestor is a folder (else the
    run would end, after its work, unable to write), and ``--plot`` has matplotlib."""
    for name in OUTPUT_OPTIONS:
        value = getattr(args, name, None)
        if value is None:
            continue
        if name == "plot":
            _need_matplotlib()
        for parent in Path(value).absolute().parents:
            if parent.exists():
                if not parent.is_dir():
                    raise NotADirectoryError(
                        20, f"cannot write --{name} {value}: not a directory", str(parent)
                    )
                break


def _need_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise ValueError("--plot needs matplotlib; install it with: pip install 'gpbf[plots]'") from None


def _said(exc: Exception) -> str:
    """A user error in one line: a file system error names the path and what is wrong."""
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        hint = (
            " (a folder on the path is a file)"
            if isinstance(exc, (FileExistsError, NotADirectoryError))
            else ""
        )
        return f"{exc.filename}: {exc.strerror.lower()}{hint}"
    return str(exc)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["router"]:
        from estimator_service.service.router import main as router

        return router(argv[1:])
    if argv[:1] == ["serve"]:
        from estimator_service.service.server import main as serve

        return serve(argv[1:])
    return run(build_parser().parse_args(argv), "python -m estimator_service")
