"""The suite runs on its own settings (tests/conftest.py): a lab shell's XNECK_* variables (where
its bridge is, robot mode, a listen address on the lab network) and its ZENOH_RUNTIME reach neither
the suite's tests nor the processes they start, and the run's header and summary name the ones it
ignored (audit and review of session 48)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

CONFTEST = f"""
import importlib.util
import sys
sys.path.insert(0, {str(HERE)!r})
_spec = importlib.util.spec_from_file_location("xneck_tests_conftest", {str(HERE / "conftest.py")!r})
_outer = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_outer)
pytest_report_header = _outer.pytest_report_header
pytest_terminal_summary = _outer.pytest_terminal_summary
"""

MODULE = """
import os, subprocess, sys

from bridge.session import ENV_CONNECT, ENV_LISTEN, ZENOH_RX_WORKERS, endpoints_from_env
from server.settings import Settings


def test_the_lab_shells_settings_are_not_read():
    s = Settings()
    assert (s.host, s.mode, s.connect, s.hub) == ("127.0.0.1", "twin", [], "tcp/127.0.0.1:0")
    assert endpoints_from_env(ENV_LISTEN) is None and endpoints_from_env(ENV_CONNECT) is None
    child = subprocess.run([sys.executable, "-c", "import os; print(sorted(k for k in os.environ if k.startswith('XNECK_')))"],
                           capture_output=True, text=True, check=True).stdout
    assert "XNECK_MODE" not in child and "XNECK_ZENOH" not in child, child
    assert os.environ["XNECK_TEST_RENICE"] == "0" and "XNECK_TEST_RENICE" in child  # the suite's own stay
    assert os.environ["ZENOH_RUNTIME"] == f"(rx: (worker_threads: {ZENOH_RX_WORKERS}))"  # xneck's, not the shell's
"""

LAB_SHELL = {"XNECK_MODE": "robot", "XNECK_CONNECT": '["tcp/192.0.2.1:7447"]', "XNECK_HOST": "0.0.0.0",
             "XNECK_ZENOH_LISTEN": "tcp/0.0.0.0:0", "XNECK_ZENOH_CONNECT": "tcp/192.0.2.1:7447",
             "xneck_hub": "tcp/0.0.0.0:7447",  # the settings read names in any case
             "ZENOH_RUNTIME": "(rx: (worker_threads: 2))"}  # Zenoh's default: the dead-peers test's regression


def test_a_lab_shells_xneck_variables_reach_no_test_and_are_named(tmp_path: Path) -> None:
    suite = tmp_path / "suite"
    suite.mkdir()
    (suite / "conftest.py").write_text(CONFTEST)
    (suite / "test_inner.py").write_text(MODULE)
    env = {**{k: v for k, v in os.environ.items() if k != "XNECK_TEST_TIMELINE"}, **LAB_SHELL,
           "XNECK_TEST_RENICE": "0", "XNECK_TEST_TURNS_DIR": str(tmp_path / "turns"),
           "PYTHONPATH": str(HERE.parent)}
    for quiet in ([], ["-q"]):  # -q, as .ci/run and the README run the suite, shows no header: the summary does
        run = subprocess.run([sys.executable, "-m", "pytest", "-n0", "-p", "no:cacheprovider", "-p", "no:randomly",
                              *quiet, str(suite)], capture_output=True, text=True, timeout=120, cwd=suite, env=env)
        assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
        named = [line for line in run.stdout.splitlines() if line.startswith("xneck: ignored from the environment")]
        assert named and all(name in line for line in named for name in LAB_SHELL), (quiet, named)
