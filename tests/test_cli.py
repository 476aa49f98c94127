"""Every user mistake on the command line: one line naming the option, exit code 2, no
traceback; defaults in --help; --version."""

from __future__ import annotations

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
        (["train", "f.npz", "--points", "1"], "--points"),
        (["train", "f.npz", "--calibration-seconds", "-5"], "--calibration-seconds"),
        (["train-agent", "--timesteps", "0"], "--timesteps"),
        (["eval-agent", "a.zip", "--episodes", "0"], "--episodes"),
        (["reproduce", "--jobs", "0"], "--jobs"),
        (["gap-sweep", "--jobs", "65"], "--jobs"),
        (["serve", "--models", "m", "--workers", "0"], "--workers"),
        (["serve"], "--models"),
        (["frobnicate"], "invalid choice"),
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
    _fails(capsys, ["train", str(tmp_path / "x.csv")], main=estimator, needle="--system")
    _fails(capsys, ["serve", "--models", str(tmp_path / "none")], needle="does not exist")


def test_help_shows_the_same_defaults_everywhere(capsys) -> None:
    helps = {}
    for cmd in (["track"], ["serve"], ["train-agent"]):
        with pytest.raises(SystemExit):
            gpbf([*cmd, "--help"])
        helps[cmd[0]] = capsys.readouterr().out
    for text in helps.values():
        assert "(default: ekf)" in text and "(default: gp)" in text and "(default: 2000)" in text


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
