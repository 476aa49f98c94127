"""A seeded, stratified random sample of the mutants ``mutmut`` has not run yet.

Running every mutant of the GP and model code takes hours on 2 cores (each mutant retrains
the GPs its tests need). Random mutant sampling (Wong & Mathur, J. Systems and Software
31(3), 1995; Zhang et al., ICSE 2013) estimates the killed ratio of the rest at a fraction of
the cost: per module, ``ceil(fraction * not_run)`` of its unrun mutants are drawn without
replacement (every unrun mutant of a module matching ``--full`` is taken). The names are
printed one per line (for ``mutmut run``) and written, with the seed and fraction, to
``sample.json`` beside this script, which ``summarise.py`` reads to estimate the killed
ratio over all configured mutants with a 95 % interval.

Run from the repository root after ``mutmut run`` has generated ``mutants/``::

    mutmut run $(python docs/results/mutation/sample.py --fraction 0.1 --seed 0)
"""

from __future__ import annotations

import argparse
import fnmatch
import json
import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # summarise.py, beside this script: the one list of mutmut's statuses
from summarise import MUTANTS, NOT_RUN  # noqa: E402

SAMPLE = HERE / "sample.json"
FULL = ("estimator_service/filters/*", "estimator_service/service/limits.py")


def unrun_by_module(also: frozenset[str] = frozenset()) -> dict[str, list[str]]:
    """Per mutated module, its mutants not run yet, and those whose status is in ``also``
    (e.g. ``{"timeout"}``, to run them again) (sorted names)."""
    return by_status(frozenset(NOT_RUN) | also)


def by_status(statuses: frozenset[str]) -> dict[str, list[str]]:
    """Per mutated module, its mutants whose mutmut status is one of ``statuses`` (sorted)."""
    from mutmut.mutation.data import SourceFileMutationData
    from mutmut.stats import status_by_exit_code
    from mutmut.utils.file_utils import walk_mutatable_files

    out: dict[str, list[str]] = {}
    for path in walk_mutatable_files():
        data = SourceFileMutationData(path=path)
        data.load()
        out[str(path)] = sorted(
            k for k, c in data.exit_code_by_key.items() if status_by_exit_code[c] in statuses
        )
    return out


def draw(
    unrun: dict[str, list[str]], fraction: float, seed: int, full: tuple[str, ...]
) -> dict[str, list[str]]:
    """Per module, the sampled names: all of a ``full`` module, else ``ceil(fraction * n)``."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    rng = np.random.default_rng(seed)
    out = {}
    for module, names in sorted(unrun.items()):
        k = len(names) if any(fnmatch.fnmatch(module, g) for g in full) else math.ceil(fraction * len(names))
        out[module] = sorted(rng.choice(names, size=k, replace=False).tolist()) if k else []
    return out


def write_record(
    path: Path, unrun: dict[str, list[str]], picked: dict[str, list[str]], seed: int, fraction: float,
    full: list[str],
) -> None:  # fmt: skip
    """The draw's record (``sample.json``): its settings, each module's unrun mutants counted
    (``population``) and the names drawn (``sample``)."""
    doc = {
        "seed": seed, "fraction": fraction, "full": list(full),
        "population": {m: len(v) for m, v in unrun.items() if v},
        "sample": {m: v for m, v in picked.items() if v},
    }  # fmt: skip
    path.write_text(json.dumps(doc, indent=1) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fraction", type=float, default=0.1, help="share of each module's unrun mutants")
    ap.add_argument("--seed", type=int, default=0, help="seed of the draw")
    ap.add_argument("--full", nargs="*", default=list(FULL), help="module globs run completely")
    ap.add_argument("--out", type=Path, default=SAMPLE, help="where the sample is recorded")
    args = ap.parse_args(argv)
    if not MUTANTS.is_dir():
        print("no mutants/ folder here: run `mutmut run` from the repository root first", file=sys.stderr)
        return 2
    unrun = unrun_by_module()
    picked = draw(unrun, args.fraction, args.seed, tuple(args.full))
    write_record(args.out, unrun, picked, args.seed, args.fraction, args.full)
    print("\n".join(n for names in picked.values() for n in names))
    return 0


if __name__ == "__main__":
    sys.exit(main())
