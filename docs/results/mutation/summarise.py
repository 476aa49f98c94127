"""Summarise a finished ``mutmut run`` (``make mutate``) into ``results.json`` and ``report.md``.

Reads mutmut's per-file results under ``mutants/`` and writes, beside this script:

- ``results.json``: ``killed``, ``survived``, ``no_tests``, ``timeout``, ``total`` and
  ``killed_ratio`` (killed and timed-out mutants over all mutants run: a mutant no test
  reaches counts as surviving), the same per module, and every surviving mutant with its
  one-line change and its reason (``"equivalent: ..."`` or ``"test to add: ..."``) from
  ``reasons.json`` (``--reasons``): ``{"mutants": {name: {"change": change, "reason":
  reason}}, "changes": [[regex, reason], ...]}``, a mutant's own entry first where it was
  written for the same change, else the first regular expression that matches its change; a
  survivor without a reason is listed as ``unexplained``.
- ``report.md``: the same for a reader.

Each module's entry records the SHA-256 of its source (``sha256``), and the document the
mutmut version and ``[tool.mutmut]`` table that made the mutants (``setup``). With
``--keep-from`` an earlier ``results.json``, a module none of whose mutants this run reached
keeps that file's entry and survivors when the setup, the source and the mutant count are
unchanged (the tests that scored it are the earlier run's): runs of a few modules at a time
add up to the whole (``kept`` lists the modules taken from the earlier file).

When the rest of the mutants was sampled (``sample.py``'s ``sample.json``, ``--sample``),
``estimate`` gives the killed ratio over *all* configured mutants: per module, the mutants
run count as they are and the module's unrun ones are expected to be killed at the rate of
its sampled ones (stratified estimate, binomial variance with the finite-population
correction), with a 95 % interval.

A run made by ``mutate_sample.py`` (``make mutate``, ``make mutate-sample``) adds its record
``mutants/run.json`` as ``run``: the code's fingerprint, the draw's settings, when it began.

Run from the repository root after ``mutmut run``: ``python docs/results/mutation/summarise.py``.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import json
import re
import sys
from collections import Counter
from pathlib import Path

from estimator_service.files import atomic_write_text, json_text

HERE = Path(__file__).resolve().parent
KILLED = {"killed", "timeout", "segfault", "caught by type check"}
NOT_RUN = {"skipped", "not checked", "check was interrupted by user"}
#: the reason of a survivor nothing explains (the start of it, where it says more)
UNEXPLAINED = "unexplained"
#: mutmut's working folder (relative to the repository root) and the record of a run in it
#: (``mutate_sample.py``: the code's fingerprint, the draw's settings, when it began)
MUTANTS = Path("mutants")
RUN_RECORD = MUTANTS / "run.json"


def _status_and_diffs(names: set[str]) -> tuple[dict[str, dict[str, str]], dict[str, str]]:
    """Per module, each mutant's status; the changed lines of the mutants in ``names``."""
    from mutmut.mutation.data import SourceFileMutationData
    from mutmut.mutation.diff_apply import get_diff_for_mutant
    from mutmut.stats import status_by_exit_code
    from mutmut.utils.file_utils import walk_mutatable_files

    status: dict[str, dict[str, str]] = {}
    diffs: dict[str, str] = {}
    for path in walk_mutatable_files():
        data = SourceFileMutationData(path=path)
        data.load()
        status[str(path)] = {k: status_by_exit_code[v] for k, v in data.exit_code_by_key.items()}
        for key in status[str(path)]:
            if key in names:
                diffs[key] = _changed_lines(get_diff_for_mutant(key, path=path))
    return status, diffs


def _changed_lines(diff: str) -> str:
    """``- old`` / ``+ new`` lines of a unified diff, stripped, on one line."""
    lines = [ln for ln in diff.splitlines() if ln[:1] in "+-" and ln[:3] not in ("+++", "---")]
    return " | ".join(f"{ln[0]} {ln[1:].strip()}" for ln in lines)


def _killed_ratio(named: dict[str, int], total: int) -> float | None:
    """Killed and timed-out mutants over those run (:func:`_named` counts of ``total``
    mutants), to four places; None when none was run."""
    run = total - named["not_run"]
    return round((named["killed"] + named["timeout"]) / run, 4) if run else None


