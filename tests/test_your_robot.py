"""docs/your-robot.md, executed: a robot that is not the blimp, from a CSV log to a running
service, through the public surface only."""

from __future__ import annotations

import os
import signal
from pathlib import Path

from estimator_service.service.client import free_port
from tests.doc_blocks import blocks, run_blocks

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "your-robot.md"


def test_the_walk_through_runs_as_written(tmp_path: Path) -> None:
    assert [lang for lang, _, name in blocks(PAGE) if not name] == [
        "python",
        "sh",
        "sh",
        "python",
        "sh",
        "sh",
        "",
        "sh",
    ]
    real = str(ROOT / "docs" / "results" / "real_mrclam")
    try:
        run_blocks(PAGE, tmp_path, {"7450": str(free_port()), "docs/results/real_mrclam": real})
    finally:
        pid = tmp_path / "serve.pid"
        if pid.exists():
            try:
                os.kill(int(pid.read_text()), signal.SIGKILL)
            except ProcessLookupError:
                pass
    assert (tmp_path / "rover_models" / "manifest.json").exists()
    assert (tmp_path / "rover_own" / "parametric.json").exists()
    assert (tmp_path / "mrclam_models" / "observation_egp_type-landmark.npz").exists()
    assert "ready" in (tmp_path / "serve.log").read_text()


def test_readme_code_blocks_run(tmp_path: Path) -> None:
    """Every python block of the README runs as written (in order, sharing nothing)."""
    text = [b for lang, b, _ in blocks(ROOT / "README.md") if lang == "python"]
    assert len(text) >= 2
    run_blocks(ROOT / "README.md", tmp_path, timeout=600, langs=("python",))
