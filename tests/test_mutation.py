"""``make mutate``'s tool chain on a three-line project: mutmut runs with this repository's
settings style, and the summary counts, lists and explains the survivors (the real run takes
hours on 2 cores, the sampled one 87 min on 2026-12-05: ``docs/results/mutation/``)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUMMARISE = ROOT / "docs" / "results" / "mutation" / "summarise.py"


def _project(root: Path) -> None:
    (root / "pkg").mkdir()
    (root / "tests").mkdir()
    (root / "pkg" / "__init__.py").write_text("")
    (root / "pkg" / "area.py").write_text(
        "def area(w, h):\n    return w * h\n\n\ndef label(x):\n"
        "    if x < 0:\n        raise ValueError('x must be >= 0')\n    return 'big' if x > 10 else 'small'\n"
    )
    (root / "pkg" / "twice.py").write_text("def twice(x):\n    return 2 * x\n")
    (root / "tests" / "test_area.py").write_text(
        "from pkg.area import area, label\nfrom pkg.twice import twice\n\n\ndef test_area():\n"
        "    assert area(2, 3) == 6\n    assert label(11) == 'big'\n    assert twice(3) == 6\n"
    )
    (root / "pyproject.toml").write_text(
        '[tool.mutmut]\nsource_paths = ["pkg"]\npytest_add_cli_args_test_selection = ["tests"]\n'
        "do_not_mutate_patterns = ['^\\s*raise ']\n"
    )


def test_mutation_run_and_summary_on_a_tiny_project(tmp_path: Path) -> None:
    _project(tmp_path)
    mutmut = Path(sys.executable).with_name("mutmut")
    run = subprocess.run(
        [mutmut, "run", "--max-children", "1"], cwd=tmp_path, capture_output=True, timeout=300
    )
    assert run.returncode == 0, run.stderr.decode()[-2000:]
    out, reasons = tmp_path / "out", tmp_path / "reasons.json"
    cmd = [
        sys.executable,
        SUMMARISE,
        "--out",
        out,
        "--reasons",
        reasons,
        "--sample",
        tmp_path / "no_sample.json",
    ]
    subprocess.run(cmd, cwd=tmp_path, capture_output=True, timeout=120, check=True)
    first = json.loads((out / "results.json").read_text())
    edge = next(s["mutant"] for s in first["survivors"] if ">= 10" in s["change"])  # x > 10 -> x >= 10
    rules = [["'XXsmallXX'", "equivalent: a label nobody reads"]]
    reasons.write_text(json.dumps({"mutants": {edge: "test to add: label(10)"}, "changes": rules}))
    last = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=120, check=True)
    res = json.loads((out / "results.json").read_text())
    assert json.loads(last.stdout.splitlines()[-1])["killed_ratio"] == res["killed_ratio"]
    assert res["total"] == res["killed"] + res["timeout"] + res["survived"] + res["no_tests"] + res["not_run"]
    assert 0 < res["killed"] < res["total"] and res["killed_ratio"] == round(res["killed"] / res["total"], 4)
    survivors = {s["mutant"]: s for s in res["survivors"]}
    assert len(survivors) == res["survived"] + res["no_tests"]
    assert all(s["change"].startswith("- ") and " | + " in s["change"] for s in survivors.values())
    assert not any("raise" in s["change"] for s in survivors.values())  # message text is not mutated
    assert any("if x <= 0" in s["change"] for s in survivors.values())  # the condition that raises is
    assert survivors[edge]["reason"] == "test to add: label(10)"
    by_rule = [s for s in survivors.values() if "'XXsmallXX'" in s["change"]]
    assert len(by_rule) == 1 and by_rule[0]["reason"] == "equivalent: a label nobody reads"
    assert res["survivors_explained"] == 2 and res["survivors_unexplained"] == len(survivors) - 2
    assert "killed ratio" in (out / "report.md").read_text()
    _a_run_of_one_module_keeps_the_other_from_the_earlier_run(tmp_path, cmd, res)


def _a_run_of_one_module_keeps_the_other_from_the_earlier_run(root: Path, cmd: list, earlier: dict) -> None:
    """A second run of ``pkg/area.py`` alone: ``--keep-from`` the first run's results takes
    ``pkg/twice.py``'s entry from it while its source is unchanged, and not once it changed."""
    first = root / "first.json"
    first.write_text(json.dumps(earlier))
    mutmut = Path(sys.executable).with_name("mutmut")
    shutil.rmtree(root / "mutants")  # a fresh run, as `make mutate` makes
    subprocess.run([mutmut, "run", "--max-children", "1", "pkg.area*"], cwd=root, capture_output=True,
                   timeout=300, check=True)  # fmt: skip
    subprocess.run([*cmd, "--keep-from", first], cwd=root, capture_output=True, timeout=120, check=True)
    res = json.loads((root / "out" / "results.json").read_text())
    twice = "pkg/twice.py"
    assert res["kept"] == [twice] and res["modules"][twice] == earlier["modules"][twice]
    assert res["not_run"] == 0 and res["total"] == earlier["total"]
    assert res["killed"] + res["timeout"] == earlier["killed"] + earlier["timeout"]
    assert sorted(s["mutant"] for s in res["survivors"]) == sorted(s["mutant"] for s in earlier["survivors"])
    other = {**earlier, "setup": {**earlier["setup"], "mutmut": "0.0"}}  # another mutmut made those mutants
    first.write_text(json.dumps(other))
    run = subprocess.run([*cmd, "--keep-from", first], cwd=root, capture_output=True, text=True, timeout=120,
                         check=True)  # fmt: skip
    assert json.loads((root / "out" / "results.json").read_text())["kept"] == []
    assert "nothing kept" in run.stderr
    first.write_text(json.dumps(earlier))
    (root / "pkg" / "twice.py").write_text("def twice(x):\n    return x + x\n")
    subprocess.run([*cmd, "--keep-from", first], cwd=root, capture_output=True, timeout=120, check=True)
    res = json.loads((root / "out" / "results.json").read_text())
    assert res["kept"] == [] and res["modules"][twice]["not_run"] > 0


