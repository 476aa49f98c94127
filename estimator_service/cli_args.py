"""Command-line plumbing shared by ``gpbf`` and ``python -m estimator_service``: a parser
whose errors are one line and exit code 2, range-checked option types, and the options
that several commands share (one definition, one default)."""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, NoReturn

from estimator_service.filters.adaptive import ADAPT_RATE
from estimator_service.filters.particle import UPDATE_RULES

__all__ = [
    "DEFAULT_FILTER",
    "DEFAULT_MODEL",
    "Parser",
    "add_filter_options",
    "add_quiet",
    "checked_float",
    "checked_int",
    "filter_options",
    "model_kind",
    "package_version",
    "seed",
]

DEFAULT_FILTER = "ekf"
DEFAULT_MODEL = "gp"
FILTERS = ("ekf", "ukf", "pf")
MODELS = ("param", "gp", "egp", "hetgp", "sparse")


def package_version() -> str:
    try:
        return version("gpbf")
    except PackageNotFoundError:  # run from a checkout without installing
        return "0+unknown"


class Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` that shows defaults in ``--help`` and reports a mistake as one
    line (``prog: error: ...``) with exit code 2, without the usage block."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        print(f"{self.prog}: error: {message} (see '{self.prog} --help')", file=sys.stderr)
        raise SystemExit(2)

    def parse_args(self, args=None, namespace=None):  # type: ignore[override]
        """As argparse's, but an option the chosen subcommand does not know is that
        subcommand's error (``gpbf track: error: ...``, see ``gpbf track --help``), and an
        unknown option without a subcommand is named (``gpbf --bogus``), not reported as a
        missing command."""
        subs = [a for a in self._actions if isinstance(a, argparse._SubParsersAction)]
        required = [s.required for s in subs]
        for s in subs:  # checked below, after the unknown options
            s.required = False
        try:
            ns, extras = self.parse_known_args(args, namespace)
        finally:
            for s, r in zip(subs, required, strict=True):
                s.required = r
        chosen = subs[0].choices.get(getattr(ns, subs[0].dest, None)) if subs else None
        if extras:
            (chosen or self).error(f"unrecognized arguments: {' '.join(extras)}")
        if subs and required[0] and chosen is None:
            self.error(f"the following arguments are required: {subs[0].metavar or subs[0].dest}")
        return ns


_ROLE = re.compile(r":[a-z]+:`(?P<short>~?)(?P<name>[^`]+)`")  # :func:`~pkg.mod.f`


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps the description's line breaks and appends ``(default: X)`` to an option's help
    once: not where the help already names its default, not for a required option, a flag
    or an option whose default is nothing (None, an empty string or list, False). A default
    of 0 is shown (``0 == False``: the test is by identity)."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        """The description as plain text: a module docstring's reST roles and literals
        (``:func:`~a.b.f```, double backquotes) read as ``f`` and the bare words."""
        text = _ROLE.sub(lambda m: m["name"].rsplit(".", 1)[-1] if m["short"] else m["name"], text)
        return super()._fill_text(text.replace("``", ""), width, indent)

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text, default = action.help or "", action.default
        nothing = default is None or default is False or default is argparse.SUPPRESS or default in ("", [])
        quiet = (action.required or nothing or "default" in text or action.nargs == 0
                 or not action.option_strings)  # fmt: skip
        return text if quiet else f"{text} (default: %(default)s)"


def checked_int(low: int | None = None, high: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer in ``[low, high]``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if (low is not None and value < low) or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be in {_range(low, high)}, got {value}")
        return value

    parse.__name__ = "integer"
    return parse


def checked_float(
    low: float | None = None, high: float | None = None, *, low_open: bool = False
) -> Callable[[str], float]:
    """An argparse type: a finite number in ``[low, high]`` (``(low, high]`` with ``low_open``)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        below = low is not None and (value <= low if low_open else value < low)
        if not math.isfinite(value) or below or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be in {_range(low, high, low_open)}, got {text}")
        return value

    parse.__name__ = "number"
    return parse


def _range(low: float | None, high: float | None, low_open: bool = False) -> str:
    lo = "-inf" if low is None else str(low)
    return f"{'(' if low_open or low is None else '['}{lo}, {'inf)' if high is None else f'{high}]'}"


seed = checked_int(0, 2**63 - 1)


def add_quiet(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress output")


def add_calibration_options(p: argparse.ArgumentParser) -> None:
    """``--calibration-folds`` and ``--calibration-refit`` / ``--calibration-condition-only``
    (defaults: ``TrainSettings``')."""
    from estimator_service.crossfit import MAX_FOLDS
    from estimator_service.training import TrainSettings

    p.add_argument(
        "--calibration-folds", type=checked_int(1, MAX_FOLDS), default=TrainSettings.calibration_folds,
        help="calibration folds: blocks spread over a single log, or with several logs each of the first "
        "FOLDS logs held out whole in turn",
    )  # fmt: skip
    refit = p.add_mutually_exclusive_group()
    refit.add_argument(
        "--calibration-refit", dest="calibration_refit", action="store_true",
        default=TrainSettings.calibration_refit,
        help="each fold learns its own hyperparameters (one more fit per fold and kind)",
    )  # fmt: skip
    refit.add_argument(
        "--calibration-condition-only", dest="calibration_refit", action="store_false",
        help="folds keep the final models' hyperparameters and are only conditioned on their data "
        "(the default)",
    )  # fmt: skip


def calibration_options(args: argparse.Namespace) -> dict[str, Any]:
    """``TrainSettings`` keyword arguments from :func:`add_calibration_options`' arguments."""
    return {"calibration_folds": args.calibration_folds, "calibration_refit": args.calibration_refit}


def add_filter_options(p: argparse.ArgumentParser, *, models_required: bool = False) -> None:
    """``--models``, ``--filter``, ``--model`` and ``--particles``, as every command has them."""
    default = None if models_required else Path("out/models")
    p.add_argument(
        "--models",
        type=Path,
        required=models_required,
        default=default,
        help="model folder from 'gpbf train'",
    )
    p.add_argument("--filter", choices=FILTERS, default=DEFAULT_FILTER, help="Bayes filter")
    p.add_argument(
        "--model", choices=MODELS, default=None,
        help="model kind (default: the first the model folder has of hetgp, egp, gp, sparse, param, "
        "the paper's ranking)",
    )  # fmt: skip
    p.add_argument("--particles", type=checked_int(10, 1_000_000), default=2000, help="particles of the PF")
    p.add_argument(
        "--pf-update", choices=UPDATE_RULES, default=None,
        help="PF: weight by the likelihood as the paper's Table 1, or bridge to an ensemble Kalman move "
        "when a reading is too sharp for the particles (default: bridge for learned models, table1 for "
        "param)",
    )  # fmt: skip
    p.add_argument(
        "--adapt", type=checked_float(0.0, 1.0), default=None, metavar="RATE",
        help=f"EKF/UKF: inflate the process noise while NIS/dof stays above its calibrated level at this "
        f"rate (0: off; default {ADAPT_RATE}, or off where the models' calibration chose the plain filter)",
    )  # fmt: skip


def model_kind(args: argparse.Namespace) -> str:
    """``--model``, or the kind the ``--models`` folder ranks first
    (:func:`~estimator_service.factory.preferred_kind`; :data:`DEFAULT_MODEL` without a folder)."""
    if args.model is not None:
        return args.model
    if args.models is None or not Path(args.models).is_dir():
        return DEFAULT_MODEL
    from estimator_service.factory import preferred_kind

    return preferred_kind(args.models)


def filter_options(args: argparse.Namespace) -> dict[str, object]:
    """The filter's own options from :func:`add_filter_options`' arguments."""
    if args.pf_update is not None and args.filter != "pf":
        raise ValueError(f"--pf-update: only the particle filter has an update rule, not {args.filter}")
    if args.filter == "pf":
        rule = {} if args.pf_update is None else {"update_rule": args.pf_update}
        return {"n_particles": args.particles, **rule}
    return {} if args.adapt is None else {"adapt_rate": args.adapt}
