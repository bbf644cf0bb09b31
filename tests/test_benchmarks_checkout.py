"""A benchmark times the checkout it is run from (benchmarks/_repo.py).

The venv's editable install maps the project's packages to the checkout it was installed from;
until 2026-11-30 a benchmark run from a second checkout (a worktree, a fresh clone measured with
the first one's venv) imported the first one's code, and so did the processes it started."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.background

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"bridge", "twin", "controller", "server"}

PROBE = """\
{first}
import subprocess, sys
import twin
print(twin.__file__)
print(subprocess.run([sys.executable, "-c", "import twin; print(twin.__file__)"], cwd="/",  # as `xneck`: not from here
                     capture_output=True, text=True, check=True).stdout.strip())
"""


def _probe(checkout: Path, first: str) -> list[str]:
    (checkout / "benchmarks" / "probe.py").write_text(PROBE.format(first=first))
    r = subprocess.run([sys.executable, "benchmarks/probe.py"], cwd=checkout, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.split()


def test_a_benchmark_run_from_another_checkout_imports_that_checkouts_packages_in_it_and_its_children(tmp_path):
    other = tmp_path / "other-checkout"
    (other / "benchmarks").mkdir(parents=True)
    (other / "twin").mkdir()
    (other / "twin" / "__init__.py").write_text('"""another checkout\'s twin"""\n')
    shutil.copy(ROOT / "benchmarks" / "_repo.py", other / "benchmarks" / "_repo.py")
    mine = str((other / "twin" / "__init__.py").resolve())
    # without it, the installed checkout's code (what the benchmarks timed until 2026-11-30)
    assert mine not in _probe(other, "")
    assert _probe(other, "import _repo") == [mine, mine]


def _module_imports(path: Path) -> list[tuple[int, str]]:
    """(line, top-level module) of the module-level imports of ``path``, in order."""
    out = []
    body = ast.parse(path.read_text()).body
    for node in [*body, *(n for t in body if isinstance(t, ast.Try) for n in t.body)]:
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name.split(".")[0]) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.lineno, node.module.split(".")[0]))
    return sorted(out)


def test_every_benchmark_imports_repo_before_the_projects_packages() -> None:
    checked = []
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        imports = _module_imports(path)
        project = [line for line, name in imports if name in PACKAGES | {"_bus_peer"}]
        if not project:
            continue
        repo = [line for line, name in imports if name == "_repo"]
        assert repo and repo[0] < project[0], f"{path.name}: import _repo before line {project[0]}"
        checked.append(path.name)
    assert len(checked) >= 15, checked
