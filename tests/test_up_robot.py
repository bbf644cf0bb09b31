"""``xneck up --robot``: a bridge that cannot disable its own drives has them disabled for it.

Audit of 2026-11-26: a hung bridge (its loop stopped, here by SIGSTOP) was noticed by nobody under
``xneck up --robot`` (the ESCONs went on driving the last currents), and once the stack was stopped
its SIGKILL left the enable lines high. The launcher now watches the bridge's states on the bus:
a bridge silent for ``BRIDGE_HUNG_S`` while its process lives is killed, the stack stops as for a
death, and ``xneck bridge --drives-off`` disables the drives. The board is tests/fake_rcpy (rcpy
cannot exist here), which logs every level and set value to ``FAKE_RCPY_LOG`` across processes.

Real processes, real Zenoh on 127.0.0.1, real uvicorn over HTTP; stopped within bounded time.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from server_harness import wait_until
from test_up_child_death import _child, _get

from bridge.drivers.beaglebone import BLUE_GP0_PINS
from bridge.session import free_tcp_port

pytestmark = pytest.mark.e2e

ROOT = Path(__file__).resolve().parents[1]
PY = [sys.executable, "-m", "server.cli"]


def _board_log(path: Path) -> list[tuple[int, str, str, str]]:
    """(pid, what, channel or pin, value) lines the fake board was told, in order."""
    if not path.exists():
        return []
    return [(int(p), w, c, v) for p, w, c, v in (line.split() for line in path.read_text().splitlines())]


def _levels(lines, pids=None) -> dict[int, int]:
    """The last level each enable pin was set to (by ``pids`` if given)."""
    out: dict[int, int] = {}
    for pid, what, pin, value in lines:
        if what == "gpio" and (pids is None or pid in pids):
            out[int(pin)] = int(value)
    return out


def test_a_hung_robot_bridge_is_killed_and_its_drives_disabled(tmp_path: Path) -> None:
    board = tmp_path / "rcpy.log"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "FAKE_RCPY_LOG": str(board),
           "PYTHONPATH": os.pathsep.join([str(ROOT / "tests" / "fake_rcpy"), os.environ.get("PYTHONPATH", "")])}
    port, hub = free_tcp_port(), f"tcp/127.0.0.1:{free_tcp_port()}"
    base = f"http://127.0.0.1:{port}"
    with open(tmp_path / "up.log", "wb") as log:
        up = subprocess.Popen([*PY, "up", "--robot", "--port", str(port), "--hub", hub, "--data-dir", str(tmp_path / "d"),
                               "--viser-port", str(free_tcp_port()), "--exit-after", "120"],
                              stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                              start_new_session=True)
    bridge = None
    try:
        def enabled() -> bool:
            health = _get(base + "/api/system/health", 2) or {}
            return (health.get("bridge") or {}).get("drive") == "active"

        assert wait_until(enabled, 90, 0.3), (tmp_path / "up.log").read_text()[-3000:]
        bridge = _child(up.pid, "bridge")
        assert bridge is not None
        assert set(_levels(_board_log(board), {bridge}).values()) == {1}  # the controller enabled every drive
        os.kill(bridge, signal.SIGSTOP)  # hung: alive, its loop (watchdog, e-stop) stopped
        assert up.wait(60) == 1
    finally:
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait(10)
        if bridge is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(bridge, signal.SIGKILL)
    printed = (tmp_path / "up.log").read_text()
    assert "error: the bridge hung (no motor state for" in printed, printed[-3000:]
    assert "its drives were disabled by `xneck bridge --drives-off`" in printed, printed[-3000:]
    lines = _board_log(board)
    others = {pid for pid, *_ in lines} - {bridge}
    assert others, "nothing but the bridge touched the board"
    assert _levels(lines) == dict.fromkeys(BLUE_GP0_PINS, 0)  # every enable line ends off
    assert _levels(lines, others) == dict.fromkeys(BLUE_GP0_PINS, 0)  # set off by the drives-off process


def test_drives_off_is_refused_for_a_driver_without_motors() -> None:
    r = subprocess.run([*PY, "bridge", "--driver", "twin", "--drives-off"], capture_output=True, text=True, timeout=60)
    assert r.returncode != 0 and "--drives-off is for --driver beaglebone" in r.stderr, r.stderr
