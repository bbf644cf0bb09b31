"""`xneck estop engage|release|status` as a lab runs it (a terminal beside, or instead of, the
console's button): the real command in a process of its own, a :class:`bridge.node.BridgeNode` on
the twin driver ticking in this process, real Zenoh sessions on 127.0.0.1.

Before it, the only e-stop holder was the console: with the console down or hung the operator had
no way to latch the bridge but its power (session 40's open point)."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

from busutil import bus_pair, repeating, wait_until
from test_bridge_node import _node

from bridge.estop_holder import EStopHolder
from bridge.session import free_tcp_port


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("XNECK_ZENOH_")}
    return {**env, "PYTHONUNBUFFERED": "1"}


def _xneck(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "server.cli", "estop", *args], capture_output=True, text=True,
                          env=_env(), timeout=timeout_s, check=False)


def _ticking(node):
    """The node's ticks every 5 ms in a thread (each publishes its state), as the bridge's loop."""
    return repeating(node.tick, 0.005)


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


def _line(stream, timeout_s: float = 15.0) -> str:
    """The next line of a child's pipe, or '' after ``timeout_s`` (a line that never comes must
    fail the test, not hang it: the restart check hung so before its fix)."""
    import threading

    got: list[str] = []
    reader = threading.Thread(target=lambda: got.append(stream.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    return got[0] if got else ""


def test_hold_latches_a_bridge_that_starts_later_and_leaving_releases_nothing(params):
    """``--hold`` with no bridge up: nothing confirms, the command keeps its token; the bridge
    that starts then comes up latched, and so does its restart under the same name (systemd's:
    review of session 42, the two runs had ended the hold as a 'conflict', exit 1); SIGTERM ends
    the command and the bridge stays latched."""
    with bus_pair() as (hub, _hub_session, connect):
        proc = subprocess.Popen([sys.executable, "-m", "server.cli", "estop", "engage", "--hold", "--wait-s", "0.3",
                                 "--connect", hub, "--reason", "before the bridge", "--json"], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env=_env())
        node = None
        try:
            assert proc.stderr is not None  # with --json the progress lines go to stderr
            assert "holding the e-stop as cli-" in _line(proc.stderr)
            node = _node(connect(), params, command_timeout_s=5.0, instance="beaglebone-lab")
            # latched once the command's token reaches the new bridge: at its start when the link is
            # up then, else when it comes (final CI of session 41, loaded: after the start; no
            # command here, so the drives stay off meanwhile: docs/safety.md rule 4)
            node.tick()
            assert wait_until(lambda: node.safety.estop_engaged, 10)
            node.tick()
            assert node.mode == "disabled"
            with _ticking(node):
                assert wait_until(lambda: node.estop_reason == "before the bridge", 5), node.estop_reason
                assert "bridge beaglebone-lab: e-stop engaged (before the bridge)" in _line(proc.stderr)
            node.shutdown()  # the board's bridge restarted: a new run under its name
            first_epoch, node = node.epoch, _node(connect(), params, command_timeout_s=5.0, instance="beaglebone-lab")
            with _ticking(node):
                assert wait_until(lambda: node.estop_reason == "before the bridge", 10), node.estop_reason
                assert "bridge beaglebone-lab: e-stop engaged (before the bridge)" in _line(proc.stderr)
                proc.send_signal(signal.SIGTERM)
                try:
                    proc.wait(20)  # what it printed is small: no pipe fills meanwhile
                except subprocess.TimeoutExpired:  # where it waits (it dumps its threads on SIGUSR1)
                    proc.send_signal(signal.SIGUSR1)
                    time.sleep(1.0)
                    proc.kill()
                    raise AssertionError(f"no exit 20 s after SIGTERM: {proc.communicate(timeout=10)[1][-6000:]}") from None
                out, err = proc.stdout.read(), proc.stderr.read()  # past what _line's readline() buffered
                assert proc.returncode == 0, err  # a bridge confirmed while it held
                answer = json.loads(out)  # stdout is the one JSON object (review of session 41)
                assert answer["ok"] and [b["reason"] for b in answer["bridges"]] == ["before the bridge"], answer
                assert answer["bridges"][0]["epoch"] == node.epoch != first_epoch and not answer["conflicts"], answer
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


def test_a_bridge_heard_that_does_not_latch_makes_the_engage_fail_naming_it(params):
    """Review of session 41: a bridge heard and never latched (here a peer stating as bridge
    "deaf") was left out and the engage reported success."""
    from bridge import bus
    from bridge.session import publisher

    with bus_pair() as (hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        deaf = publisher(hub_session, bus.MOTOR_STATE)
        seq = itertools.count(1)

        def deaf_bridge() -> None:
            deaf.put(bus.MotorState(seq=next(seq), stamp_s=time.time(), theta_rad=[0.0] * 4,
                                    force_applied_N=[10.0] * 4, drive="active", epoch="e-deaf", bridge="deaf"))

        try:
            with _ticking(node), repeating(deaf_bridge, 0.01):
                r = _xneck("engage", "--connect", hub, "--wait-s", "1", "--json")
                assert r.returncode == 1, r.stdout + r.stderr
                out = json.loads(r.stdout)
                assert out["outcome"] == "partial" and "NOT on deaf" in out["message"], out
                assert {b["bridge"]: b["engaged"] for b in out["bridges"]} == {node.instance: True, "deaf": False}
                assert node.safety.estop_engaged
        finally:
            node.shutdown()


def test_a_latin1_reason_and_the_bridges_listen_endpoint_in_the_environment_still_engage(params):
    """Review of session 41: a ``--reason`` typed in a Latin-1 terminal (bytes Python keeps as
    lone surrogates) failed to encode and sent nothing; a shell sharing the bridge's environment
    (``XNECK_ZENOH_LISTEN`` = the bridge's port) had the command bind that port and fail."""
    with bus_pair() as (hub, _hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        try:
            with _ticking(node):
                r = subprocess.run([sys.executable, "-m", "server.cli", "estop", "engage", "--connect", hub,
                                    "--reason", b"c\xe2ble coinc\xe9\n\x1b[2Jforged"], capture_output=True,
                                   env={**_env(), "XNECK_ZENOH_LISTEN": hub}, timeout=60, check=False)
                assert r.returncode == 0, r.stderr
                assert node.safety.estop_engaged and node.estop_reason == "c?ble coinc?  [2Jforged", node.estop_reason
        finally:
            node.shutdown()


def test_the_default_endpoint_is_the_bridge_of_the_one_xneck_up_running(tmp_path):
    """Not the hub: the console hosting it may be what hangs (review of session 41). A folder a
    killed stack left, whose pid another process has taken since, is no stack (the fix's review:
    it had made two stacks of one and the engage sent nothing)."""
    from server.cli.up import BRIDGE_ENDPOINT_FILE, SOCKETS_PREFIX, stack_bridge_endpoints

    up = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "xneck", "up"])  # argv as xneck up's
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # took a dead stack's pid
    # Popen returns once the child is forked: until it has exec'd, /proc shows the parent's command
    # line (a loaded CI saw no stack at all)
    assert wait_until(lambda: b"\0xneck\0up" in Path(f"/proc/{up.pid}/cmdline").read_bytes(), 10, 0.01)
    try:
        for pid, endpoint in ((up.pid, "unixsock-stream//tmp/x/bridge.sock"), (other.pid, "unixsock-stream//tmp/y"),
                              (999999999, "tcp/127.0.0.1:1")):  # no such pid
            folder = tmp_path / f"{SOCKETS_PREFIX}{pid}-abc"
            folder.mkdir()
            (folder / BRIDGE_ENDPOINT_FILE).write_text(endpoint + "\n")
        (tmp_path / f"{SOCKETS_PREFIX}{up.pid}-nofile").mkdir()  # a stack that wrote no endpoint
        assert stack_bridge_endpoints(tmp_path) == {up.pid: "unixsock-stream//tmp/x/bridge.sock"}
    finally:
        for proc in (up, other):
            proc.kill()
            proc.wait(10)


