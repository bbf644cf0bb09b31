"""One bridge per name on a bus (bridge.instance_check): a second bridge of a live bridge's name
refuses to start, with drives left off, and the first goes on undisturbed.

Found in session 38: two BeagleBones with the factory hostname take the same default name
(``beaglebone-beaglebone``), and nothing stopped the second from joining the bus under it.
Real Zenoh sessions on 127.0.0.1; every process is stopped within bounded time.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from server_harness import stop_process_groups, wait_until
from test_up_child_death import ENV, PY

from bridge import bus
from bridge.instance_check import NameTaken, check_name_free
from bridge.session import REPLAYED, free_tcp_port, liveliness_token, open_session


def _state(name: str, seq: int) -> bytes:
    return bus.encode(bus.MotorState(seq=seq, stamp_s=0.002 * seq, theta_rad=[0.0] * 4, force_applied_N=[5.0] * 4,
                                     drive="inactive", epoch="e-test", bridge=name))


@pytest.fixture
def linked() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """Two linked sessions: ``other`` (where another bridge would be) and ``mine``."""
    at = f"tcp/127.0.0.1:{free_tcp_port()}"
    other = open_session(listen=[at], connect=[], credentials=None, tls=None)
    mine = open_session(listen=[], connect=[at], credentials=None, tls=None)
    try:
        assert wait_until(lambda: bool(list(mine.info.peers_zid())), 10, 0.02)
        yield other, mine
    finally:
        mine.close()
        other.close()


def _publish(session: zenoh.Session, name: str, stop: threading.Event) -> threading.Thread:
    def run() -> None:
        seq = 0
        while not stop.is_set():
            session.put(bus.MOTOR_STATE, _state(name, seq))
            seq += 1
            time.sleep(0.002)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_live_bridge_of_the_name_is_refused_at_once_others_names_and_no_peer_pass(linked) -> None:
    other, mine = linked
    stop = threading.Event()
    token = liveliness_token(other, "bridge", "dup")
    publisher = _publish(other, "dup", stop)
    try:
        # on the states, not at the end of the lease wait (whose reason is "sent nothing for")
        with pytest.raises(NameTaken, match=r"another bridge named 'dup' is on this bus \(its motor states arrive"):
            check_name_free(mine, "dup", lease_wait_s=30)
        check_name_free(mine, "not-dup", lease_wait_s=30)  # another bridge's states and token: free
        check_name_free(mine, "")  # a random name (none given) is never checked
    finally:
        stop.set()
        publisher.join(5)
        token.undeclare()
    alone = open_session(listen=[], connect=[], credentials=None, tls=None)
    try:
        check_name_free(alone, "dup")  # no peer: nobody to ask
    finally:
        alone.close()


def test_a_silent_token_is_waited_for_then_refused_and_a_token_that_goes_frees_the_name(linked) -> None:
    """A token without states: a peer cut off without a goodbye (its token lasts until the lease
    ends), or a hung bridge. Waited for; refused if it stays, started once it goes."""
    other, mine = linked
    token = liveliness_token(other, "bridge", "dup")
    with pytest.raises(NameTaken, match="sent nothing for"):
        check_name_free(mine, "dup", lease_wait_s=0.5)
    timer = threading.Timer(0.5, token.undeclare)
    timer.start()
    try:
        check_name_free(mine, "dup", lease_wait_s=30)  # returns once the token is gone
    finally:
        timer.join(5)


def test_a_replay_of_the_names_states_is_no_process_of_that_name(linked) -> None:
    """Audit of 2026-11-29 (session 39): a console replaying a campaign republishes its bridge's
    states under the bridge's name; a bridge of that name started meanwhile (the board's, after the
    operator looked at what happened) was refused as if a second board were on the bus."""
    other, mine = linked
    stop = threading.Event()

    def replay() -> None:
        seq = 0
        while not stop.is_set():
            other.put(bus.MOTOR_STATE, _state("dup", seq), attachment=REPLAYED)
            other.put(bus.health_key("bridge", "dup"), b"{}", attachment=REPLAYED)
            seq += 1
            time.sleep(0.002)

    thread = threading.Thread(target=replay, daemon=True)
    thread.start()
    try:
        check_name_free(mine, "dup", lease_wait_s=30)
    finally:
        stop.set()
        thread.join(5)


def test_a_signal_ends_the_wait_for_a_silent_token(linked) -> None:
    """Audit of 2026-11-29 (session 39): SIGTERM or Ctrl-C during the lease wait was ignored for up to
    12 s, beyond a supervisor's grace. The stop event (bridge.runtime.stop_on_signals) ends it."""
    other, mine = linked
    token = liveliness_token(other, "bridge", "dup")
    stop = threading.Event()
    timer = threading.Timer(0.5, stop.set)
    timer.start()
    try:
        check_name_free(mine, "dup", lease_wait_s=30, stop=stop)  # returns: the caller sees stop and stops
        assert stop.is_set()  # returned on the stop: the lease wait's end would have raised NameTaken
    finally:
        timer.join(5)
        token.undeclare()


