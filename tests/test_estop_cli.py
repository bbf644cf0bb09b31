"""`xneck estop engage|release|status` as a lab runs it (a terminal beside, or instead of, the
console's button): the real command in a process of its own, a :class:`bridge.node.BridgeNode` on
the twin driver ticking in this process, real Zenoh sessions on 127.0.0.1.

Before it, the only e-stop holder was the console: with the console down or hung the operator had
no way to latch the bridge but its power (session 40's open point)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from busutil import bus_pair, wait_until
from test_bridge_node import _node

from bridge.estop_holder import EStopHolder
from bridge.session import free_tcp_port


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("XNECK_ZENOH_")}
    return {**env, "PYTHONUNBUFFERED": "1"}


def _xneck(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "server.cli", "estop", *args], capture_output=True, text=True,
                          env=_env(), timeout=timeout_s, check=False)


@contextmanager
def _ticking(node) -> Iterator[None]:
    """The node's ticks every 5 ms in a thread (each publishes its state), as the bridge's loop."""
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            node.tick()
            time.sleep(0.005)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    try:
        yield
    finally:
        stop.set()
        th.join(5)


def test_engage_latches_the_bridge_and_release_lets_it_go_each_answered_by_the_bridges_word(params):
    with bus_pair() as (hub, _hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        try:
            with _ticking(node):
                assert wait_until(lambda: node.ticks > 10, 5)
                r = _xneck("engage", "--connect", hub, "--reason", "cable rubbing at pulley 3", "--json")
                assert r.returncode == 0, r.stderr
                out = json.loads(r.stdout)
                assert out["ok"] and out["outcome"] == "engaged", out
                assert [(b["engaged"], b["drive"]) for b in out["bridges"]] == [(True, "disabled")], out
                assert node.safety.estop_engaged and node.mode == "disabled"
                assert node.estop_reason == "cable rubbing at pulley 3"
                # The command has gone (its token with it): the bridge stays latched.
                assert wait_until(lambda: not node.estop_holders.holders, 5)
                r = _xneck("status", "--connect", hub, "--wait-s", "0.3")
                assert r.returncode == 0, r.stderr
                assert "e-stop engaged (cable rubbing at pulley 3), drives disabled" in r.stdout, r.stdout
                assert node.mode == "disabled"

                r = _xneck("release", "--connect", hub)
                assert r.returncode == 0, r.stderr
                assert "e-stop released" in r.stdout and "drives inactive" in r.stdout, r.stdout
                assert not node.safety.estop_engaged and node.mode == "inactive"
        finally:
            node.shutdown()


def test_release_refuses_to_end_an_estop_another_holder_keeps_and_names_it(params):
    """The console's engaged button (a live holder): a terminal's release is not obeyed, and says
    whose it is; once that holder releases, the bridge is free."""
    with bus_pair() as (hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        console = EStopHolder(hub_session, "console-abc123")
        try:
            with _ticking(node):
                console.engage("operator e-stop")
                assert wait_until(lambda: node.safety.estop_engaged and "console-abc123" in node.estop_holders.holders, 5)
                r = _xneck("release", "--connect", hub, "--wait-s", "0.5", "--json")
                assert r.returncode == 1, r.stdout + r.stderr
                out = json.loads(r.stdout)
                assert not out["ok"] and out["holders"] == ["console-abc123"], out
                assert "held by console-abc123" in out["message"], out
                assert node.safety.estop_engaged and node.mode == "disabled"
                console.release("cleared at the console")
                assert wait_until(lambda: not node.safety.estop_engaged, 5)
        finally:
            console.close()
            node.shutdown()


def test_hold_latches_a_bridge_that_starts_later_and_leaving_releases_nothing(params):
    """``--hold`` with no bridge up: nothing confirms, the command keeps its token; the bridge
    that starts then comes up latched; SIGTERM ends the command and the bridge stays latched."""
    with bus_pair() as (hub, _hub_session, connect):
        proc = subprocess.Popen([sys.executable, "-m", "server.cli", "estop", "engage", "--hold", "--wait-s", "0.3",
                                 "--connect", hub, "--reason", "before the bridge"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env=_env())
        node = None
        try:
            assert proc.stdout is not None
            assert "holding the e-stop as cli-" in proc.stdout.readline()
            node = _node(connect(), params, command_timeout_s=5.0)
            assert node.safety.estop_engaged and node.mode == "disabled"  # latched before its first tick
            with _ticking(node):
                assert wait_until(lambda: node.estop_reason == "before the bridge", 5), node.estop_reason
                proc.send_signal(signal.SIGTERM)
                out, err = proc.communicate(timeout=20)
                assert proc.returncode == 0, err  # a bridge confirmed while it held
                assert "bridge " in out and "e-stop engaged (before the bridge)" in out, out
                assert wait_until(lambda: not node.estop_holders.holders, 5)
                time.sleep(0.05)
                assert node.safety.estop_engaged and node.mode == "disabled"
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate(timeout=10)
            if node is not None:
                node.shutdown()


def test_no_bridge_is_a_clear_error_and_exit_1():
    nobody = f"tcp/127.0.0.1:{free_tcp_port()}"
    for args in (("engage", "--wait-s", "0.3"), ("release", "--wait-s", "0.3"), ("status", "--wait-s", "0.3")):
        r = _xneck(*args, "--connect", nobody)
        assert r.returncode == 1, (args, r.stdout, r.stderr)
        assert f"no bridge state heard within 0.3 s through {nobody}" in r.stderr, (args, r.stderr)
