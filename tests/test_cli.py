"""Every user mistake on the command line: one line naming the option, exit code 2, no
traceback; defaults in --help; --version."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from agents.cli import main as gpbf
from estimator_service.cli import main as estimator


def _fails(capsys, argv: list[str], main=gpbf, needle: str = "") -> str:
    with pytest.raises(SystemExit) as exc:
        code = main(argv)
        raise SystemExit(code)
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert needle in err, err
    return err


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["collect", "--minutes", "-1"], "--minutes"),
        (["collect", "--minutes", "0"], "--minutes"),
        (["collect", "--minutes", "nan"], "--minutes"),
        (["collect", "--env", "CartPole-v1"], "--env"),
        (["collect", "--seed", "-3"], "--seed"),
        (["track", "flight.npz", "--particles", "0"], "--particles"),
        (["track", "flight.npz", "--filter", "kf"], "--filter"),
        (["track", "flight.npz", "--pf-update", "enkf"], "--pf-update"),
        (["track", "flight.npz", "--pf-update", "bridge"], "--pf-update"),  # the EKF has none
        (["train-agent", "--filter", "pf", "--pf-update", "table1"], "--pf-update"),
        (["train", "f.npz", "--points", "1"], "--points"),
        (["train", "f.npz", "--calibration-seconds", "-5"], "--calibration-seconds"),
        (["train-agent", "--timesteps", "0"], "--timesteps"),
        (["train-agent", "--threads", "0"], "--threads"),
        (["eval-agent", "a.zip", "--episodes", "0"], "--episodes"),
        (["eval-agent", "a.zip", "--threads", "300"], "argument --threads: must be in"),
        (["reproduce", "--jobs", "0"], "--jobs"),
        (["gap-sweep", "--jobs", "65"], "--jobs"),
        (["serve", "--models", "m", "--workers", "0"], "--workers"),
        (["serve"], "--models"),
        (["frobnicate"], "invalid choice"),
        (["track", "f.npz", "--out", "x"], "gpbf track: error: unrecognized arguments: --out x"),
        (["--bogus"], "gpbf: error: unrecognized arguments: --bogus"),
        ([], "gpbf: error: the following arguments are required: command"),
    ],
)
def test_option_mistakes_are_one_line_with_exit_code_2(capsys, argv: list[str], needle: str) -> None:
    _fails(capsys, argv, needle=needle)


def test_file_mistakes_are_one_line_with_exit_code_2(capsys, tmp_path: Path) -> None:
    _fails(
        capsys, ["train", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "m")], needle="missing.npz"
    )
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    _fails(capsys, ["track", str(tmp_path / "bad.npz"), "--models", str(tmp_path)], needle="bad.npz")
    _fails(capsys, ["eval-agent", str(tmp_path / "nowhere" / "model.zip")], needle="agent.json")
    (tmp_path / "notes.txt").write_text("a text file")
    _fails(capsys, ["eval-agent", str(tmp_path / "notes.txt")], needle="a file, not an agent's folder")
    notes = str(tmp_path / "notes.txt")
    err = _fails(capsys, ["track", notes, "--models", str(tmp_path)], needle="notes.txt")
    assert "not a NumPy .npz file" in err and "pickle" not in err, err  # NumPy's advice: an unsafe load
    _fails(capsys, ["train", str(tmp_path / "x.csv")], main=estimator, needle="--system")
    _fails(capsys, ["serve", "--models", str(tmp_path / "none")], needle="does not exist")


def test_the_experiment_scripts_refuse_mistakes_in_one_line_and_write_nothing(capsys, tmp_path: Path) -> None:
    """``python -m agents.experiments.rl --report-only`` and ``python -m
    agents.experiments.report`` on a folder with nothing to report, under a file, or (the
    report) without arguments: one line, exit code 2, no folder or file written."""
    from agents.experiments.report import main as report
    from agents.experiments.rl import main as rl

    (tmp_path / "afile").write_text("x")
    _fails(capsys, ["--report-only", "--out", str(tmp_path / "empty")], main=rl, needle="no trained agent")
    _fails(
        capsys, ["--report-only", "--out", str(tmp_path / "afile" / "x")], main=rl, needle="not a directory"
    )
    _fails(capsys, [], main=report, needle="folders")
    _fails(capsys, [str(tmp_path / "empty")], main=report, needle="no results.json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_help_shows_the_same_defaults_everywhere(capsys) -> None:
    helps = {}
    for cmd in (["track"], ["serve"], ["train-agent"]):
        with pytest.raises(SystemExit):
            gpbf([*cmd, "--help"])
        helps[cmd[0]] = capsys.readouterr().out
    for text in helps.values():
        text = " ".join(text.split())
        assert "(default: ekf)" in text and "(default: 2000)" in text
        assert "hetgp, egp, gp, sparse, param" in text


def test_help_names_each_default_once_and_no_empty_default(capsys) -> None:
    """Every command's --help: no ``(default: None)`` or ``(default: False)``, no option whose
    help names its default twice, and required options without a default."""
    import re

    from agents.cli import build_parser

    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices
    assert {"train", "track", "serve", "router", "collect", "train-agent"} <= set(commands)
    for name, sub in commands.items():
        text = sub.format_help()
        assert "(default: None)" not in text and "(default: False)" not in text, name
        assert "(default: )" not in text and "(default: [])" not in text, name
        seed = next((b for b in re.split(r"\n  (?=-)", text) if b.startswith("--seed ")), None)
        assert seed is None or re.search(r"\(default: \d+\)", seed), (name, seed)  # 0 is a default too
        for block in re.split(r"\n  (?=-)", text):  # one option's help per block
            assert len(re.findall(r"\bdefault\b", block)) <= 1, (name, block)


def test_help_texts_are_plain_text_without_the_docstrings_markup(capsys) -> None:
    """Descriptions taken from module docstrings read as plain text: no reST literals
    (double backquotes) or roles (``:func:`~a.b``) in any command's --help."""
    from agents.experiments.report import main as report
    from agents.experiments.rl import main as rl

    for main, argv in ((gpbf, []), (gpbf, ["router"]), (gpbf, ["serve"]), (gpbf, ["reproduce"]),
                       (gpbf, ["train-agent"]), (estimator, ["train"]), (rl, []), (report, [])):  # fmt: skip
        with pytest.raises(SystemExit):
            main([*argv, "--help"])
        text = capsys.readouterr().out
        assert text.startswith("usage:") and "``" not in text and not re.search(r":[a-z]+:`", text), text


def test_python_m_estimator_service_help_lists_its_commands() -> None:
    """``python -m estimator_service --help`` is the command list, not serve's options."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "estimator_service", "--help"], capture_output=True,
                         text=True, timeout=60, check=True).stdout  # fmt: skip
    assert out.startswith("usage: python -m estimator_service") and "{serve,router,train,track}" in out


def test_json_output_has_no_bare_nan() -> None:
    """Command output is standard JSON: NaN and infinities (nothing measured) are null."""
    import json

    import numpy as np

    from estimator_service.files import json_text

    text = json_text(
        {"nis": float("nan"), "rms": np.float64(1.5), "v": np.array([np.inf, 2.0]), "k": [1, None]}
    )
    assert json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c}")) == {
        "nis": None, "rms": 1.5, "v": [None, 2.0], "k": [1, None]}  # fmt: skip


def test_rl_experiment_never_writes_the_committed_results_by_default() -> None:
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "agents.experiments.rl", "--help"], capture_output=True,
                         text=True, timeout=120, check=True).stdout  # fmt: skip
    block = next(b for b in re.split(r"\n  (?=-)", out) if b.startswith("--out"))
    assert "(default: out/rl)" in block, block


def test_version(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        gpbf(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.startswith("gpbf ")


def test_progress_is_one_display_with_periodic_plain_lines_off_a_terminal() -> None:
    import io

    from estimator_service.progress import ProgressBar

    out = io.StringIO()  # not a terminal: no bar redraws, a line every `every_s` and at the end
    with ProgressBar("train", 1000, unit="step", stream=out, every_s=3600) as bar:
        for k in range(1000):
            bar.update_to(k + 1)
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("train: 1000/1000 steps (100%)") and "ETA" in lines[0]


def test_plain_progress_keeps_printing_while_a_unit_of_work_reports_nothing() -> None:
    """Off a terminal a line comes every ``every_s`` even when no progress is reported (a
    long calibration), and none after the job ends."""
    import io
    import time

    from estimator_service.progress import ProgressBar

    out = io.StringIO()
    with ProgressBar("train", 10, unit="part", stream=out, every_s=0.05) as bar:
        bar.advance()
        time.sleep(0.5)
    silent = out.getvalue().splitlines()
    assert len(silent) >= 4 and all(line.startswith("train: 1/10 parts") for line in silent[:-1])
    time.sleep(0.2)
    assert out.getvalue().splitlines() == silent


def test_weighted_progress_shows_the_share_of_the_weight_done_and_refuses_bad_weights() -> None:
    """Units of unequal cost: the percentage (and so the ETA) is the weight done over the
    whole weight, while the count stays in units; weights that cannot be shares are refused."""
    import io

    from estimator_service.progress import ProgressBar

    out = io.StringIO()
    with ProgressBar("train", unit="part", stream=out, every_s=3600, weights=[3.0, 1.0, 96.0]) as bar:
        bar.advance()
        bar._line()  # what the heartbeat prints
        bar.advance()
        bar._line()
        bar.advance()
    lines = out.getvalue().splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "train: 1/3 parts (3%)", "train: 2/3 parts (4%)", "train: 3/3 parts (100%)"]  # fmt: skip
    out = io.StringIO()  # units ending out of order (worker processes) add their own weight
    with ProgressBar("run", unit="unit", stream=out, every_s=3600, weights=[1.0, 9.0]) as bar:
        bar.advance(index=1)
        bar._line()
        bar.advance(index=0)
        with pytest.raises(ValueError, match="index 2 is not one of the 2 weighted units"):
            bar.advance(index=2)
    assert [line.split(",")[0] for line in out.getvalue().splitlines()] == [
        "run: 1/2 units (90%)", "run: 2/2 units (100%)"]  # fmt: skip

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    out = Terminal()  # a terminal's bar: the percentage by weight, the count of units beside it
    with ProgressBar("train", unit="part", stream=out, weights=[3.0, 1.0, 96.0]) as bar:
        bar.advance(postfix="gp done")
        bar.advance()
    assert "4%" in out.getvalue() and "2/3 parts, gp done]" in out.getvalue()
    for bad in ([], [1.0, 0.0], [1.0, float("nan")], [[1.0]]):
        with pytest.raises(ValueError, match="weights must be"):
            ProgressBar("x", weights=bad, enabled=False)
    with pytest.raises(ValueError, match="total 2 differs from the 3 weights"):
        ProgressBar("x", 2, weights=[1.0, 1.0, 1.0], enabled=False)


def test_the_eta_counts_down_while_a_long_unit_runs(monkeypatch) -> None:
    """Off a terminal the ETA is the share left at the pace of the share done, less the time
    the running unit has taken (at most its own estimate): while a long unit reports nothing
    it counts down, and it never grows with the elapsed time (it did: 90 s, then 360 s)."""
    import io

    import estimator_service.progress as progress

    clock = [0.0]
    monkeypatch.setattr(progress, "monotonic", lambda: clock[0])
    out = io.StringIO()
    with progress.ProgressBar("train", unit="part", stream=out, every_s=3600, weights=[1.0, 6.0, 3.0]) as bar:
        clock[0] = 5.0
        bar._line()  # no pace yet: says when there will be one (it said "ETA ?")
        clock[0] = 10.0
        bar.advance()  # 10 % in 10 s: the job looks like 100 s, the running part like 60 s
        for t in (10.0, 40.0, 70.0, 200.0):
            clock[0] = t
            bar._line()  # what the heartbeat prints
        clock[0] = 210.0
        bar.advance()
        bar._line()
    etas = [line.rsplit("ETA ", 1)[1] for line in out.getvalue().splitlines()]
    # 90 s left; 30 s into the 60-s part, 60 s; past its estimate, the 30 s after it; then
    # 70 % in 210 s: 90 s left (and the closing line)
    assert etas == ["after the first part", "90 s", "60 s", "30 s", "30 s", "90 s", "90 s"]


def test_a_resumed_jobs_kept_units_count_as_done_but_do_not_set_the_eta(monkeypatch) -> None:
    """Units a resumed run keeps (read back in a second) are done from the start and are not
    the pace of the work left: the ETA waits for a unit of this job (it took the kept agents'
    seconds as the pace of training and said 25 min where 80 were left)."""
    import io

    import estimator_service.progress as progress

    clock = [0.0]
    monkeypatch.setattr(progress, "monotonic", lambda: clock[0])
    out = io.StringIO()
    weights = [1.0, 1.0, 4.0, 4.0]
    with progress.ProgressBar(
        "run", unit="unit", stream=out, every_s=3600, weights=weights, done=[0, 1]
    ) as bar:
        clock[0] = 3.0
        bar.advance(index=0)  # a kept unit's worker ends: counted already
        bar.advance(index=1)
        bar._line()
        clock[0] = 40.0
        bar.advance(index=2)  # 40 % of the weight in 40 s: 40 s left for the last 40 %
        bar._line()
    lines = out.getvalue().splitlines()
    assert lines[0] == "run: 2/4 units (20%), 3 s elapsed, ETA after the first unit"
    assert lines[1] == "run: 3/4 units (60%), 40 s elapsed, ETA 40 s"
    with pytest.raises(ValueError, match="done needs weights"):
        progress.ProgressBar("x", 3, done=[0], enabled=False)
    with pytest.raises(ValueError, match=r"done: \[2\] not among the 2 weighted units"):
        progress.ProgressBar("x", weights=[1.0, 1.0], done=[0, 2], enabled=False)


def test_the_eta_caps_the_running_unit_by_the_unit_left_first_not_the_next_in_order(monkeypatch) -> None:
    """Where units are counted by index (kept units, workers ending out of order), the time
    the running unit may take off the ETA is that of the lowest unit left, the one begun
    first: here unit 1 (weight 1) runs late and unit 2 (weight 4) is still to come, so the
    ETA stays at unit 2's 40 s (it took unit 3's weight, a kept unit, and said 20 s)."""
    import io

    import estimator_service.progress as progress

    clock = [0.0]
    monkeypatch.setattr(progress, "monotonic", lambda: clock[0])
    out = io.StringIO()
    with progress.ProgressBar(
        "run", unit="unit", stream=out, every_s=3600, weights=[1.0, 1.0, 4.0, 4.0, 4.0], done=[3, 4]
    ) as bar:
        clock[0] = 10.0
        bar.advance(index=0)  # 1/14 of the weight in 10 s: 140 s the whole, 50 s the 5/14 left
        clock[0] = 40.0  # unit 1, 10 s by that pace, has run 30 s
        bar._line()
    assert out.getvalue().splitlines()[0].endswith("ETA 40 s")


def test_a_job_that_ends_early_says_why_and_never_claims_100_percent() -> None:
    import io

    from estimator_service.progress import ProgressBar

    out = io.StringIO()
    with ProgressBar("fly", 480, stream=out, every_s=3600) as bar:
        for _ in range(195):
            bar.advance()
        bar.stop("the blimp crashed at t = 48.8 s")
    assert out.getvalue().splitlines() == ["fly: stopped at 195/480 steps: the blimp crashed at t = 48.8 s"]


def test_a_model_kind_the_folder_lacks_is_named_with_the_kinds_it_has(capsys, tmp_path: Path) -> None:
    """``serve``/``track`` with a kind the folder was not trained for: one line naming the
    kinds the folder holds (was: the missing file's path)."""
    import numpy as np

    from tests.robot_log import write_robot_log

    log, system = write_robot_log(tmp_path, np.random.default_rng(1), rows=300)
    out = tmp_path / "models"
    argv = ["train", str(log), "--system", str(system), "--out", str(out), "--kinds", "gp", "--points", "40"]
    assert estimator([*argv, "--calibration-seconds", "0", "--quiet"]) == 0
    capsys.readouterr()
    err = _fails(capsys, ["serve", "--models", str(out), "--model", "sparse"], main=estimator)
    assert "has no 'sparse' models (it has: gp)" in err
    track = ["track", str(log), "--system", str(system), "--models", str(out), "--model", "sparse"]
    _fails(capsys, track, main=estimator, needle="(it has: gp)")
    # a folder without the plain GP: with no --model every command runs a kind it has
    sparse = tmp_path / "sparse"
    argv = [
        "train",
        str(log),
        "--system",
        str(system),
        "--out",
        str(sparse),
        "--kinds",
        "sparse",
        "--points",
        "40",
    ]
    assert estimator([*argv, "--calibration-seconds", "0", "--quiet"]) == 0
    capsys.readouterr()
    assert estimator(["track", str(log), "--system", str(system), "--models", str(sparse)]) == 0
    assert "track ekf/sparse" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv",
    [
        ["collect", "--out", "{f}/flight.npz"],
        ["track", "flight.npz", "--plot", "{f}/plot.png"],
        ["reproduce", "--out", "{f}/report"],
        ["gap-sweep", "--out", "{f}/sweep"],
        ["train-agent", "--out", "{f}/agent"],
    ],
)
def test_an_output_path_through_a_file_is_one_line_before_any_work(capsys, tmp_path: Path, argv) -> None:
    """An output path whose folder is a file fails at once, in one line naming it (was: a
    traceback, after the work)."""
    f = tmp_path / "a_file"
    f.write_text("x")
    _fails(capsys, [a.format(f=f) for a in argv], needle=f"{f}: cannot write --")