@pytest.mark.e2e
def test_a_second_xneck_bridge_of_a_running_bridges_name_exits_2_and_the_first_runs_on(tmp_path: Path) -> None:
    hub_at = f"tcp/127.0.0.1:{free_tcp_port()}"
    hub = open_session(listen=[hub_at], connect=[], credentials=None, tls=None)
    epochs: dict[str, int] = {}
    sub = hub.declare_subscriber(bus.MOTOR_STATE, lambda s: epochs.__setitem__(
        e := bus.decode(bus.MotorState, s.payload.to_bytes()).epoch, epochs.get(e, 0) + 1))
    argv = [*PY, "bridge", "--driver", "twin", "--instance", "dup", "--listen", "tcp/127.0.0.1:0", "--connect", hub_at,
            "--max-ticks", "60000"]
    with open(tmp_path / "first.log", "wb") as log:
        first = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=ENV,
                                 start_new_session=True)
    try:
        assert wait_until(lambda: sum(epochs.values()) > 100, 120, 0.1), (tmp_path / "first.log").read_text()
        (first_epoch,) = epochs
        second = subprocess.run(argv, capture_output=True, text=True, env=ENV, timeout=120, stdin=subprocess.DEVNULL)
        assert second.returncode == 2, second.stdout + second.stderr
        assert "bridge not started, drives left off: another bridge named 'dup' is on this bus" in second.stderr
        assert "--instance NAME" in second.stderr
        before = epochs[first_epoch]
        assert wait_until(lambda: epochs[first_epoch] > before + 100, 30, 0.05)  # the first runs on
        assert set(epochs) == {first_epoch}  # the second never published a state
        assert first.poll() is None
    finally:
        stop_process_groups([first])
        sub.undeclare()
        hub.close()


def test_a_controller_of_the_name_is_refused_on_its_commands_or_its_health(linked) -> None:
    """Audit of 2026-11-29 (session 39): a second ``xneck controller --instance C`` ran beside the
    first, the bridge obeyed both as one owner and the forces swung 10 N a tick."""
    other, mine = linked
    token = liveliness_token(other, "controller", "ctA")
    try:
        command = bus.encode(bus.ForceCommand(seq=1, stamp_s=0.0, force_N=[10.0] * 4, source="law2", sender="ctA",
                                              epoch="e-test"))
        beat = threading.Timer(0.1, lambda: other.put(bus.MOTOR_COMMAND, command))
        beat.start()
        with pytest.raises(NameTaken, match=r"another controller named 'ctA' is on this bus \(its force commands arrive"):
            check_name_free(mine, "ctA", kind="controller", lease_wait_s=30)
        beat.join(5)
        # no bridge, no commands: its health (about 1 Hz) says it is alive
        beat = threading.Timer(0.6, lambda: other.put(bus.health_key("controller", "ctA"), b"{}"))
        beat.start()
        with pytest.raises(NameTaken, match=r"\(its health arrives\)"):
            check_name_free(mine, "ctA", kind="controller", lease_wait_s=30)
        beat.join(5)
        check_name_free(mine, "ctB", kind="controller")
    finally:
        token.undeclare()
    with pytest.raises(ValueError, match="no name check"):
        check_name_free(mine, "x", kind="camera")


@pytest.mark.e2e
def test_a_second_xneck_controller_of_a_running_controllers_name_exits_2(tmp_path: Path) -> None:
    hub_at = f"tcp/127.0.0.1:{free_tcp_port()}"
    hub = open_session(listen=[hub_at], connect=[], credentials=None, tls=None)
    owners: dict[str, int] = {}
    sub = hub.declare_subscriber(bus.MOTOR_STATE, lambda s: owners.__setitem__(
        o := bus.decode(bus.MotorState, s.payload.to_bytes()).owner, owners.get(o, 0) + 1))
    common = ["--listen", "tcp/127.0.0.1:0", "--connect", hub_at]
    procs: list[subprocess.Popen] = []
    try:
        for name, argv in (("bridge", ["bridge", "--driver", "twin", "--max-ticks", "60000"]),
                           ("controller", ["controller", "--law", "2", "--instance", "ctA"])):
            with open(tmp_path / f"{name}.log", "wb") as log:
                procs.append(subprocess.Popen([*PY, *argv, *common], stdout=log, stderr=subprocess.STDOUT,
                                              stdin=subprocess.DEVNULL, env=ENV, start_new_session=True))
        assert wait_until(lambda: owners.get("ctA", 0) > 100, 120, 0.1), (tmp_path / "controller.log").read_text()
        second = subprocess.run([*PY, "controller", "--law", "2", "--instance", "ctA", *common], capture_output=True,
                                text=True, env=ENV, timeout=120, stdin=subprocess.DEVNULL)
        assert second.returncode == 2, second.stdout + second.stderr
        assert "controller not started: another controller named 'ctA' is on this bus" in second.stderr
        assert "controller ctA up" not in second.stdout + second.stderr
        before = owners["ctA"]
        assert wait_until(lambda: owners["ctA"] > before + 100, 30, 0.05)  # the first drives on
        assert all(p.poll() is None for p in procs)
    finally:
        stop_process_groups(procs)
        sub.undeclare()
        hub.close()
