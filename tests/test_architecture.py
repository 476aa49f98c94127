"""The one-way architecture: agents -> (gpbf_env, estimator_service); no import cycles; the
estimator runs on a robot's logs without gymnasium or torch."""

from __future__ import annotations

import ast
import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("gpbf_env", "estimator_service", "agents")
#: what each package may import, of the project and of the heavy third-party stacks
FORBIDDEN = {
    "estimator_service": ("gpbf_env", "agents", "gymnasium", "torch", "stable_baselines3"),
    "gpbf_env": ("estimator_service", "agents", "torch", "stable_baselines3"),
    "agents": (),
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _imports(path: Path, modules: set[str]) -> set[str]:
    """Modules ``path`` imports (anywhere in it, except under ``if TYPE_CHECKING``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = {id(n) for node in ast.walk(tree) if isinstance(node, ast.If) and _is_type_checking(node)
            for n in ast.walk(node)}  # fmt: skip
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                found.add(sub if sub in modules else node.module)
    return found


def _graph() -> dict[str, set[str]]:
    files = [p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")]
    modules = {_module_name(p) for p in files}
    return {_module_name(p): _imports(p, modules) for p in files}


def test_every_pointer_to_a_measurement_names_a_section_of_it() -> None:
    """Figures from particular runs live in ``docs/measurements.md``; the code points to them
    as ``docs/measurements.md#anchor``, and each anchor is there (a renamed section would
    leave a pointer to nothing)."""
    import re

    text = (ROOT / "docs" / "measurements.md").read_text(encoding="utf-8")
    anchors = set(re.findall(r'<a id="([a-z0-9-]+)"></a>', text))
    files = [p for pkg in (*PACKAGES, "benchmarks") for p in (ROOT / pkg).rglob("*.py")]
    pointer = re.compile(r"docs/measurements\.md#([a-z0-9-]+)")
    pointers = {(p.relative_to(ROOT).as_posix(), a) for p in [*files, ROOT / "pyproject.toml"]
                for a in pointer.findall(p.read_text(encoding="utf-8"))}  # fmt: skip
    assert len(pointers) >= 10
    assert {(f, a) for f, a in pointers if a not in anchors} == set()


def test_imports_follow_the_one_way_flow() -> None:
    bad = []
    for mod, deps in _graph().items():
        pkg = mod.split(".")[0]
        for dep in deps:
            if dep.split(".")[0] in FORBIDDEN[pkg]:
                bad.append(f"{mod} imports {dep}")
    assert not bad, "imports against agents -> (gpbf_env, estimator_service):\n" + "\n".join(sorted(bad))


def test_no_import_cycles() -> None:
    graph = _graph()
    edges = {m: {d for d in deps if d in graph and d != m} for m, deps in graph.items()}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for d in sorted(edges[m]):
            if state.get(d) == 1:
                cycles.append([*path[path.index(d) :], d])
            elif d not in state:
                visit(d, [*path, d])
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m, [m])

    # a package importing its own submodules, and those importing siblings, is no cycle
    def nested(a: str, b: str) -> bool:
        return a.startswith(b + ".") or b.startswith(a + ".")

    real = [c for c in cycles if not all(nested(a, b) for a, b in itertools.pairwise(c))]
    assert not real, "import cycles:\n" + "\n".join(" -> ".join(c) for c in real)


def blocker(blocked: tuple[str, ...]) -> str:
    """A script prologue under which importing any of ``blocked`` (top-level names) fails."""
    return f"BLOCKED = {blocked!r}" + BLOCK_IMPORTS


BLOCK_IMPORTS = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"blocked: {name}")
        return None
sys.meta_path.insert(0, Block())
"""
BLOCKER = blocker(("gymnasium", "torch", "stable_baselines3", "gpbf_env", "agents", "matplotlib"))
#: an install of ``gpbf`` without extras: agents is there, the simulator and RL stacks not
NO_EXTRAS = blocker(("gymnasium", "torch", "stable_baselines3", "gpbf_env", "numba", "matplotlib"))


def test_estimator_runs_on_a_log_without_gymnasium_or_torch(tmp_path: Path) -> None:
    """Import the whole estimator, train on a CSV log, track it and start the service, in a
    process where importing gymnasium, torch, the simulator or agents fails."""
    from tests.robot_log import write_robot_log

    log, system = write_robot_log(tmp_path, np.random.default_rng(0))
    script = (
        BLOCKER
        + f"""
import pkgutil, importlib, estimator_service
for m in pkgutil.walk_packages(estimator_service.__path__, "estimator_service."):
    if not m.name.endswith("__main__"):
        importlib.import_module(m.name)
from estimator_service.cli import main
assert main(["train", {str(log)!r}, "--system", {str(system)!r}, "--out", {str(tmp_path / "m")!r},
             "--points", "60", "--calibration-seconds", "5", "--calibration-folds", "2",
             "--calibration-condition-only", "--quiet"]) == 0
assert main(["track", {str(log)!r}, "--system", {str(system)!r}, "--models", {str(tmp_path / "m")!r},
             "--filter", "ekf", "--quiet"]) == 0
from estimator_service.service.server import EstimatorService, ServiceConfig
from estimator_service.service.client import free_port
svc = EstimatorService(ServiceConfig({str(tmp_path / "m")!r}, listen=(f"tcp/127.0.0.1:{{free_port()}}",)))
try:
    assert svc._close_session("gone") is None  # a close that lost a race answers, not KeyError
finally:
    svc.close()
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("gymnasium", "torch", "gpbf_env", "agents"))
assert not heavy, heavy
print("ok")
"""
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stdout + out.stderr


@pytest.mark.parametrize("mod", ["estimator_service", "estimator_service.service.client"])
def test_estimator_modules_import_alone(mod: str) -> None:
    script = BLOCKER + f"import {mod}; print('ok')"
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 0, out.stderr


def test_gpbf_runs_the_estimators_commands_without_the_simulator(tmp_path: Path) -> None:
    """``gpbf`` in an install without the ``sim`` and ``rl`` extras: the estimator's commands
    and ``--help``/``--version`` work; the simulator's and agents' commands answer with the
    extra to install, one line, exit code 2."""
    from tests.robot_log import write_robot_log

    log, system = write_robot_log(tmp_path, np.random.default_rng(0))
    script = (
        NO_EXTRAS
        + f"""
import contextlib, io
from agents.cli import main
for argv in (["--version"], ["--help"], ["train", "--help"], ["track", "--help"], ["serve", "--help"]):
    with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit) as done:
        main(argv)
assert main(["train", {str(log)!r}, "--system", {str(system)!r}, "--out", {str(tmp_path / "m")!r},
             "--points", "40", "--calibration-seconds", "0", "--kinds", "gp", "--quiet"]) == 0
for command, extra in (("collect", "sim"), ("train-agent", "rl"), ("reproduce", "sim")):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main([command, "--out", "x"]) == 2
    line = f"gpbf {{command}}: needs the '{{extra}}' extra; install it with: pip install 'gpbf[{{extra}}]'"
    assert err.getvalue() == line + "\\n", err.getvalue()
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("gymnasium", "torch", "gpbf_env"))
assert not heavy, heavy
print("ok")
"""
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=ROOT
    )
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stdout + out.stderr
