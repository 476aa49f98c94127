"""``make mutate-sample`` and ``make mutate``: a mutation run that can stop and go on.

The sampled run took 87 minutes on 2 cores (2026-12-05: 2,540 mutants, timeouts most of the
time), the whole run hours more: longer than a working session. mutmut records each
mutant's result as it finishes, so a stopped run loses only the
mutants that were running. Started again on the same code with the same draw settings, this
script runs only the mutants that have no result yet; otherwise it starts afresh (removing
``mutants/``), so every result of one run comes from one code version.

- A fresh run: ``mutants/`` is removed and the run's record ``mutants/run.json`` (the code's
  fingerprint, the draw's settings, when it began) is written; ``mutmut`` runs the mutants
  of ``--first`` (the service's limits: it also makes every module's mutants); then
  ``sample.py`` draws from the mutants not yet run (every one of a ``--full`` module,
  ``--fraction`` of each other module's; ``--fraction 1`` is the whole run) into
  ``mutants/sample.json``.
- Going on: the first mutants still without a result, the draw if it was not made, then the
  drawn mutants still without a result.
- Then ``summarise.py`` writes ``results.json`` and ``report.md`` (``--out``: ``sampled/``, or
  ``full/`` with ``--fraction 1``), with the run's record, and the draw is copied beside them
  as ``sample.json``; for a folder beside this script, ``combine.py`` then scores every run
  kept here into this folder's ``results.json``. Mutants still without a
  result (mutmut stopped early) are named and the exit status is 1.

The fingerprint is the SHA-256 of ``pyproject.toml``, ``constraints.txt``, the Python and
mutmut versions and every Python file under the tests and the folders ``[tool.mutmut]``
names (``source_paths``, ``also_copy``), except this folder's tools, which read the results
and do not run the code under test: the code the tests run, not only the mutated modules
(mutmut keeps its first copy of the modules it does not mutate). ``[tool.mutmut]``'s
timeout settings (``timeout_multiplier``, ``timeout_constant``) are left out of it: they
decide only when a mutant counts as timed out, so a run goes on after they change, running
its timed-out mutants again under the new settings (the record keeps the settings of each
part of the run, ``timeouts``).

Run from the repository root: ``python docs/results/mutation/mutate_sample.py
--max-children 2``.
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from importlib.metadata import version
from pathlib import Path

from estimator_service.files import atomic_write_text

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # sample.py and summarise.py, beside this script
import combine  # noqa: E402
import run_mutmut  # noqa: E402
import sample  # noqa: E402
import summarise  # noqa: E402

#: mutants run first, making every module's mutants before the draw
FIRST = "estimator_service.service.limits*"
MUTANTS, RUN = summarise.MUTANTS, summarise.RUN_RECORD
SAMPLE = MUTANTS / "sample.json"
DRAW_KEYS = ("fraction", "seed", "full", "first")
#: survivors rerun per mutmut call (each call starts afresh: its statistics, the fixtures'
#: collection, 13 s here, and the fork server; a stopped rerun loses at most one batch)
RERUN_BATCH = 16
#: ``[tool.mutmut]`` keys that only decide when a mutant counts as timed out
TIMEOUT_KEYS = ("timeout_multiplier", "timeout_constant")


def code_folders(root: Path = Path(".")) -> list[str]:
    """The folders whose Python files make a run's code version: the tests and those
    ``[tool.mutmut]`` names (``source_paths``, ``also_copy``)."""
    import tomllib

    table = tomllib.loads((root / "pyproject.toml").read_text()).get("tool", {}).get("mutmut", {})
    return sorted({"tests", *table.get("source_paths", []), *table.get("also_copy", [])})


def fingerprint(root: Path = Path(".")) -> str:
    """SHA-256 over the Python and mutmut versions and the relative path and bytes of
    ``pyproject.toml``, ``constraints.txt`` and every ``*.py`` under :func:`code_folders`
    (caches and this folder's tools left out)."""
    root = root.resolve()
    h = hashlib.sha256(f"python {platform.python_version()} mutmut {version('mutmut')}\0".encode())
    files = [
        p for d in code_folders(root) for p in (root / d).rglob("*.py")
        if "__pycache__" not in p.parts and HERE not in p.resolve().parents
    ]  # fmt: skip
    for p in sorted([*files, root / "pyproject.toml", root / "constraints.txt"]):
        if p.is_file():
            text = p.read_bytes()
            if p.name == "pyproject.toml":  # without the timeout settings (see timeouts)
                keys = tuple(k.encode() for k in TIMEOUT_KEYS)
                text = b"".join(ln for ln in text.splitlines(True) if ln.split(b"=")[0].strip() not in keys)
            h.update(str(p.relative_to(root)).encode() + b"\0" + text + b"\0")
    return h.hexdigest()


def timeouts() -> dict[str, float]:
    """``[tool.mutmut]``'s timeout settings as mutmut reads them (its defaults where unset)."""
    from mutmut.configuration import config

    return {k: float(getattr(config(), k)) for k in TIMEOUT_KEYS}


def _save(record: dict) -> None:
    """Write the run's record ``mutants/run.json`` whole or not at all."""
    atomic_write_text(RUN, json.dumps(record, indent=1) + "\n")


def _mutmut(max_children: int, names: list[str], env: dict[str, str] | None = None) -> None:
    """``run_mutmut.py run`` in its own process (``env``: variables added); stops this
    script if it fails."""
    cmd = [sys.executable, str(HERE / "run_mutmut.py"), "run", "--max-children", str(max_children), *names]
    if subprocess.run(cmd, env={**os.environ, **(env or {})}).returncode != 0:
        raise SystemExit("mutate_sample.py: mutmut failed (see above); the results so far are kept")


def _resumable(record: dict | None, settings: dict) -> str:
    """Why the run in ``mutants/`` cannot go on (empty: it can)."""
    if record is None:
        return "no run recorded in mutants/run.json"
    if record.get("fingerprint") != settings["fingerprint"]:
        return f"the code changed since the run began {record.get('began', '?')}"
    changed = [k for k in DRAW_KEYS if record.get(k) != settings[k]]
    return f"other draw settings ({', '.join(changed)})" if changed else ""


def pending(drawn: dict[str, list[str]], unrun: dict[str, list[str]]) -> list[str]:
    """The drawn mutants (per module) that have no result yet, in module order."""
    left = {m: set(names) for m, names in unrun.items()}
    return [n for m, names in sorted(drawn.items()) for n in names if n in left.get(m, ())]


def _unrun(also: frozenset[str] = frozenset()) -> dict[str, list[str]]:
    """Per module, its mutants without a result (or with a status in ``also``); none
    before mutmut has made them."""
    return sample.unrun_by_module(also) if any(MUTANTS.rglob("*.meta")) else {}


def _first_left(pattern: str, also: frozenset[str] = frozenset()) -> list[str]:
    """The ``--first`` mutants still to run (or with a status in ``also``): all (the
    pattern) before mutmut made them, also when a run stopped while mutmut was making them
    left some modules' mutants and not yet the pattern's (the first pass was then skipped)."""
    unrun = _unrun(also)
    if not unrun or not _made(pattern):
        return [pattern]
    return [n for names in unrun.values() for n in names if fnmatch.fnmatch(n, pattern)]


def _made(pattern: str) -> bool:
    """Whether mutmut has made any mutant that ``pattern`` names, run or not."""
    from mutmut.stats import status_by_exit_code

    made = sample.by_status(frozenset(status_by_exit_code.values()))
    return any(fnmatch.fnmatch(n, pattern) for names in made.values() for n in names)


def _draw(settings: dict) -> dict[str, list[str]]:
    """The draw among the mutants not run, recorded in ``mutants/sample.json``."""
    unrun = sample.unrun_by_module()
    drawn = sample.draw(unrun, settings["fraction"], settings["seed"], tuple(settings["full"]))
    sample.write_record(SAMPLE, unrun, drawn, settings["seed"], settings["fraction"], settings["full"])
    return drawn


def _settings(argv: list[str] | None) -> tuple[argparse.Namespace, dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--max-children", type=int, default=2, help="mutants run at once")
    ap.add_argument("--fraction", type=float, default=0.1, help="share of other modules' mutants (1: all)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the draw")
    ap.add_argument("--full", nargs="*", default=list(sample.FULL), help="module globs run completely")
    ap.add_argument("--first", default=FIRST, help="mutants run before the draw (mutmut's pattern)")
    ap.add_argument(
        "--out",
        type=Path,
        help="folder for results.json and report.md (default: sampled/ "
        "beside this script, full/ with --fraction 1; combine.py then scores all runs here)",
    )
    ap.add_argument("--reasons", type=Path, default=HERE / "reasons.json", help="survivors' reasons")
    args = ap.parse_args(argv)
    if not 0.0 < args.fraction <= 1.0:
        ap.error(f"--fraction must be in (0, 1], got {args.fraction}")
    if args.max_children < 1:
        ap.error(f"--max-children must be at least 1, got {args.max_children}")
    if args.seed < 0:
        ap.error(f"--seed must be at least 0, got {args.seed}")
    if not args.first.strip():
        ap.error("--first must name mutants (a mutmut pattern such as 'pkg.module*')")
    args.out = args.out or HERE / ("full" if args.fraction >= 1 else "sampled")
    if args.out.resolve() == HERE:
        ap.error(f"--out {args.out}: that folder holds the combined score of all runs (combine.py)")
    settings = {"fingerprint": fingerprint(), "fraction": args.fraction, "seed": args.seed,
                "full": list(args.full), "first": args.first, "timeouts": timeouts()}  # fmt: skip
    return args, settings


def _survivors_again(max_children: int, record: dict, drawn: dict[str, list[str]], first: str) -> None:
    """Run the run's surviving mutants again, each once, against their tests and every test
    sharing a wider-scoped fixture with them (``run_mutmut.py``'s ``SHARED_FIXTURES``: mutmut
    maps a function that only a module- or session-scoped fixture calls to the first test that
    built the fixture); the record lists them (``survivors_rerun``) after each batch of
    :data:`RERUN_BATCH`, so a stopped rerun goes on where it stopped."""
    done = set(record.get("survivors_rerun", []))
    mine = {n for names in drawn.values() for n in names}
    survived = [n for names in sample.by_status(frozenset({"survived"})).values() for n in names
                if (n in mine or fnmatch.fnmatch(n, first)) and n not in done]  # fmt: skip
    if not survived:
        return
    print(
        f"mutate_sample.py: {len(survived)} survivors run again with the tests sharing their fixtures",
        flush=True,
    )
    for i in range(0, len(survived), RERUN_BATCH):
        batch = survived[i : i + RERUN_BATCH]
        _mutmut(max_children, batch, {run_mutmut.SHARED_FIXTURES: "1"})
        done |= set(batch)
        record["survivors_rerun"] = sorted(done)
        _save(record)


def _new_timeouts(record: dict, settings: dict) -> frozenset[str]:
    """``{"timeout"}`` when the timeout settings changed since the run's last part (its
    timed-out mutants run again, and the record keeps each part's settings), else empty."""
    if record.get("timeouts") == settings["timeouts"]:
        return frozenset()
    print(f"mutate_sample.py: timeout settings {settings['timeouts']} (the run had "
          f"{record.get('timeouts', 'mutmut 3.8 defaults or unrecorded')}): timed-out mutants run again",
          flush=True)  # fmt: skip
    record["timeouts_before"] = [*record.get("timeouts_before", []), record.get("timeouts")]
    record["timeouts"] = settings["timeouts"]
    _save(record)
    return frozenset({"timeout"})


def main(argv: list[str] | None = None) -> int:
    args, settings = _settings(argv)
    try:
        record = json.loads(RUN.read_text()) if RUN.is_file() else None
    except ValueError:  # a record cut short: nothing to go on from
        record = None
    why = _resumable(record, settings)
    if why:
        print(f"mutate_sample.py: a fresh run ({why}; mutants/ removed)", flush=True)
        shutil.rmtree(MUTANTS, ignore_errors=True)
        MUTANTS.mkdir()
        record = {**settings, "began": time.strftime("%Y-%m-%d %H:%M:%S %Z")}
        _save(record)
    again = _new_timeouts(record, settings)
    first: list[str] = []  # --first mutants to run again with the draw (new timeout settings)
    if not SAMPLE.is_file():
        todo = _first_left(args.first, again)
        if todo:
            _mutmut(args.max_children, todo)
        drawn = _draw(settings)
    else:
        drawn = json.loads(SAMPLE.read_text())["sample"]
        first = _first_left(args.first, again) if again else []
    names = [*first, *pending(drawn, sample.unrun_by_module(again))]
    total = sum(len(v) for v in drawn.values())
    print(f"mutate_sample.py: the run begun {record['began']}: {len(names)} of {total} sampled mutants "
          "left", flush=True)  # fmt: skip
    if names:
        _mutmut(args.max_children, names)
    _survivors_again(args.max_children, record, drawn, args.first)
    status = summarise.main(["--out", str(args.out), "--reasons", str(args.reasons), "--sample", str(SAMPLE)])
    if args.out.resolve() != SAMPLE.parent.resolve():
        shutil.copyfile(SAMPLE, args.out / "sample.json")  # the draw beside the results it gave
    if HERE in args.out.resolve().parents:  # a run kept beside the others: score them all again
        combine.main([])
    left = pending(drawn, sample.unrun_by_module()) + _first_left(args.first)
    if left:
        print(f"mutate_sample.py: {len(left)} mutants still without a result (mutmut stopped early?): "
              "run again to go on", file=sys.stderr)  # fmt: skip
        return 1
    return status


if __name__ == "__main__":
    sys.exit(main())
