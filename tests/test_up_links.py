"""Under ``xneck up`` the control path opens no link to a tool: tools link to it, over its Unix sockets.

Found 2026-11-30 (docs/safety.md, "Peers that stop reading"): with gossip's autoconnect on, the
bridge and the controller opened loopback TCP links to every tool that joined the hub (``ss``: the
controller's socket to the hub itself, the bridge's and the controller's to a tool's listener). A
TCP link to a tool that stops reading lingers on close (SO_LINGER, hard-coded in Zenoh) on the
thread of Zenoh's ``net`` runtime, which also serves every link the process opened: the
controller's to the bridge. The bridge and the controller now open only their ``--connect``
links; a tool links to them by gossip, to their Unix sockets, whose close does not wait.

Real processes, real Zenoh on 127.0.0.1; every process is stopped within bounded time.
"""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import pytest
from proc_net import tcp_sockets
from server_harness import wait_until
from test_up_child_death import _child, _xneck_up

from bridge import bus
from bridge.session import zenoh_config

pytestmark = [pytest.mark.e2e]

#: How long gossip is given to link the tools: the control path linked them within ~1 s before.
GOSSIP_S = 5.0


def _hub(up_log: Path) -> str:
    # said with "xneck is up", once a campaign could start (the console has the bridge's states)
    wait_until(lambda: re.search(r"bus hub (tcp/\S+?);", up_log.read_text()) is not None, 60, 0.1)
    m = re.search(r"bus hub (tcp/\S+?);", up_log.read_text())
    assert m, up_log.read_text()
    return m.group(1)


def test_the_bridge_and_the_controller_open_no_link_to_the_tools_on_the_hub(tmp_path: Path) -> None:
    import zenoh

    with _xneck_up(tmp_path) as (_url, data, up):
        bridge_log = data / "logs" / "bridge.log"
        assert wait_until(lambda: bridge_log.exists() and "bumpless ramp done" in bridge_log.read_text(), 120, 0.3), \
            (tmp_path / "up.log").read_text()
        hub = _hub(tmp_path / "up.log")
        bridge, controller = _child(up.pid, "bridge"), _child(up.pid, "controller")
        assert bridge is not None and controller is not None
        # A tool as every xneck tool is configured (it links by gossip), and one that links to no one
        # by itself: any link between it and the control path is one the control path opened.
        tool_conf = zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[hub])
        passive_conf = zenoh_config(listen=["tcp/127.0.0.1:0"], connect=[hub])
        passive_conf.insert_json5("scouting/gossip/autoconnect", '{router: [], peer: []}')
        states = {"n": 0}
        lock = threading.Lock()

        def on_state(_sample: zenoh.Sample) -> None:
            with lock:
                states["n"] += 1

        with zenoh.open(tool_conf) as tool, zenoh.open(passive_conf) as _passive:
            tool.declare_subscriber(bus.MOTOR_STATE, on_state)
            # The tool hears the bridge: it linked to it (peers do not relay), over its Unix socket.
            assert wait_until(lambda: states["n"] > 100, 30, 0.1), states
            seen: list = []
            deadline = time.monotonic() + GOSSIP_S
            while time.monotonic() < deadline and not seen:
                seen = tcp_sockets([bridge, controller])
                time.sleep(0.1)
            linked_with = {str(z) for z in tool.info.peers_zid()}
            with lock:
                before = states["n"]
            assert wait_until(lambda: states["n"] > before + 100, 10, 0.1), "the tool stopped hearing the bridge"
        names = {bridge: "bridge", controller: "controller"}
        assert not seen, [f"{names[s.pid]}: state {s.state} local port {s.local[1]} remote port {s.remote[1]}"
                          for s in seen]
        assert len(linked_with) >= 3, linked_with  # the console, the bridge and the controller at least
