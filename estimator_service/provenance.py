"""Where a result came from: the code version, the command line and the wall time, recorded
by an experiment beside its figures and shown in one line at the top of its report."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from estimator_service.cli_args import package_version

__all__ = ["code_version", "named_argv", "provenance", "provenance_line"]

_ROOT = Path(__file__).resolve().parents[1]


def code_version() -> str:
    """The checkout's commit (``+changes`` when the working tree differs from it), or the
    installed package's version outside a git checkout."""
    try:
        run = {"cwd": _ROOT, "capture_output": True, "text": True, "timeout": 10, "check": True}
        commit = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], **run).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], **run).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return f"gpbf {package_version()}"
    return f"{commit}{'+changes' if dirty else ''}"


def named_argv(argv: list[str] | None = None) -> list[str]:
    """``argv`` (default: this process's) with its program by name only: no machine's paths;
    this process's command run as ``python -m module`` is recorded so (its file's name alone,
    e.g. ``rl.py``, cannot be run)."""
    if argv is None:
        orig = list(getattr(sys, "orig_argv", []))
        for i, arg in enumerate(orig[1:], start=1):  # python [options] -m module / -mmodule args
            module, rest = (orig[i + 1 : i + 2], orig[i + 2 :]) if arg == "-m" else ([arg[2:]], orig[i + 1 :])
            if arg.startswith("-m") and module and rest == sys.argv[1:]:
                return ["python", "-m", module[0], *sys.argv[1:]]
    argv = list(sys.argv if argv is None else argv) or [""]
    return [Path(argv[0]).name, *argv[1:]]


def provenance(wall_s: float, argv: list[str] | None = None, code: str | None = None) -> dict[str, object]:
    """``{"code", "command", "wall_s"}`` of the running experiment (the command's program
    by its name, e.g. ``gpbf reproduce --quick``); ``code``: :func:`code_version` taken when
    the experiment started (default: now), since the checkout may move while it runs."""
    command = " ".join(named_argv(argv))
    return {"code": code or code_version(), "command": command, "wall_s": round(wall_s, 1)}


def provenance_line(p: dict[str, object]) -> str:
    """The report's header line for a :func:`provenance` record."""
    minutes = float(p["wall_s"]) / 60  # type: ignore[arg-type]
    return f"Provenance: code {p['code']}; command `{p['command']}`; wall time {minutes:.1f} min."