def test_zenoh_mistakes_are_one_line_without_rust_internals(capsys, tmp_path: Path) -> None:
    """A bad endpoint or zenoh configuration file: one line naming it, without the Rust
    source paths and internal structures of zenoh's message (was: a traceback)."""
    text, json5 = tmp_path / "z.txt", tmp_path / "z.json5"
    text.write_text("hello")
    json5.write_text("{listen: 5}")
    broken = tmp_path / "broken.json"
    broken.write_text('{"mode": "router",\n "x": }')
    for argv, needle in (
        (["router", "--listen", "garbage"], "--listen garbage: Endpoints must be of the form"),
        (["router", "--connect", "tcp/"], "--connect tcp/: Endpoints must be of the form"),
        (["router", "--zenoh-config", str(text)], f"--zenoh-config {text}: Unsupported file type"),
        (["router", "--zenoh-config", str(json5)], "expected struct ListenConfig (line 1, column 10)"),
        (["router", "--zenoh-config", str(broken)],
         "expected array, boolean, null, number, object, or string (line 2, column 7)"),
        (["router", "--listen", "tcp/127.0.0.1:99999"], "invalid port value (mode router, listening on "
         "['tcp/127.0.0.1:99999']"),
    ):  # fmt: skip
        err = _fails(capsys, argv, main=estimator, needle=needle)
        assert ".rs:" not in err and "Message {" not in err and "Location" not in err, err
        assert "column" not in err or "--zenoh-config" in err, err  # no place in JSON the user never wrote


def test_plot_without_matplotlib_is_one_line_before_any_work(capsys, monkeypatch, tmp_path: Path) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as in the estimator-only install
    _fails(capsys, ["track", "f.npz", "--plot", str(tmp_path / "p.png")], main=estimator,
           needle="--plot needs matplotlib; install it with: pip install 'gpbf[plots]'")  # fmt: skip
