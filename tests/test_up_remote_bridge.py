"""``xneck up --no-bridge --bridge-at``: the layout that keeps a remote bridge from retrying a console.

The BeagleBone's bridge connecting to the PC's hub retries it while a console hangs, and each retry
costs it a bumpless hold (docs/safety.md, "Peers that stop reading"; tests/test_up_stalled_console.py
for the local stack). With the bridge listening and the PC connecting to it, nothing on the board
retries the PC. Here a twin bridge stands in for the board's.

Real processes, real Zenoh on 127.0.0.1; every process is stopped within bounded time.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from server_harness import stop_process_groups, stop_xneck_up, wait_until
from test_up_child_death import ENV, PY, _child
from test_up_stalled_console import _bridge_state_age_s

from bridge.bus_credentials import ENV_CREDENTIALS, write_new
from bridge.session import free_tcp_port

pytestmark = pytest.mark.e2e


def test_with_a_remote_bridge_listening_the_control_path_connects_to_it_not_to_the_hub(tmp_path: Path) -> None:
    """``xneck up --no-bridge --bridge-at`` (the BeagleBone's bridge listening): the controller
    commands the bridge through its endpoint, the console sees its states, and neither the
    controller nor the bridge has the hub to retry. With credentials (XNECK_ZENOH_CREDENTIALS
    reaches every process of the stack), as on the lab network."""
    bridge_at, hub, port = (f"tcp/127.0.0.1:{free_tcp_port()}", f"tcp/127.0.0.1:{free_tcp_port()}",
                            free_tcp_port())
    url, data = f"http://127.0.0.1:{port}", tmp_path / "d"
    env = ENV | {ENV_CREDENTIALS: str(write_new(tmp_path / "bus-credentials").path)}
    with open(tmp_path / "bridge.log", "wb") as log:
        bridge = subprocess.Popen([*PY, "bridge", "--driver", "twin", "--listen", bridge_at, "--instance", "remote-br"],
                                  stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                  start_new_session=True)
    with open(tmp_path / "up.log", "wb") as log:
        up = subprocess.Popen([*PY, "up", "--no-bridge", "--bridge-at", bridge_at, "--port", str(port), "--hub", hub,
                               "--data-dir", str(data), "--viser-port", str(free_tcp_port())],
                              stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                              start_new_session=True)
    try:
        bridge_log = tmp_path / "bridge.log"
        assert wait_until(lambda: "bumpless ramp done" in bridge_log.read_text(errors="replace"), 120, 0.3), \
            bridge_log.read_text(errors="replace") + (tmp_path / "up.log").read_text()
        assert wait_until(lambda: _bridge_state_age_s(url) < 0.5, 60, 0.5)
        assert f"bridge expected at {bridge_at}" in (tmp_path / "up.log").read_text()
        assert "bus: credentials" in (tmp_path / "up.log").read_text()
        controller = _child(up.pid, "controller")
        assert controller is not None
        argv = Path(f"/proc/{controller}/cmdline").read_text().split("\0")
        assert argv[argv.index("--connect") + 1] == bridge_at and hub not in argv, argv
    finally:
        stop_xneck_up(up)
        stop_process_groups([bridge])


def test_without_bridge_at_xneck_up_says_the_bridge_is_expected_on_the_hub_and_what_that_costs(tmp_path: Path) -> None:
    port, hub = free_tcp_port(), f"tcp/127.0.0.1:{free_tcp_port()}"
    r = subprocess.run([*PY, "up", "--no-bridge", "--port", str(port), "--hub", hub, "--data-dir", str(tmp_path / "d"),
                        "--viser-port", str(free_tcp_port()), "--exit-after", "2"],
                       capture_output=True, text=True, env=ENV, timeout=120, stdin=subprocess.DEVNULL)
    assert "bridge expected on the hub" in r.stdout, r.stdout + r.stderr
    assert "--bridge-at avoid" in r.stdout, r.stdout
    assert "bus: no credentials: anyone on the network can link to the hub and the bridge" in r.stdout, r.stdout


def test_bridge_at_needs_no_bridge_and_a_well_formed_endpoint() -> None:
    for args, says in ((["--bridge-at", "tcp/127.0.0.1:7447"], "needs --no-bridge"),
                       (["--no-bridge", "--bridge-at", "nonsense"], "not of the form")):
        r = subprocess.run([*PY, "up", *args], capture_output=True, text=True, env=ENV, timeout=60,
                           stdin=subprocess.DEVNULL)
        assert r.returncode == 2 and says in r.stderr, r.stdout + r.stderr
