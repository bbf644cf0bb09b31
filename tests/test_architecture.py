"""The tree's static rules: one-way layers (import-linter), lint (ruff) and types (pyright).

Each tool's configuration lives in pyproject.toml; a failure shows the tool's own report.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

# The tools run at nice 19: this module starts beside the realtime ones (tests/conftest.py) and
# takes only the CPU they leave (about one of two), never theirs. Alone, nice changes nothing.
pytestmark = pytest.mark.background

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _tool(name: str) -> str:
    """The tool installed beside this interpreter (the `test` extra), else the one on PATH."""
    path = BIN / name
    if path.exists():
        return str(path)
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: pip install -e '.[test]'")
    return found


def _run(argv: list[str], timeout_s: float) -> None:
    # coreutils' nice, not preexec_fn=os.nice: a pytest worker has threads, and preexec_fn may deadlock then
    niced = ["nice", "-n", "19", *argv] if shutil.which("nice") else argv
    done = subprocess.run(niced, cwd=ROOT, capture_output=True, text=True, timeout=timeout_s, check=False)
    if done.returncode != 0:
        pytest.fail(f"{' '.join(argv)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}", pytrace=False)


def test_layers_import_one_way():
    """bridge <- twin <- controller <- server, imports inside functions included."""
    _run([_tool("lint-imports"), "--no-cache"], timeout_s=300)


def test_ruff_is_clean():
    _run([_tool("ruff"), "check", "--no-cache", "."], timeout_s=300)


def test_pyright_is_clean():
    _run([_tool("pyright")], timeout_s=900)


def test_no_script_folder_shadows_a_package():
    """`python benchmarks/NAME.py` puts benchmarks/ first on sys.path (issue 21): a script named like a
    package (benchmarks/twin.py did) hides the real package and the script dies on a circular import."""
    packages = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()}
    assert {"bridge", "twin", "controller", "server"} <= packages
    for folder in ("benchmarks", "docs", ".ci"):
        names = {p.stem for p in (ROOT / folder).glob("*.py")} | {p.name for p in (ROOT / folder).iterdir() if p.is_dir()}
        assert not names & packages, f"{folder}/ shadows {sorted(names & packages)} when its scripts run"
