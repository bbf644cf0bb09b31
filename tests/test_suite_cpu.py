"""benchmarks/suite_cpu.py: a command's CPU by kind of process (docs/testing.md, "Where the CPU goes")."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.background

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("suite_cpu", ROOT / "benchmarks" / "suite_cpu.py")
assert _spec is not None and _spec.loader is not None
suite_cpu = importlib.util.module_from_spec(_spec)
sys.modules["suite_cpu"] = suite_cpu  # its dataclass looks its module up there
_spec.loader.exec_module(suite_cpu)

PY = "/repo/.venv/bin/python"


@pytest.mark.parametrize("cmdline, kind", [
    (f"{PY} -m server.cli controller --law 2 --listen unixsock-stream//tmp/x/controller.sock", "xneck controller"),
    (f"{PY} /repo/.venv/bin/xneck up --port 8765", "xneck up"),
    (f"{PY} -m server.cli twin --realtime --seed 0", "xneck twin"),  # forked: the command line it stands for
    (f"{PY} /repo/tests/xneck_forkserver.py /tmp/fs.sock", "fork server (tests)"),
    (f"{PY} -u -c import sys;exec(eval(sys.stdin.readline()))", "pytest worker (tests run in it)"),
    ("node /repo/.venv/lib/python3.11/site-packages/pyright/dist/pyright.js --outputjson", "pyright"),
    ("/usr/lib/chromium/chromium --type=renderer --headless", "chromium"),
    ("/proc/self/exe --type=utility --utility-sub-type=network.mojom.NetworkService", "chromium"),
    (f"{PY} -m controller.warmup", "numba warm-up (set-up)"),
    (f"{PY} -m pip install --no-compile -e .[pc,test]", "pip"),
    ("/repo/.venv/bin/uv pip install --python /repo/.venv/bin/python -e .[pc,test]", "uv"),
    (f"{PY} /repo/benchmarks/_bus_peer.py publish tcp/127.0.0.1:7447", "python _bus_peer.py"),
    ("/usr/bin/gcc -O2 -c x.c", "gcc"),
    (f"{PY} -c from multiprocessing.spawn import spawn_main; spawn_main(tracker_fd=5, pipe_handle=7) --multiprocessing-fork",
     "python multiprocessing child"),
    (f"{PY} -m pytest -q", "pytest"),
    (f"{PY} /tmp/pytest-of-root/pytest-3/t0/burn.py", "python burn.py"),  # not pytest for its folder
    ("", "(no command line)"),
])
def test_a_command_line_is_named_by_its_kind(cmdline: str, kind: str) -> None:
    assert suite_cpu.kind(cmdline) == kind


BURN = """\
import os, sys, time
def burn(s):
    t = time.process_time()
    while time.process_time() - t < s:
        pass
    time.sleep(0.6)  # sampled at least once after its CPU: counted whole
r, w = os.pipe()
if os.fork() == 0:  # an orphan: its parent exits before it, it must still be counted
    if os.fork() == 0:
        os.write(w, str(os.getpid()).encode())
        burn(0.4)
    os._exit(0)
os.wait()
orphan = int(os.read(r, 32))
burn(0.5)
for _ in range(100):  # reaped once it exits, as init would: else kill(pid, 0) finds its zombie
    try:
        os.kill(orphan, 0)
    except ProcessLookupError:
        sys.exit(3)
    time.sleep(0.1)
sys.exit(4)
"""


def test_the_commands_children_and_an_orphaned_grandchild_are_counted_and_the_exit_code_kept(tmp_path: Path) -> None:
    script = tmp_path / "burn.py"
    script.write_text(BURN)
    out = tmp_path / "cpu.json"
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_cpu.py"), "--period-s", "0.05",
                          "--json", str(out), "--", sys.executable, str(script)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 3, run.stderr  # the command's own exit code: it saw its orphan go (4: a zombie)
    figures = json.loads(out.read_text())
    burners = figures["kinds"]["python burn.py"]
    assert burners["processes"] >= 2, figures  # the script and the orphaned grandchild (its parent, if seen alive)
    assert burners["cpu_s"] >= 0.85, figures  # 0.5 + 0.4 s of CPU, each sampled after it
    assert figures["cpu_s"] >= burners["cpu_s"] - 0.02, figures  # getrusage saw the orphan too: reaped here
    assert "not sampled" in run.stdout and "python burn.py" in run.stdout


def test_no_command_is_a_usage_error() -> None:
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_cpu.py"), "--"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "no command" in run.stderr


def test_a_command_that_cannot_start_is_one_line_and_exit_127(tmp_path: Path) -> None:
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_cpu.py"), "--", str(tmp_path / "nothing")],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 127 and run.stderr.strip() == f"suite_cpu.py: {tmp_path / 'nothing'}: No such file or directory"


def test_an_anonymous_child_is_named_with_its_parents_kind(tmp_path: Path) -> None:
    script = tmp_path / "parent.py"
    script.write_text("import subprocess, sys\n"
                      "subprocess.run([sys.executable, '-c', 'import time; time.sleep(0.5)'], check=True)\n")
    out = tmp_path / "cpu.json"
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_cpu.py"), "--period-s", "0.05",
                          "--json", str(out), "--", sys.executable, str(script)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert json.loads(out.read_text())["kinds"]["python -c (from python parent.py)"]["processes"] == 1


def test_a_process_outside_the_command_is_the_machines_not_the_commands(tmp_path: Path) -> None:
    """A VM's own processes (its memory monitor's kernel thread, its agent) took about 8 % of a
    suite run's CPU (docs/testing.md): counted apart, as the machine's, never in the command's."""
    burner = subprocess.Popen([sys.executable, "-c", "import time\nend = time.process_time() + 30\n"
                               "while time.process_time() < end: pass"])
    try:
        out = tmp_path / "cpu.json"
        run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "suite_cpu.py"), "--period-s", "0.05",
                              "--json", str(out), "--", sys.executable, "-c", "import time; time.sleep(1.0)"],
                             capture_output=True, text=True, timeout=60)
    finally:
        burner.kill()
        burner.wait(10)
    assert run.returncode == 0, run.stderr
    figures = json.loads(out.read_text())
    assert figures["cpu_s"] < 0.5, figures  # the sleeper only
    assert figures["outside"].get("[python]", 0.0) > 0.3, figures  # the burner, beside it
    assert figures["machine_busy_s"] >= figures["outside"]["[python]"], figures
    assert "the machine meanwhile" in run.stdout