def _reason(reasons: dict, name: str, change: str) -> str:
    """``name``'s reason (:func:`main`'s ``--reasons`` format), or one starting with
    :data:`UNEXPLAINED`.

    A mutant's own entry is a reason, or ``{"change": c, "reason": r}``: ``r`` holds for the
    change ``c`` only. mutmut numbers the mutants of a function in order, so once its code
    changes the same name can stand for another change; then the regular expressions decide,
    and without one the survivor is unexplained, naming the change the entry was written for.
    """
    own = reasons.get("mutants", {}) if "mutants" in reasons or "changes" in reasons else reasons
    entry = own.get(name)
    if isinstance(entry, str):
        return entry
    if isinstance(entry, dict) and entry.get("change") == change:
        return entry["reason"]
    by_rule = next((why for rx, why in reasons.get("changes", []) if re.search(rx, change)), None)
    if by_rule is not None:
        return by_rule
    if entry is None:
        return UNEXPLAINED
    return f"{UNEXPLAINED}: its entry in reasons.json was written for another change: `{entry.get('change')}`"


def is_explained(reason: str) -> bool:
    """Whether a survivor's :func:`_reason` explains it."""
    return not reason.startswith(UNEXPLAINED)


def estimate(status: dict[str, dict[str, str]], sample: dict, kept: dict[str, dict] | None = None) -> dict:
    """Stratified estimate of the killed ratio over every mutant (module docstring), from the
    per-module ``status`` and ``sample`` (``sample.json``); ``kept``: entries taken from an
    earlier run (:func:`summarise`) for modules this run did not reach, counted as they are."""
    killed = var = total = 0.0
    for module, entry in (kept or {}).items():
        if entry["not_run"]:
            return {"killed_ratio": None, "why": f"{module}: kept from an earlier run with mutants not run"}
        total, killed = total + entry["total"], killed + entry["killed"] + entry["timeout"]
    for module, per in status.items():
        if module in (kept or {}):
            continue
        total += len(per)
        killed += sum(s in KILLED for s in per.values())
        left = sum(s in NOT_RUN for s in per.values())
        drawn = [
            per[n] for n in sample.get("sample", {}).get(module, []) if per.get(n) not in NOT_RUN | {None}
        ]
        if not left:
            continue
        if not drawn:
            return {"killed_ratio": None, "why": f"{module}: {left} mutants not run and none of them sampled"}
        rate, pop = sum(s in KILLED for s in drawn) / len(drawn), sample["population"][module]
        killed += left * rate
        var += left**2 * rate * (1 - rate) / len(drawn) * max(0.0, 1 - len(drawn) / pop)
    half = 1.96 * var**0.5 / total
    ratio = killed / total
    return {"killed_ratio": round(ratio, 4), "ci95": [round(ratio - half, 4), round(ratio + half, 4)],
            "seed": sample.get("seed"), "fraction": sample.get("fraction")}  # fmt: skip


def summarise(reasons: dict, sample: dict | None = None, earlier: dict | None = None) -> dict:
    """The results document (see the module docstring); ``earlier``: a previous results
    document whose unchanged modules stand in for the ones this run did not reach."""
    status, _ = _status_and_diffs(set())
    surviving = {k for per in status.values() for k, s in per.items() if s not in KILLED | NOT_RUN}
    status, diffs = _status_and_diffs(surviving)
    this_setup = setup()
    same_setup = earlier is not None and earlier.get("setup") == this_setup
    if earlier is not None and not same_setup:
        print("--keep-from: the earlier run had another mutmut or [tool.mutmut] (or recorded neither): "
              "nothing kept", file=sys.stderr)  # fmt: skip
    modules, kept = {}, []
    for path, per in sorted(status.items()):
        if not per:
            continue
        old = earlier.get("modules", {}).get(path) if same_setup else None
        if old and all(s in NOT_RUN for s in per.values()) and _same_module(old, path, len(per)):
            modules[path] = old
            kept.append(path)
            continue
        named = _named(Counter(per.values()))
        modules[path] = {"total": len(per), "killed_ratio": _killed_ratio(named, len(per)), **named,
                         "sha256": source_hash(path)}  # fmt: skip
    survivors = [
        {"mutant": k, "status": s, "change": (c := diffs.get(k, "")), "reason": _reason(reasons, k, c)}
        for path, per in status.items() if path not in kept
        for k, s in sorted(per.items()) if k in surviving
    ] + [
        {**s, "reason": _reason(reasons, s["mutant"], s["change"])}
        for s in (earlier or {}).get("survivors", []) if _module_of(s["mutant"]) in kept
    ]  # fmt: skip
    explained = sum(is_explained(r["reason"]) for r in survivors)
    total = {k: sum(v[k] for v in modules.values()) for k in _named(Counter())}
    n_all = sum(v["total"] for v in modules.values())
    return {
        **total, "total": n_all, "killed_ratio": _killed_ratio(total, n_all),
        "run_fraction": round((n_all - total["not_run"]) / max(1, n_all), 4), "setup": this_setup,
        "modules_complete": [m for m, v in modules.items() if v["not_run"] == 0],
        "kept": kept,
        "survivors_explained": explained, "survivors_unexplained": len(survivors) - explained,
        **({"estimate": estimate(status, sample, {m: modules[m] for m in kept})} if sample else {}),
        "modules": modules, "survivors": survivors,
    }  # fmt: skip