def _script(name: str):
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, ROOT / "docs" / "results" / "mutation" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_sampled_mutants_give_a_stratified_estimate_with_its_interval() -> None:
    """A module of 10 mutants: 4 run before (3 killed), 6 not; 3 of those drawn and run (2
    killed): 3 + 2 + 3 x 2/3 = 7 expected killed, and the interval from the binomial variance
    with the finite-population correction, 1.96 sqrt(3^2 (2/3)(1/3) / 3 (1 - 3/6)) / 10."""
    sample, summarise = _script("sample"), _script("summarise")
    per = {f"m{i}": s for i, s in enumerate(["killed"] * 3 + ["survived"] + ["not checked"] * 6)}
    drawn = sample.draw({"pkg/a.py": [k for k, s in per.items() if s == "not checked"]}, 0.5, 0, ())
    unrun = {"pkg/a.py": [k for k, s in per.items() if s == "not checked"]}
    assert drawn == sample.draw(unrun, 0.5, 0, ())  # same seed, same draw
    assert len(drawn["pkg/a.py"]) == 3 and set(drawn["pkg/a.py"]) <= {f"m{i}" for i in range(4, 10)}
    for name, status in zip(drawn["pkg/a.py"], ["killed", "timeout", "survived"], strict=True):
        per[name] = status
    est = summarise.estimate({"pkg/a.py": per}, {"population": {"pkg/a.py": 6}, "sample": drawn, "seed": 0})
    half = 1.96 * (9 * (2 / 3) * (1 / 3) / 3 * 0.5) ** 0.5 / 10
    assert est["killed_ratio"] == 0.7 and est["ci95"] == [round(0.7 - half, 4), round(0.7 + half, 4)]
    full = sample.draw({"pkg/a.py": ["x", "y"], "pkg/b.py": ["z"]}, 0.1, 3, ("pkg/b.py",))
    assert len(full["pkg/a.py"]) == 1 and full["pkg/b.py"] == ["z"]
    assert summarise.estimate({"pkg/a.py": {"x": "not checked"}}, {"sample": {}})["killed_ratio"] is None
    kept = {"pkg/b.py": {"total": 10, "killed": 8, "timeout": 1, "not_run": 0}}  # run before, counted as is
    both = summarise.estimate({"pkg/a.py": per}, {"population": {"pkg/a.py": 6}, "sample": drawn}, kept)
    assert both["killed_ratio"] == round((7 + 9) / 20, 4) and both["ci95"][1] - both["ci95"][0] < 2 * half
    partial = {"pkg/b.py": {**kept["pkg/b.py"], "not_run": 1}}
    assert summarise.estimate({}, {"sample": {}}, partial)["killed_ratio"] is None


