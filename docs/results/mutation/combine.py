"""One score over every configured module from the mutation runs kept in this folder.

A whole ``make mutate`` takes longer than a working session on 2 cores, so modules are run
in full a few at a time (``mutate_sample.py --full ...``), each run in a folder of its own
beside this script (``results.json`` with its ``run`` record). This script reads every such
``results.json`` below this folder (``sampled/`` and the per-run folders; not its own
output), takes for each module the latest run that ran *all* its mutants as one of the
run's ``--full`` modules, and writes ``results.json`` and ``report.md`` here:

- per module: that run's counts, its folder, when it began, its timeout settings and whether
  the module's code is still the one it ran (``source_current``): the same bytes (SHA-256),
  or the same code with other docstrings or comments (``summarise.code_hash``, the version
  the run saw found in the repository's history by its SHA-256; its mutants are the same,
  under the same names); a module no run took in full is listed in ``not_in_full`` with
  nothing counted;
- in total over the modules run in full: ``killed`` (timed-out mutants apart, ``timeout``),
  ``survived``, ``no_tests``, ``killed_ratio`` (timeouts counted as killed, mutmut's rule)
  and ``killed_ratio_without_timeouts`` (its lower bound: a timed-out mutant is not always a
  killed one, ``gp_models_base/README.md``);
- every survivor of those runs with its reason as ``reasons.json`` gives it today (a
  mutant's own reason only where it was written for the same change: mutmut numbers a
  function's mutants in order, so a name can stand for another change after a code edit),
  and
  ``killed_ratio_with_tests_added``: survivors whose reason says a test was added after the
  run (each failing with its mutant applied by hand) counted as killed.

Run from the repository root: ``python docs/results/mutation/combine.py``.
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # summarise.py, beside this script
import summarise  # noqa: E402

from estimator_service.provenance import code_version  # noqa: E402

COUNTS = ("killed", "timeout", "survived", "no_tests")
TEST_ADDED = "test added after this run"
#: what runs made before their record kept the timeout settings were measured with
UNRECORDED_TIMEOUTS = "timeout_constant 1 s (mutmut's), multiplier 5 or 15"


def runs(folder: Path) -> list[tuple[Path, dict]]:
    """Every run's ``results.json`` below ``folder`` (not a combined one), oldest first."""
    found = []
    for path in sorted(folder.rglob("results.json")):
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise SystemExit(f"combine.py: {path} is not a readable results.json: {exc}") from None
        if not doc.get("combined") and "run" in doc and "modules" in doc:
            found.append((path.parent, doc))
    return sorted(found, key=lambda fd: fd[1]["run"].get("began", ""))


def latest_full(found: list[tuple[Path, dict]], root: Path) -> dict[str, tuple[Path, dict, dict]]:
    """Per module, the latest run that ran all its mutants as a ``--full`` module:
    ``(folder, its entry, the run's results)``."""
    best: dict[str, tuple[Path, dict, dict]] = {}
    for folder, doc in found:  # oldest first: a later run replaces an earlier one
        for module, entry in doc["modules"].items():
            full = any(fnmatch.fnmatch(module, g) for g in doc["run"].get("full", []))
            if full and entry["not_run"] == 0:
                best[module] = (folder.relative_to(root), entry, doc)
    return best


def _ratio(killed: float, total: int) -> float | None:
    return round(killed / total, 4) if total else None


def _committed_versions(module: str) -> list[bytes]:
    """Every committed version of ``module``, newest first: one ``git log`` and one ``git
    cat-file --batch`` (its output: ``<id> blob <size>`` and the bytes, or ``<name> missing``)."""
    log = subprocess.run(["git", "log", "--format=%H", "--", module], capture_output=True, check=True,
                         timeout=60).stdout.decode().split()  # fmt: skip
    names = "".join(f"{commit}:{module}\n" for commit in log).encode()
    batch = subprocess.run(["git", "cat-file", "--batch"], input=names, capture_output=True, check=True,
                           timeout=60).stdout  # fmt: skip
    versions, pos = [], 0
    while pos < len(batch):
        end = batch.index(b"\n", pos)
        head = batch[pos:end].split()
        size = int(head[2]) if len(head) == 3 and head[1] == b"blob" else -1
        versions += [batch[end + 1 : end + 1 + size]] if size >= 0 else []
        pos = end + 1 + (size + 1 if size >= 0 else 0)
    return versions


