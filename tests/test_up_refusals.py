"""Issue 13, finding 5: ``xneck up`` refuses before starting anything, on the real processes and
bus: a taken port, another stack on the hub. Nothing here is timed, so, unlike the rest of issue
13's console tests (tests/test_stack_faults.py), this module shares the machine."""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

import pytest
from server_harness import wait_until
from test_stack import ENV, PY, _alive_kinds, _healthy, _procs, _robot_console

from bridge.session import free_tcp_port


def _up_refused(tmp_path: Path, port: int, viser_port: int, hub_port: int) -> tuple[str, Path]:
    """Run ``xneck up`` expecting a refusal: its stderr and its data directory."""
    data = tmp_path / "second"
    r = subprocess.run([*PY, "up", "--port", str(port), "--viser-port", str(viser_port), "--hub",
                        f"tcp/127.0.0.1:{hub_port}", "--data-dir", str(data), "--exit-after", "5"],
                       capture_output=True, text=True, env=ENV, timeout=60)
    assert r.returncode == 3, (r.returncode, r.stdout, r.stderr)
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: xneck up refused to start: "), r.stderr
    assert "xneck is up" not in r.stdout and "Traceback" not in r.stderr
    assert not (data / "logs").exists(), "a child process was started"  # up creates the logs dir only to start them
    return lines[0], data


@pytest.mark.parametrize("taken", ["hub", "port", "viser"])
def test_up_refuses_a_taken_port_before_starting_anything(tmp_path: Path, taken: str) -> None:
    ports = {"hub": free_tcp_port(), "port": free_tcp_port(), "viser": free_tcp_port()}
    with socket.socket() as squatter:  # another program holds the port
        squatter.bind(("127.0.0.1", ports[taken]))
        squatter.listen()
        line, _ = _up_refused(tmp_path, ports["port"], ports["viser"], ports["hub"])
    assert f"127.0.0.1:{ports[taken]}" in line
    assert {"hub": "--hub", "port": "--port", "viser": "--viser-port"}[taken] in line


def test_up_refuses_when_another_stack_answers_on_the_hub(tmp_path: Path) -> None:
    """Finding 5: a second `xneck up` on the hub of a running stack joined its bus and started a
    second bridge and controller before failing with a raw zenoh error."""
    with _procs() as spawn:
        base, hub_port, *_ = _robot_console(spawn, tmp_path, tmp_path / "first", controller=False)
        line, _ = _up_refused(tmp_path, free_tcp_port(), free_tcp_port(), hub_port)
        assert "another xneck stack answers on the hub" in line and "bridge/" in line, line
        assert "--data-dir" in line, line  # all it needs at once (it was refused again for the folder)
        assert _alive_kinds(base) == {"bridge"}  # no second controller joined
        time.sleep(0.5)
    assert "drives enabled" not in (tmp_path / "b.log").read_text()


def test_up_refuses_a_data_directory_in_use_before_starting_anything(tmp_path: Path) -> None:
    """Audit of 2026-11-28: a second `xneck up` on the data directory of a running console started
    its own console, which refused, and printed the tail of the shared logs/server.log: the first
    console's lines, its API token among them."""
    port = free_tcp_port()
    data = tmp_path / "second"  # the directory _up_refused gives the second stack
    with _procs() as spawn:
        (data / "logs").mkdir(parents=True)  # as a first `xneck up` leaves it: its console's log there
        spawn(["server", "--port", str(port), "--data-dir", str(data), "--hub", f"tcp/127.0.0.1:{free_tcp_port()}"],
              data / "logs" / "server.log")
        base = f"http://127.0.0.1:{port}"
        assert wait_until(lambda: _healthy(base), 60, 0.3), (data / "logs" / "server.log").read_text()
        log_before = (data / "logs" / "server.log").read_text()
        r = subprocess.run([*PY, "up", "--port", str(free_tcp_port()), "--viser-port", str(free_tcp_port()), "--hub",
                            f"tcp/127.0.0.1:{free_tcp_port()}", "--data-dir", str(data), "--exit-after", "5"],
                           capture_output=True, text=True, env=ENV, timeout=60)
        assert r.returncode == 3, (r.returncode, r.stdout, r.stderr)
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and "in use by another xneck server" in lines[0], r.stderr
        assert f":{port}" in log_before and f":{port}" not in r.stderr + r.stdout  # none of the first's log
        assert (data / "logs" / "server.log").read_text() == log_before  # nothing of a second console in it