def test_a_test_that_leaves_a_child_process_does_not_stop_the_run(tmp_path: Path) -> None:
    """A test module starts a process it never waits for (in mutmut's own process, during its
    clean and coverage runs) that ends while mutants run: mutmut 3.8 alone stops there with a
    ``KeyError`` (its worker pool waits for any child); ``run_mutmut.py`` reaps it and runs
    every mutant."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "tests").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "area.py").write_text(
        "def area(w, h):\n    return w * h\n\n\ndef twice(x):\n    return 2 * x + 0\n"
    )
    (tmp_path / "tests" / "test_area.py").write_text(
        "import subprocess\nimport sys\nimport time\n\nfrom pkg.area import area, twice\n\n"
        "STRAY = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(1.0)'])\n\n\n"
        "def test_area():\n    time.sleep(0.3)\n    assert area(2, 3) == 6 and twice(3) == 6\n"
    )
    (tmp_path / "pyproject.toml").write_text(
        '[tool.mutmut]\nsource_paths = ["pkg"]\npytest_add_cli_args_test_selection = ["tests"]\n'
    )
    run = subprocess.run(
        [sys.executable, SUMMARISE.with_name("run_mutmut.py"), "run", "--max-children", "1"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert run.returncode == 0 and "KeyError" not in run.stderr, run.stderr[-2000:]
    out = tmp_path / "out"
    subprocess.run([sys.executable, SUMMARISE, "--out", out, "--reasons", tmp_path / "none.json"],
                   cwd=tmp_path, capture_output=True, timeout=120, check=True)  # fmt: skip
    res = json.loads((out / "results.json").read_text())
    assert res["not_run"] == 0 and res["total"] >= 5 and res["killed"] > 0


def test_a_stopped_run_goes_on_and_other_code_starts_afresh(tmp_path: Path) -> None:
    """``make mutate``'s driver: a run whose mutant lost its result (stopped while it ran) runs
    only that mutant again and scores as before; changed code starts a fresh run."""
    _project(tmp_path)
    out = tmp_path / "out"
    driver = [sys.executable, SUMMARISE.with_name("mutate_sample.py"), "--max-children", "1", "--fraction",
              "1", "--first", "pkg.twice*", "--out", out, "--reasons", tmp_path / "none.json"]  # fmt: skip

    def go() -> tuple[str, dict]:
        run = subprocess.run(driver, cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert run.returncode == 0, run.stderr[-2000:]
        return run.stdout, json.loads((out / "results.json").read_text())

    said, first = go()
    assert "a fresh run (no run recorded" in said and first["not_run"] == 0 and first["total"] >= 5
    assert first["run"]["fraction"] == 1 and len(first["run"]["fingerprint"]) == 64
    meta = tmp_path / "mutants" / "pkg" / "area.py.meta"
    doc = json.loads(meta.read_text())
    stopped = sorted(doc["exit_code_by_key"])[0]
    doc["exit_code_by_key"][stopped] = None  # as a run stopped while this mutant ran leaves it
    meta.write_text(json.dumps(doc))
    said, again = go()
    drawn = sum(map(len, json.loads((tmp_path / "mutants" / "sample.json").read_text())["sample"].values()))
    assert f"1 of {drawn} sampled mutants left" in said and drawn >= 3
    assert json.loads(meta.read_text())["exit_code_by_key"][stopped] is not None
    assert {k: again[k] for k in ("killed", "survived", "not_run")} == {
        k: first[k] for k in ("killed", "survived", "not_run")
    }
    assert again["run"] == first["run"]
    (tmp_path / "pkg" / "twice.py").write_text("def twice(x):\n    return x + x\n")
    said, fresh = go()
    assert "a fresh run (the code changed since the run began" in said and fresh["not_run"] == 0
    assert fresh["run"]["fingerprint"] != first["run"]["fingerprint"]
    _new_timeouts_run_timed_out_mutants_again(tmp_path, go, fresh, meta)
    _stopped_before_the_draw(tmp_path, go, fresh)
    _stopped_while_mutmut_made_the_mutants(tmp_path, go, fresh)


def _new_timeouts_run_timed_out_mutants_again(root: Path, go, done: dict, meta: Path) -> None:
    """Changed timeout settings keep the run (same code) and run its timed-out mutants again."""
    doc = json.loads(meta.read_text())
    timed_out = sorted(doc["exit_code_by_key"])[0]
    doc["exit_code_by_key"][timed_out] = 36  # mutmut's code for a mutant stopped as timed out
    meta.write_text(json.dumps(doc))
    project = root / "pyproject.toml"
    project.write_text(project.read_text() + "timeout_constant = 3.0\n")
    said, again = go()
    assert "timed-out mutants run again" in said and "a fresh run" not in said
    assert json.loads(meta.read_text())["exit_code_by_key"][timed_out] not in (None, 36)
    assert {k: again[k] for k in ("killed", "timeout", "not_run")} == {
        k: done[k] for k in ("killed", "timeout", "not_run")
    }
    assert again["run"]["fingerprint"] == done["run"]["fingerprint"]
    assert again["run"]["timeouts"]["timeout_constant"] == 3.0
    assert again["run"]["timeouts_before"] == [done["run"]["timeouts"]]


def _stopped_before_the_draw(root: Path, go, done: dict) -> None:
    """A run stopped while its first mutants ran (one without a result, no draw yet, no
    other module run): it runs that one, draws, and runs the rest."""
    (root / "mutants" / "sample.json").unlink()
    for name, keep_one in (("area.py.meta", False), ("twice.py.meta", True)):
        meta = root / "mutants" / "pkg" / name
        doc = json.loads(meta.read_text())
        keys = sorted(doc["exit_code_by_key"])
        doc["exit_code_by_key"] |= {k: None for k in (keys[:1] if keep_one else keys)}
        meta.write_text(json.dumps(doc))
    said, again = go()
    area = len(json.loads((root / "mutants" / "pkg" / "area.py.meta").read_text())["exit_code_by_key"])
    assert "a fresh run" not in said and f"{area} of {area} sampled mutants left" in said
    assert {k: again[k] for k in ("killed", "survived", "not_run", "total")} == {
        k: done[k] for k in ("killed", "survived", "not_run", "total")
    }


def _stopped_while_mutmut_made_the_mutants(root: Path, go, done: dict) -> None:
    """A run stopped while mutmut was making the mutants, before those of ``--first``: the
    first pass runs them (it was skipped, the draw made without them, and the run ended with
    them unrun, 2026-12-06)."""
    (root / "mutants" / "sample.json").unlink()
    for made in ("twice.py.meta", "twice.py"):
        (root / "mutants" / "pkg" / made).unlink()
    meta = root / "mutants" / "pkg" / "area.py.meta"
    doc = json.loads(meta.read_text())
    meta.write_text(json.dumps({**doc, "exit_code_by_key": dict.fromkeys(doc["exit_code_by_key"])}))
    said, again = go()
    assert "a fresh run" not in said
    assert {k: again[k] for k in ("killed", "survived", "not_run", "total")} == {
        k: done[k] for k in ("killed", "survived", "not_run", "total")
    }


def test_runs_of_a_few_modules_combine_into_one_score(tmp_path: Path, monkeypatch) -> None:
    """``combine.py``: each module scored by the latest run that ran all its mutants as a
    ``--full`` module; timed-out mutants give the lower bound; survivors take today's reasons;
    a module no run took in full is named, not counted."""
    monkeypatch.syspath_prepend(str(SUMMARISE.parent))
    import combine

    def entry(total, killed, timeout, survived, not_run=0):
        return {"total": total, "killed": killed, "timeout": timeout, "survived": survived, "no_tests": 0,
                "not_run": not_run, "killed_ratio": None, "sha256": f"h{total}"}  # fmt: skip

    change = "- a = b * c | + a = b / c"
    older = {"run": {"began": "2026-01-01 10:00:00 UTC", "full": ["pkg/a.py", "pkg/b.py"]},
             "modules": {"pkg/a.py": entry(10, 8, 1, 1), "pkg/b.py": entry(5, 3, 0, 2),
                         "pkg/c.py": entry(4, 1, 0, 0, not_run=3)},
             "survivors": [{"mutant": "pkg.a.x_f__mutmut_1", "status": "survived", "change": change,
                            "reason": "unexplained"}]}  # fmt: skip
    run = {"began": "2026-01-02 10:00:00 UTC", "full": ["pkg/b.py"], "timeouts": {"timeout_constant": 10}}
    newer = {"run": run,
             "modules": {"pkg/a.py": entry(10, 1, 0, 0, not_run=9), "pkg/b.py": entry(5, 4, 0, 1)},
             "survivors": [{"mutant": "pkg.b.x_g__mutmut_2", "status": "survived", "change": change,
                            "reason": "unexplained"}]}  # fmt: skip
    for name, doc in (
        ("older", older),
        ("newer", newer),
        (".", {"combined": True, "modules": {}, "run": {}}),
    ):
        (tmp_path / name).mkdir(exist_ok=True)
        (tmp_path / name / "results.json").write_text(json.dumps(doc))
    reasons = {"mutants": {"pkg.a.x_f__mutmut_1": "test added after this run (fails with it): t"},
               "changes": [[r"b / c", "equivalent: c is 1"]]}  # fmt: skip
    res = combine.combine(combine.runs(tmp_path), reasons, tmp_path, {"pkg/a.py": "h10", "pkg/b.py": "other"})
    assert res["modules"]["pkg/a.py"]["run"] == "older" and res["modules"]["pkg/b.py"]["run"] == "newer"
    assert res["not_in_full"] == ["pkg/c.py"] and res["source_changed_since_run"] == ["pkg/b.py"]
    assert (res["total"], res["killed"], res["timeout"], res["survived"]) == (15, 12, 1, 2)
    assert res["killed_ratio"] == round(13 / 15, 4) and res["killed_ratio_without_timeouts"] == round(
        12 / 15, 4
    )
    assert res["killed_ratio_with_tests_added"] == round(14 / 15, 4) and res["survived_with_test_added"] == 1
    assert [s["reason"] for s in res["survivors"]] == ["test added after this run (fails with it): t",
                                                       "equivalent: c is 1"]  # fmt: skip
    assert res["survivors_unexplained"] == 0 and "| `pkg/b.py` | 5 | 4 | 0 | 1 |" in combine.report(res)
    assert res["runs"] == [{"folder": "older", "began": "2026-01-01 10:00:00 UTC"},
                           {"folder": "newer", "began": "2026-01-02 10:00:00 UTC"}]  # fmt: skip
    head = combine.report({**res, "combined_at": "abc1234567"}).splitlines()[2]
    assert head.startswith("Provenance: 2 runs ") and "begun 2026-01-01 10:00:00 UTC to 2026-01-02" in head
    assert head.endswith("combined at code abc1234567 by `python docs/results/mutation/combine.py`.")


def test_a_mutants_own_reason_holds_only_for_the_change_it_was_written_for(monkeypatch) -> None:
    """mutmut numbers a function's mutants in order, so after a code change a name can stand
    for another change: an entry written for one change does not explain another (a rule
    still may, and the survivor names the change the entry was written for); an entry
    without its change holds for any."""
    monkeypatch.syspath_prepend(str(SUMMARISE.parent))
    import summarise

    mine, other = "- a = b * c | + a = b / c", "- a = b * c | + a = b + c"
    reasons = {"mutants": {"m.x_f__mutmut_1": {"change": mine, "reason": "equivalent: c is 1"},
                           "m.x_f__mutmut_2": "equivalent: any change"},
               "changes": [[r"\+ .*'XX", "equivalent: a label nobody reads"]]}  # fmt: skip
    assert summarise._reason(reasons, "m.x_f__mutmut_1", mine) == "equivalent: c is 1"
    stale = summarise._reason(reasons, "m.x_f__mutmut_1", other)
    assert not summarise.is_explained(stale) and mine in stale
    assert summarise._reason(reasons, "m.x_f__mutmut_1", "- s = 'a' | + s = 'XXaXX'") == (
        "equivalent: a label nobody reads"
    )
    assert summarise._reason(reasons, "m.x_f__mutmut_2", other) == "equivalent: any change"
    assert summarise._reason(reasons, "m.x_g__mutmut_1", other) == summarise.UNEXPLAINED


def test_a_module_whose_docstrings_or_comments_alone_changed_keeps_its_run(
    tmp_path: Path, monkeypatch
) -> None:
    """A run stays the module's score when only docstrings or comments changed since (mutmut
    mutates neither, so the mutants and their names are the same): the version the run saw is
    found in the git history by its SHA-256 and its code compared with today's. A changed
    statement, a single-quoted docstring (mutmut mutates it) or a ``pragma: no mutate`` comment
    still counts as changed. It named three modules changed whose docstrings alone had."""
    monkeypatch.syspath_prepend(str(SUMMARISE.parent))
    import combine
    import summarise

    code = summarise.code_hash
    base = b'"""Module."""\n\n\ndef f(x):\n    """Twice x."""\n    return 2 * x  # doubled\n'
    assert code(base) == code(
        base.replace(b"Twice x.", b"Two times x,\n    on two lines.").replace(b"# doubled", b"")
    )
    assert code(base) == code(base.replace(b'"""Module."""', b"'''Another module text.'''"))
    assert code(base) != code(base.replace(b"2 * x", b"3 * x"))
    assert code(base) != code(base.replace(b"# doubled", b"# pragma: no mutate"))
    single = b'def f(x):\n    "Twice x."\n    return 2 * x\n'
    assert code(single) != code(single.replace(b"Twice", b"Two times"))

    monkeypatch.chdir(tmp_path)
    (tmp_path / "pkg").mkdir()
    module = tmp_path / "pkg" / "a.py"
    module.write_bytes(base)
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    subprocess.run(["git", "init", "-q"], check=True)
    subprocess.run([*git, "add", "pkg"], check=True)
    subprocess.run([*git, "commit", "-qm", "run"], check=True)
    entry = {"total": 3, "killed": 3, "timeout": 0, "survived": 0, "no_tests": 0, "not_run": 0,
             "killed_ratio": 1.0, "sha256": summarise.source_hash("pkg/a.py")}  # fmt: skip
    (tmp_path / "runs" / "r").mkdir(parents=True)
    doc = {"run": {"began": "2026-01-01 10:00:00 UTC", "full": ["pkg/a.py"]}, "modules": {"pkg/a.py": entry}}
    (tmp_path / "runs" / "r" / "results.json").write_text(json.dumps(doc))

    def changed(text: bytes) -> list[str]:
        module.write_bytes(text)
        now = {"pkg/a.py": summarise.source_hash("pkg/a.py")}
        res = combine.combine(combine.runs(tmp_path / "runs"), {}, tmp_path / "runs", now,
                              {"pkg/a.py": code(text)}, combine.code_in_history)  # fmt: skip
        return res["source_changed_since_run"]

    assert changed(base) == [] and changed(base.replace(b"Twice x.", b"Doubles x.")) == []
    assert changed(base.replace(b"2 * x", b"x + x")) == ["pkg/a.py"]
    assert combine.code_in_history("pkg/a.py", "0" * 64) is None
    module.write_bytes(base.replace(b"2 * x", b"x + x"))  # two commits later, one deleting it:
    subprocess.run([*git, "commit", "-qam", "edit"], check=True)  # the first version is found
    subprocess.run([*git, "rm", "-q", "pkg/a.py"], check=True)
    subprocess.run([*git, "commit", "-qm", "gone"], check=True)
    assert combine.code_in_history("pkg/a.py", entry["sha256"]) == code(base)


def test_a_mutant_only_a_module_fixture_reaches_is_run_against_every_test_of_the_fixture(
    tmp_path: Path,
) -> None:
    """mutmut maps a function that only a module-scoped fixture calls to the first test that
    built it; the driver runs such survivors again against every test using that fixture,
    where the test that checks the value kills them."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "tests").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "calc.py").write_text("def scale(x):\n    return 3 * x\n")
    (tmp_path / "tests" / "test_calc.py").write_text(
        "import pytest\n\nfrom pkg.calc import scale\n\n\n@pytest.fixture(scope='module')\ndef scaled():\n"
        "    return scale(2)\n\n\ndef test_runs(scaled):\n    assert scaled is not None\n\n\n"
        "def test_value(scaled):\n    assert scaled == 6\n"
    )
    (tmp_path / "pyproject.toml").write_text(
        '[tool.mutmut]\nsource_paths = ["pkg"]\npytest_add_cli_args_test_selection = ["tests"]\n'
    )
    out = tmp_path / "out"
    driver = [sys.executable, SUMMARISE.with_name("mutate_sample.py"), "--max-children", "1", "--fraction",
              "1", "--first", "pkg.calc*", "--out", out, "--reasons", tmp_path / "none.json"]  # fmt: skip
    run = subprocess.run(driver, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    res = json.loads((out / "results.json").read_text())
    assert "survivors run again with the tests sharing their fixtures" in run.stdout
    assert res["survived"] == 0 and res["killed"] == res["total"] >= 2 and res["run"]["survivors_rerun"]