def code_in_history(module: str, sha256: str) -> str | None:
    """:func:`summarise.code_hash` of the version of ``module`` (a path from the repository
    root) whose bytes have ``sha256``, looked up in the git history of the current directory;
    None when no committed version has them (or git cannot tell)."""
    try:
        versions = _committed_versions(module)
    except (OSError, ValueError, subprocess.SubprocessError):
        return None
    same = (v for v in versions if hashlib.sha256(v).hexdigest() == sha256)
    return next((summarise.code_hash(v) for v in same), None)


def combine(
    found: list[tuple[Path, dict]], reasons: dict, root: Path, current: dict[str, str],
    code_now: dict[str, str] | None = None, code_at: Callable[[str, str], str | None] = lambda m, h: None,
) -> dict:  # fmt: skip
    """The combined document (see the module docstring); ``current``: each module's SHA-256
    today, ``code_now`` its :func:`summarise.code_hash`, ``code_at(module, sha256)`` the code
    hash of the version with that SHA-256 (:func:`code_in_history`)."""
    code_now = code_now or {}

    def same(module: str, sha: str | None) -> bool:
        if sha == current.get(module):
            return True
        return sha is not None and module in code_now and code_at(module, sha) == code_now[module]

    chosen = latest_full(found, root)
    modules = sorted({m for _, doc in found for m in doc["modules"]})
    out_modules, survivors = {}, []
    for module, (folder, entry, doc) in sorted(chosen.items()):
        out_modules[module] = {
            **{k: entry[k] for k in ("total", *COUNTS)},
            "killed_ratio": entry["killed_ratio"],
            "run": str(folder), "began": doc["run"].get("began"),
            "timeouts": doc["run"].get("timeouts", UNRECORDED_TIMEOUTS),
            "source_current": same(module, entry.get("sha256")),
        }  # fmt: skip
        survivors += [
            {**s, "run": str(folder), "reason": summarise._reason(reasons, s["mutant"], s["change"])}
            for s in doc.get("survivors", [])
            if summarise._module_of(s["mutant"]) == module
        ]
    used = sorted(
        {(str(folder), doc["run"].get("began", "")) for folder, _, doc in chosen.values()}, key=lambda r: r[1]
    )
    total = {k: sum(v[k] for v in out_modules.values()) for k in COUNTS}
    n = sum(v["total"] for v in out_modules.values())
    added = sum(s["reason"].startswith(TEST_ADDED) for s in survivors)
    explained = sum(summarise.is_explained(s["reason"]) for s in survivors)
    return {
        "combined": True, **total, "total": n,
        "killed_ratio": _ratio(total["killed"] + total["timeout"], n),
        "killed_ratio_without_timeouts": _ratio(total["killed"], n),
        "killed_ratio_with_tests_added": _ratio(total["killed"] + total["timeout"] + added, n),
        "survived_with_test_added": added,
        "survivors_explained": explained, "survivors_unexplained": len(survivors) - explained,
        "modules_in_full": len(out_modules),
        "not_in_full": [m for m in modules if m not in chosen],
        "source_changed_since_run": [m for m, v in out_modules.items() if not v["source_current"]],
        "runs": [{"folder": f, "began": b} for f, b in used],
        "modules": out_modules, "survivors": survivors,
    }  # fmt: skip