def setup() -> dict[str, str]:
    """What makes the mutants of a module: mutmut's version and the SHA-256 of the
    ``[tool.mutmut]`` table of ``pyproject.toml`` (read from the working directory)."""
    import tomllib
    from importlib.metadata import version

    table = tomllib.loads(Path("pyproject.toml").read_text()).get("tool", {}).get("mutmut", {})
    return {"mutmut": version("mutmut"), "config_sha256": hashlib.sha256(
        json.dumps(table, sort_keys=True).encode()).hexdigest()}  # fmt: skip


def _same_module(old: dict, path: str, mutants: int) -> bool:
    """An earlier entry stands for ``path`` only if made from the same source and mutants
    (the tests that scored it are the earlier run's)."""
    return old.get("sha256") == source_hash(path) and old.get("total") == mutants


def source_hash(path: str) -> str:
    """SHA-256 of the module's source, as the run saw it (``path`` relative to the root)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def code_hash(source: bytes) -> str:
    """SHA-256 of what mutmut mutates in a module's ``source``: its syntax tree without the
    triple-quoted docstrings (mutmut mutates no triple-quoted string) and without comments,
    except the lines that say ``pragma: no mutate``. Two sources with one code hash give the
    same mutants under the same names."""
    text = source.decode()
    tree = ast.parse(text)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and _triple_quoted_docstring(body[0], text):
            node.body = body[1:] or [ast.Pass()]
    pragmas = [ln.strip() for ln in text.splitlines() if "pragma: no mutate" in ln]
    return hashlib.sha256("\0".join([ast.dump(tree), *pragmas]).encode()).hexdigest()


def _triple_quoted_docstring(node: ast.stmt, text: str) -> bool:
    if not (isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)):
        return False
    quoted = (ast.get_source_segment(text, node.value) or "").lstrip("rRuUbB")
    return isinstance(node.value.value, str) and quoted.startswith(('"""', "'''"))


def _module_of(mutant: str) -> str:
    """A mutant's module path: ``a.b.c.x_f__mutmut_3`` -> ``a/b/c.py``."""
    return "/".join(mutant.split(".")[:-1]) + ".py"


def _named(counts: Counter) -> dict[str, int]:
    return {
        "killed": counts["killed"] + counts["segfault"] + counts["caught by type check"],
        "timeout": counts["timeout"], "survived": counts["survived"] + counts["suspicious"],
        "no_tests": counts["no tests"], "not_run": sum(counts[s] for s in NOT_RUN),
    }  # fmt: skip


