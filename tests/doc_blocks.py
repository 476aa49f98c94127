"""Run the fenced code blocks of a markdown page, in order, as a reader would."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

BLOCK = re.compile(r"(?:<!-- file: (?P<file>[^ ]+) -->\n)?```(?P<lang>\w*)\n(?P<body>.*?)```", re.S)


def blocks(page: Path) -> list[tuple[str, str, str | None]]:
    """``(language, text, file name or None)`` of each fenced block."""
    text = page.read_text(encoding="utf-8")
    return [(m["lang"], m["body"], m["file"]) for m in BLOCK.finditer(text)]


def run_blocks(
    page: Path, folder: Path, replace: dict[str, str] | None = None, timeout: float = 300,
    langs: tuple[str, ...] = ("python", "sh", "bash"),
) -> None:  # fmt: skip
    """Write ``<!-- file: -->`` blocks to ``folder``, run ``python`` blocks with this
    interpreter and ``sh`` blocks with bash (``gpbf`` runs this checkout's CLI); raise with
    the output when one fails."""
    bin_dir = folder / ".bin"  # `gpbf` runs this checkout's CLI, as one process (for `&` and `$!`)
    bin_dir.mkdir(exist_ok=True)
    (bin_dir / "gpbf").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m agents.cli "$@"\n')
    (bin_dir / "gpbf").chmod(0o755)
    path = os.pathsep.join([str(bin_dir), os.environ.get("PATH", "")])
    pythonpath = os.pathsep.join([str(Path(__file__).resolve().parents[1]), *sys.path])
    env = {**os.environ, "PYTHONPATH": pythonpath, "PATH": path}
    prelude = "set -e\n"
    for lang, body, name in blocks(page):
        for a, b in (replace or {}).items():
            body = body.replace(a, b)
        if name:
            (folder / name).write_text(body, encoding="utf-8")
            continue
        if lang not in langs:
            continue
        if lang == "python":
            cmd = [sys.executable, "-c", body]
        elif lang in ("sh", "bash"):
            cmd = ["bash", "-c", prelude + body]
        else:
            continue
        out = subprocess.run(cmd, cwd=folder, env=env, capture_output=True, text=True, timeout=timeout)
        if out.returncode != 0:
            raise AssertionError(
                f"{page.name}: block failed ({out.returncode}):\n{body}\n{out.stdout}\n{out.stderr}"
            )