def _provenance(res: dict) -> list[str]:
    """The header line: the runs this page combines and the code that combined them."""
    if not res["runs"]:
        return []
    began = [r["began"] for r in res["runs"]]
    code = res.get("combined_at", "unknown")
    return [
        f"Provenance: {len(began)} runs of `mutate_sample.py --full ...` (`make mutate`'s driver), "
        f"begun {began[0]} to {began[-1]} (each run's command, wall time and, where it was recorded, "
        f"code version in its folder's README.md or report.md); combined at code {code} by "
        "`python docs/results/mutation/combine.py`.",
        "",
    ]


def report(res: dict) -> str:
    """``res`` as markdown."""
    three = summarise._three
    head = [
        "# Mutation testing: the equations and the service's limits",
        "",
        *_provenance(res),
        "One operator, constant, name or argument of the code changed at a time (a *mutant*, made by",
        "[mutmut](https://github.com/boxed/mutmut) 3); the unit tests that reach the changed function",
        "run against it. The configuration is `[tool.mutmut]` in `pyproject.toml`:",
        "`estimator_service/filters`, `gp`, `models` and `service/limits.py`; tests marked `slow` are",
        "left out; `raise` statements keep their message text. Modules are run in full a few at a",
        "time, each run in its own folder here with a README (when, which code, which settings);",
        "this page takes for each module the latest run of all its mutants (`combine.py`).",
        "",
        f"**Over the {res['modules_in_full']} modules run in full ({res['total']} mutants): killed ratio "
        f"{three(res['killed_ratio'])}** ({res['killed']} killed, {res['timeout']} timed out, "
        f"{res['survived']} survived, {res['no_tests']} reached by no test). mutmut counts a timed-out",
        "mutant as killed, and some are not; not counting them, the ratio is "
        f"{three(res['killed_ratio_without_timeouts'])}. With the {res['survived_with_test_added']} "
        "survivors that have a test added after their run (each fails with its mutant applied by hand) "
        f"counted as killed: {three(res['killed_ratio_with_tests_added'])}. Survivors explained: "
        f"{res['survivors_explained']}, unexplained: {res['survivors_unexplained']}.",
        "",
        "Not run in full yet: "
        + (
            ", ".join(f"`{m}`" for m in res["not_in_full"])
            + " (the sampled run in `sampled/` estimates them)."
            if res["not_in_full"]
            else "none; `sampled/` holds an earlier sampled run over every module."
        ),
        "Code changed since its run (docstrings and comments aside): "
        + (", ".join(f"`{m}`" for m in res["source_changed_since_run"]) or "none")
        + ".",
        "",
        "| module | mutants | killed | timed out | survived | no test | killed ratio | run | began |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    rows = [
        f"| `{m}` | {v['total']} | {v['killed']} | {v['timeout']} | {v['survived']} | {v['no_tests']} | "
        f"{three(v['killed_ratio'])} | `{v['run']}` | {v['began']} |"
        for m, v in res["modules"].items()
    ]
    return "\n".join([*head, *rows, *summarise.survivors_table(res["survivors"])]) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folder", type=Path, default=HERE, help="the folder of runs; the results go here")
    ap.add_argument("--reasons", type=Path, default=HERE / "reasons.json", help="survivors' reasons")
    args = ap.parse_args(argv)
    found = runs(args.folder)
    if not found:
        print(f"no mutation runs (results.json with a run record) below {args.folder}", file=sys.stderr)
        return 2
    reasons = json.loads(args.reasons.read_text()) if args.reasons.exists() else {}
    modules = {m for _, doc in found for m in doc["modules"]}
    current = {m: summarise.source_hash(m) for m in modules if Path(m).is_file()}
    code_now = {m: summarise.code_hash(Path(m).read_bytes()) for m in current}
    res = combine(found, reasons, args.folder, current, code_now, code_in_history)
    res["combined_at"] = code_version()
    summarise.write_results(args.folder, res, report(res))
    keys = ("killed_ratio", "killed_ratio_without_timeouts", "killed_ratio_with_tests_added", "total",
            "modules_in_full", "survivors_unexplained")  # fmt: skip
    print(json.dumps({k: res[k] for k in keys}))
    return 0 if res["survivors_unexplained"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
