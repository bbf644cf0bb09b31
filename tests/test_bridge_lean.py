"""The bridge runs lean, as on the robot's BeagleBone Blue (issue 20).

- The import path of ``xneck bridge --driver replay|beaglebone`` (composition, hold forces
  included) loads none of the PC's heavy packages: checked on a real bridge process with
  ``-X importtime``, a failure names the module and who imported it.
- The hold forces come from the same model code with numba unavailable (an import hook refuses
  it) as with numba: same forces to 1e-9 N.
- In a fresh virtual environment with only the bridge's dependencies (the base install, numpy at
  Debian 12's 1.24, msgspec built from source as on ARMv7) the bridge starts (hold forces
  included), serves states, rejects a malformed command and disables the drives on SIGTERM.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bridge import bus

ROOT = Path(__file__).resolve().parents[1]
FAKE_RCPY = ROOT / "tests" / "fake_rcpy"
HEAVY = ("numba", "llvmlite", "scipy", "matplotlib", "fastapi", "uvicorn", "viser", "starlette", "pydantic_settings",
         "cv2", "dask", "distributed", "pyarrow")
# Their distributions, which belong in the `pc` extra, never in the base install.
HEAVY_DISTS = {"numba", "llvmlite", "scipy", "matplotlib", "fastapi", "uvicorn", "viser", "starlette", "pydantic-settings",
               "opencv-python", "opencv-python-headless", "dask", "distributed", "pyarrow"}

# Refuses `import numba` (and llvmlite) in a child process: the robot's situation.
NO_NUMBA = """
import importlib.abc, sys
class _NoNumba(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('numba', 'llvmlite'):
            raise ImportError(f'{name} is not installed (test_bridge_lean)')
        return None
sys.meta_path.insert(0, _NoNumba())
"""


@pytest.fixture(scope="module")
def replay_file(tmp_path_factory) -> Path:
    from bridge.archive import write_campaign

    # A recorded bridge run; the identity fields exist from MotorState v2 on.
    identity: dict[str, Any] = {"epoch": "recorded", "bridge": "bridge-lean"} if "epoch" in bus.MotorState.__struct_fields__ else {}
    states = [bus.MotorState(seq=k, stamp_s=0.002 * k, theta_rad=[0.02 * np.sin(k / 40), 0.0, -0.02 * np.sin(k / 40), 0.0],
                             force_applied_N=[10.0] * 4, drive="active", **identity) for k in range(400)]
    return write_campaign(tmp_path_factory.mktemp("replay") / "replay.mcap",
                          [(bus.MOTOR_STATE, k * 2_000_000, s) for k, s in enumerate(states)],
                          {"campaign_id": "lean", "kind": "control"})


def importers(importtime_stderr: str, name: str) -> list[str]:
    """The chain of modules that imported ``name`` (innermost first), from ``-X importtime``
    output: a module is listed after its imports, one indentation level (2 spaces) deeper."""
    rows = []
    for line in importtime_stderr.splitlines():
        m = re.match(r"import time:\s+\d+ \|\s+\d+ \|( *)(\S+)", line)
        if m:
            rows.append((len(m.group(1)) // 2, m.group(2)))
    chain: list[str] = []
    for k, (depth, module) in enumerate(rows):
        if module == name:
            chain, level = [module], depth
            for d, parent in rows[k + 1:]:
                if d < level:
                    chain.append(parent)
                    level = d
            break
    return chain


def heavy_imports(importtime_stderr: str) -> list[str]:
    """One line per heavy top-level package loaded: the package and its import chain."""
    found = []
    for pkg in HEAVY:
        chain = importers(importtime_stderr, pkg)
        if chain:
            found.append(" <- ".join(chain))
    return found


def test_importers_names_the_chain():
    out = ("import time:       10 |         10 |     llvmlite\n"
           "import time:       10 |         20 |   numba\n"
           "import time:       10 |         30 | twin.model.compiled\n"
           "import time:       10 |         40 | server.cli\n")
    assert importers(out, "llvmlite") == ["llvmlite", "numba", "twin.model.compiled"]
    assert heavy_imports(out) == ["numba <- twin.model.compiled", "llvmlite <- numba <- twin.model.compiled"]


@pytest.mark.parametrize("driver", ["replay", "beaglebone"])
def test_bridge_process_imports_nothing_heavy(driver, replay_file):
    """A real `xneck bridge` (hold forces computed at start-up, 20 ticks on the bus) loads no
    numba, llvmlite, scipy, matplotlib, fastapi, uvicorn or viser, numba installed or not."""
    args = ["--driver", driver, "--max-ticks", "20"]
    env = {**os.environ}
    env.pop("XNECK_NO_NUMBA", None)
    if driver == "replay":
        args += ["--replay", str(replay_file)]
    else:  # rcpy faked at the library boundary, as on a PC
        env["PYTHONPATH"] = os.pathsep.join([str(FAKE_RCPY), env.get("PYTHONPATH", "")])
    run = subprocess.run([sys.executable, "-X", "importtime", "-m", "server.cli", "bridge", *args],
                         capture_output=True, text=True, timeout=120, cwd=ROOT, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "stopped after 20 ticks" in run.stderr
    found = heavy_imports(run.stderr)
    assert not found, "the bridge's import path loads heavy modules:\n" + "\n".join(found)


HOLD_SCRIPT = """
import json, sys
import numpy as np
from server.cli.processes import bridge_node  # the composition `xneck bridge` uses
from controller.laws import encoder_hold_forces
from twin.model import compiled
from twin.model.params import load_params
hold = encoder_hold_forces(load_params())
thetas = np.array(json.loads(sys.argv[1]))
print(json.dumps({"numba": compiled.numba_enabled(), "loaded": sorted(m for m in ("numba", "llvmlite", "scipy") if m in sys.modules),
                  "f": [hold(t).tolist() for t in thetas]}))
"""


def test_hold_forces_without_numba_match_the_compiled_model(params):
    from controller.laws import encoder_hold_forces
    from twin.model import compiled

    assert compiled.numba_enabled(), "the PC's venv has numba: this compares the two ways to run the model"
    rng = np.random.default_rng(20)
    thetas = np.vstack([np.zeros(4), rng.uniform(-3.0, 3.0, size=(12, 4)), [[40.0, -40.0, 40.0, -40.0]]])
    env = {k: v for k, v in os.environ.items() if k != "XNECK_NO_NUMBA"}
    run = subprocess.run([sys.executable, "-c", NO_NUMBA + HOLD_SCRIPT, json.dumps(thetas.tolist())],
                         capture_output=True, text=True, timeout=300, cwd=ROOT, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    plain = json.loads(run.stdout)
    assert plain["numba"] is False and plain["loaded"] == []
    hold = encoder_hold_forces(params)
    compiled_f = np.array([hold(t) for t in thetas])
    np.testing.assert_allclose(np.array(plain["f"]), compiled_f, rtol=0, atol=1e-9)
    assert np.all(compiled_f >= params.limits.t_min - 1e-9)


def test_prefer_plain_python_is_refused_once_compiled():
    """Once a kernel is compiled the process keeps numba (same numbers); the bridge command calls
    prefer_plain_python() before importing the model, so it gets the plain path."""
    from twin.model import compiled

    assert compiled.numba_enabled()
    assert compiled.prefer_plain_python() is False
    assert compiled.numba_enabled()


def test_base_install_is_the_bridge_and_meets_debian_armhf():
    """pyproject's base dependencies are the bridge's, with minimums Debian 12 armhf's packages
    meet (python3-numpy 1.24.2); the PC's heavy packages come with the `pc` extra."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    names = {re.split(r"[<>=!~ \[;]", d, maxsplit=1)[0].lower().replace("_", "-"): d for d in project["dependencies"]}
    assert not HEAVY_DISTS & set(names), f"heavy packages in the base install: {sorted(HEAVY_DISTS & set(names))}"
    assert names["numpy"] == "numpy>=1.24"
    pc = {re.split(r"[<>=!~ \[;]", d, maxsplit=1)[0].lower() for d in project["optional-dependencies"]["pc"]}
    assert {"numba", "scipy", "matplotlib", "fastapi", "uvicorn", "viser"} <= pc


def test_armhf_check_script_parses():
    """benchmarks/armhf_bridge.sh (the expensive part, run by hand as root) stays valid bash."""
    run = subprocess.run(["bash", "-n", str(ROOT / "benchmarks" / "armhf_bridge.sh")], capture_output=True, text=True,
                         timeout=30)
    assert run.returncode == 0, run.stderr


# -- the cheap part of the target-platform check (benchmarks/armhf_bridge.sh does the rest) ------

def _lean_venv(path: Path) -> Path:
    """A virtual environment with the project's base install only, as the robot has it:
    numpy at Debian 12's version, msgspec compiled from its source (no ARMv7 wheel exists)."""
    src = path.parent / "src"  # built from a copy: a build never writes into the shared checkout
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for package in ("bridge", "twin", "controller", "server"):
        shutil.copytree(ROOT / package, src / package, ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run([sys.executable, "-m", "venv", str(path)], check=True, timeout=120)
    py = path / "bin" / "python"
    pip = [str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
    run = subprocess.run([*pip, "--no-binary", "msgspec", "numpy==1.24.*", str(src)],
                         capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return py


@pytest.mark.slow
def test_bridge_in_a_venv_with_only_its_dependencies_serves_states(tmp_path, replay_file):
    from bridge.session import free_tcp_port, open_session

    py = _lean_venv(tmp_path / "venv")
    probe = subprocess.run([str(py), "-c", "import importlib.util as u, numpy, msgspec; "
                            f"print(numpy.__version__, [m for m in {HEAVY!r} if u.find_spec(m)])"],
                           capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert probe.returncode == 0, probe.stderr
    assert probe.stdout.split()[0].startswith("1.24.") and probe.stdout.strip().endswith("[]"), probe.stdout

    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as session:
        seen: list[bus.MotorState] = []
        sub = session.declare_subscriber(bus.MOTOR_STATE, lambda s: seen.append(bus.decode(bus.MotorState, s.payload.to_bytes())))
        proc = subprocess.Popen([str(tmp_path / "venv" / "bin" / "xneck"), "bridge", "--driver", "replay", "--replay",
                                 str(replay_file), "--loop", "--connect", hub, "--listen", "tcp/127.0.0.1:0"],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
        try:
            deadline = time.monotonic() + 60
            while len(seen) < 200 and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(0.05)
            assert len(seen) >= 200, f"{len(seen)} states received"
            assert {s.drive for s in seen} == {"inactive"}
            cmd = session.declare_publisher(bus.MOTOR_COMMAND)
            cmd.put(b"{not a force command")  # hostile: counted as rejected, never moves a motor
            time.sleep(0.5)
            assert {s.drive for s in seen} == {"inactive"}
            cmd.undeclare()
        finally:
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=30)
            sub.undeclare()
    assert proc.returncode == 0, out[-3000:]
    assert "rejected 1" in out, out[-2000:]
    assert seen[-1].drive == "disabled"