def report(res: dict) -> str:
    """``res`` as markdown."""
    head = [
        "# Mutation testing: the equations and the service's limits",
        "",
        "One operator, constant, name or argument of the code changed at a time (a *mutant*, made by",
        "[mutmut](https://github.com/boxed/mutmut) 3); the unit tests that reach the changed",
        "function run against it (`make mutate`: all mutants, hours on 2 cores; `make mutate-sample`:",
        "a seeded random tenth of the GP and model mutants, 87 min on 2 cores on 2026-12-05;",
        "the configuration is `[tool.mutmut]` in",
        "`pyproject.toml`: `estimator_service/filters`, `gp`, `models` and `service/limits.py`;",
        "tests marked `slow` are left out; `raise` statements keep their message text). A mutant",
        "is *killed* when a test fails or it times out; one that no test reaches counts as surviving.",
        "",
        f"**killed ratio {_three(res['killed_ratio'])}** over the mutants run ({res['killed']} killed,",
        f"{res['timeout']} timed out, {res['survived']} survived, {res['no_tests']} reached by no test);",
        f"{res['not_run']} of the {res['total']} mutants not run (run fraction {res['run_fraction']:.3f});",
        f"survivors explained: {res['survivors_explained']}, unexplained: {res['survivors_unexplained']}.",
        *_estimate_lines(res.get("estimate")),
        *(
            [
                "",
                "Taken from an earlier run of the same source (`--keep-from`, same SHA-256): "
                + ", ".join(f"`{m}`" for m in res["kept"])
                + ".",
            ]
            if res.get("kept")
            else []
        ),
        "",
        "| module | mutants | not run | killed ratio (of those run) | survived | no test |",
        "|---|---|---|---|---|---|",
    ]
    rows = [
        f"| `{m}` | {v['total']} | {v['not_run']} | {_three(v['killed_ratio'])} | {v['survived']} | "
        f"{v['no_tests']} |"
        for m, v in res["modules"].items()
    ]
    return "\n".join([*head, *rows, *survivors_table(res["survivors"])]) + "\n"


def write_results(folder: Path, res: dict, text: str) -> None:
    """``results.json`` and ``report.md`` in ``folder``, each written whole or not at all."""
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(folder / "results.json", json_text(res, indent=1) + "\n")
    atomic_write_text(folder / "report.md", text)


def survivors_table(survivors: list[dict]) -> list[str]:
    """The report's section of surviving mutants, one row each with its change and reason."""
    head = ["", "## Surviving mutants", "", "| mutant | change | reason |", "|---|---|---|"]
    rows = [f"| `{s['mutant']}` | `{s['change'].replace('|', '/')}` | {s['reason']} |" for s in survivors]
    return head + rows


def _three(x: float | None) -> str:
    """A ratio to three places; ``-`` where nothing was run (None, or NaN before JSON)."""
    return "-" if x is None or x != x else f"{x:.3f}"


def _estimate_lines(est: dict | None) -> list[str]:
    if not est:
        return []
    if est["killed_ratio"] is None:
        return ["", f"No estimate over all mutants: {est['why']}."]
    if (est.get("fraction") or 0) >= 1:  # every mutant was drawn: the ratio above is the whole
        return []
    lo, hi = est["ci95"]
    return [
        "",
        f"**Estimated killed ratio over all the configured mutants: {est['killed_ratio']:.3f}**",
        f"(95 % interval {lo:.3f}-{hi:.3f}): the mutants not run were sampled at random, a fraction",
        f"{est['fraction']} of each module's (seed {est['seed']}, `sample.py`), and each module's rest",
        "is expected to be killed at its sample's rate (a stratified estimate; random mutant",
        "sampling: Wong & Mathur 1995, Zhang et al. 2013).",
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE, help="folder for results.json and report.md")
    ap.add_argument(
        "--reasons", type=Path, default=HERE / "reasons.json", help="survivors' reasons: {mutant: reason}"
    )
    ap.add_argument("--sample", type=Path, default=HERE / "sample.json", help="sample.py's record, if any")
    ap.add_argument(
        "--keep-from", type=Path, help="an earlier results.json: its unchanged modules this run did not reach"
    )
    args = ap.parse_args(argv)
    if not MUTANTS.is_dir():
        print("no mutants/ folder here: run `make mutate` from the repository root", file=sys.stderr)
        return 2
    reasons = json.loads(args.reasons.read_text()) if args.reasons.exists() else {}
    sample = json.loads(args.sample.read_text()) if args.sample.exists() else None
    try:
        earlier = json.loads(args.keep_from.read_text()) if args.keep_from else None
    except (OSError, ValueError) as exc:
        print(f"--keep-from {args.keep_from}: cannot read an earlier results.json: {exc}", file=sys.stderr)
        return 2
    res = summarise(reasons, sample, earlier)
    if RUN_RECORD.is_file():
        res = {**res, "run": json.loads(RUN_RECORD.read_text())}
    write_results(args.out, res, report(res))
    keys = ("killed_ratio", "killed", "timeout", "survived", "no_tests", "not_run", "total", "run_fraction",
            "survivors_unexplained")  # fmt: skip
    est = {"estimated_killed_ratio": res["estimate"]["killed_ratio"]} if "estimate" in res else {}
    print(json.dumps({**{k: res[k] for k in keys}, **est}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