def test_an_engage_whose_message_fails_still_holds_the_token(params):
    """The holder's engage published first and declared its token after: a publication that
    raised (a reason that did not encode, a closed publisher) lost both (review of session 41)."""
    import pytest

    with bus_pair() as (_hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        holder = EStopHolder(hub_session, "console-failing")

        def broken(*_a, **_k) -> None:
            raise OSError("link gone")

        holder._pub.put = broken  # pyright: ignore[reportAttributeAccessIssue]
        try:
            with _ticking(node):
                with pytest.raises(OSError):
                    holder.engage("operator e-stop")
                assert holder.holds
                assert wait_until(lambda: node.safety.estop_engaged, 5)
                assert "console-failing" in node.estop_reason
        finally:
            holder.close()
            node.shutdown()


def test_a_release_forged_in_a_live_holders_name_does_not_end_its_estop(params):
    """Review of session 41: any peer's release whose attachment named the console (its name is
    public: ``xneck estop status`` prints it) ended the e-stop the console still held."""
    from bridge import bus
    from bridge.session import estop_holder_attachment, publisher

    with bus_pair() as (_hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        console = EStopHolder(hub_session, "console-abc123")
        forger = publisher(connect(), bus.ESTOP)
        try:
            with _ticking(node):
                console.engage("operator e-stop")
                assert wait_until(lambda: "console-abc123" in node.estop_holders.holders, 5)
                n = node.estop_received
                forged = bus.EStop(seq=1, stamp_s=time.time(), engaged=False, reason="forged")
                # Sent until heard: a put before the forger's session has linked goes nowhere.
                assert wait_until(lambda: (forger.put(forged, attachment=estop_holder_attachment("console-abc123")),
                                           node.estop_received > n)[1], 5, 0.05)
                time.sleep(0.1)
                assert node.safety.estop_engaged and node.mode == "disabled"
                console.release("cleared at the console")  # its token goes, then its release
                assert wait_until(lambda: not node.safety.estop_engaged, 5)
        finally:
            console.close()
            node.shutdown()


def _fake_states(session, states: list[dict]) -> Callable[[], None]:
    """A peer's step publishing ``states`` (made-up ``MotorState`` fields: bridge, epoch,
    estop_engaged, drive) on the bridges' key, encoded once: a hostile or misconfigured peer."""
    from bridge import bus

    pub = session.declare_publisher(bus.MOTOR_STATE)
    payloads = [bus.encode(bus.MotorState(seq=1, stamp_s=1.0, theta_rad=[0.0] * 4, force_applied_N=[0.0] * 4, **s))
                for s in states]

    def step() -> None:
        for p in payloads:
            pub.put(p)

    return step


def _each_command_under_a_console_estop(node, console, hub: str, outcome: str) -> Iterator[tuple[str, dict]]:
    """With ``console`` engaging the e-stop on ``node``: run status, release and engage through
    ``hub``, check each fails with ``outcome`` (exit 1), and give its JSON for the caller's
    checks; the bridge stays latched throughout."""
    console.engage("operator e-stop")
    assert wait_until(lambda: node.safety.estop_engaged, 5)
    for command in ("status", "release", "engage"):
        r = _xneck(command, "--connect", hub, "--wait-s", "1", "--json")
        assert r.returncode == 1, (command, r.stdout, r.stderr)
        out = json.loads(r.stdout)
        assert not out["ok"] and out["outcome"] == outcome, (command, out)
        yield command, out
    assert node.safety.estop_engaged and node.mode == "disabled"


def test_more_bridges_than_the_cap_fail_every_command_as_crowded(params):
    """Audit of session 42: 16 made-up bridges heard first filled the CLI's 16 places; ``status``
    listed only them and ``release`` said "released" (exit 0) while the real bridge stayed latched."""
    with bus_pair() as (hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        console = EStopHolder(hub_session, "console-abc123")
        # On the hub's session, which the commands link to first (see the conflict test below).
        flood = _fake_states(hub_session, [{"bridge": f"a{k:02d}", "epoch": "e", "drive": "inactive"} for k in range(16)])
        try:
            with _ticking(node), repeating(flood, 0.002):
                for command, out in _each_command_under_a_console_estop(node, console, hub, "crowded"):
                    assert "more than 16 bridges answered" in out["message"], (command, out)
                    assert out["bridges_heard"] == 17 and len(out["bridges"]) == 16, (command, out)
                    assert out["unlisted"] == 1, (command, out)
        finally:
            console.close()
            node.shutdown()


def test_states_with_an_invalid_bridge_name_are_ignored_counted_and_never_listed(params):
    """A name no bridge can have (a zero-width character making a near twin of the real bridge's,
    a space, a slash, none, too long; or a run id as bad) is no bridge's word: an engage is not
    made partial by it and no listing shows it; the report counts it."""
    with bus_pair() as (hub, _hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        bad = [node.instance + "\u200b", "has space", "a/b", "", "x" * 65, "tw\x1b[2Jin"]
        junk = _fake_states(connect(), [{"bridge": b, "epoch": "e", "drive": "active"} for b in bad]
                            + [{"bridge": "good-name", "epoch": "e\u200b", "drive": "active"}])
        try:
            with _ticking(node), repeating(junk, 0.005):
                r = _xneck("engage", "--connect", hub, "--wait-s", "1", "--json")
                assert r.returncode == 0, r.stdout + r.stderr
                out = json.loads(r.stdout)
                assert out["outcome"] == "engaged" and [b["bridge"] for b in out["bridges"]] == [node.instance], out
                assert out["invalid_states"] > 0 and "with an invalid bridge name" in out["message"], out
                r = _xneck("status", "--connect", hub, "--wait-s", "0.5")
                assert r.returncode == 0, r.stdout + r.stderr
                assert [line.split(":")[0] for line in r.stdout.splitlines() if line.startswith("bridge ")] == [
                    f"bridge {node.instance}"], r.stdout
                assert "with an invalid bridge name" in r.stdout and "good-name" not in r.stdout, r.stdout
                r = _xneck("release", "--connect", hub, "--wait-s", "1", "--json")
                assert r.returncode == 0, r.stdout + r.stderr
                assert json.loads(r.stdout)["outcome"] == "released"
                assert not node.safety.estop_engaged
        finally:
            node.shutdown()


def test_two_runs_answering_under_one_bridge_name_are_a_conflict_never_a_success(params):
    """A second process stating as the real bridge (another epoch), released while the real one
    is latched: its word must not pass for the bridge's (a release "released", an engage confirmed
    or not by whichever state came last)."""
    with bus_pair() as (hub, hub_session, connect):
        node = _node(connect(), params, command_timeout_s=5.0)
        console = EStopHolder(hub_session, "console-abc123")
        # On the hub's session: the commands link to the hub first, so they hear the impostor at
        # once; from a session of its own it was heard only once gossip had linked the two, after
        # an engage had settled on the real bridge alone (CI of session 42).
        impostor = _fake_states(hub_session, [{"bridge": node.instance, "epoch": "e-impostor", "drive": "inactive"}])
        try:
            with _ticking(node), repeating(impostor, 0.002):
                for command, out in _each_command_under_a_console_estop(node, console, hub, "conflict"):
                    assert out["conflicts"] == [node.instance] and node.instance in out["message"], (command, out)
                    runs = {b["epoch"]: (b["engaged"], b["conflict"]) for b in out["bridges"]}
                    assert runs == {node.epoch: (True, True), "e-impostor": (False, True)}, (command, out)
        finally:
            console.close()
            node.shutdown()
