"""The bridge node on the BeagleBone driver with the fake board (rcpy faked at its lowest layer,
tests/conftest.py's ``board``) on a real Zenoh bus: what the board's faults (an encoder glitch, a
failed read) and the bus's extremes (a flood of e-stop messages, commands answering no state
the bridge published) do to the drives. The audit of 2026-11-29's reproductions, as tests."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterator

import numpy as np
import pytest
from busutil import bus_pair, wait_until

from bridge import bus
from bridge.drivers.beaglebone import BeagleBoneConfig, BeagleBoneDriver
from bridge.log_limit import LogLimit
from bridge.motor_speed import MotorSpeed
from bridge.node import BridgeConfig, BridgeNode, HoldWorker
from bridge.session import liveliness_token, publisher
from server.cli.processes import bridge_node

pytestmark = pytest.mark.realtime  # the node's ticks and its watchdog, on a real bus
DT = 0.002


class Rig:
    """A bridge node on the fake board, a controller's token and publishers on the hub."""

    def __init__(self, node: BridgeNode, board, hub) -> None:
        self.node, self.board, self.hub = node, board, hub
        self.pub = publisher(hub, bus.MOTOR_COMMAND)
        self.estop = publisher(hub, bus.ESTOP)
        self.seq = 0

    def command(self, force, stamp_s: float | None = None) -> bus.ForceCommand:
        """A command of controller ``test`` answering the node's latest state (or ``stamp_s``)."""
        self.seq += 1
        if stamp_s is None:
            stamp_s = self.node.last_state_stamp_s
        return bus.ForceCommand(seq=self.seq, stamp_s=stamp_s, force_N=[float(f) for f in force], source="test",
                                sender="test", epoch=self.node.epoch)

    def send(self, force) -> None:
        """Publish a command answering the latest state until the node took it."""
        if not self.put(self.command(force)):
            raise AssertionError(f"command not accepted: {self.node.commands.stats.last_reject_reason}")

    def put(self, msg: bus.ForceCommand) -> bool:
        """Publish ``msg`` until the node took it (True) or refused it (False): the first
        messages on a fresh route may be lost."""
        commands = self.node.commands
        before = commands.stats
        deadline = time.monotonic() + 5.0
        copies = 0
        while time.monotonic() < deadline:
            self.pub.put(msg)
            copies += 1
            if wait_until(lambda: commands.stats.received > before.received, 0.02, 0.001):
                if copies > 1:
                    # Copies put while the first was slow in coming may still be in flight: let
                    # them land now, not after the next put's count was taken (a loaded machine).
                    wait_until(lambda: commands.stats.received >= before.received + copies, 0.5, 0.002)
                return commands.stats.accepted > before.accepted
        raise AssertionError("the command never arrived")

    def answered_ticks(self, force, n: int) -> None:
        """``n`` ticks about one period apart, each state answered with ``force``."""
        for _ in range(n):
            self.send(force)
            self.node.tick()
            time.sleep(DT)


@contextlib.contextmanager
def _rig(board, params, **config) -> Iterator[Rig]:
    with bus_pair() as (_hub, hub, connect):
        _token = liveliness_token(hub, "controller", "test")
        node = bridge_node(connect(), BeagleBoneDriver.from_params(BeagleBoneConfig(), params), params,
                           BridgeConfig(**config))
        try:
            # The token reaches the node by its liveliness subscriber, in a thread of its own: on a
            # loaded machine the first command came first and was refused (CI of 2026-12-02, ci148).
            assert wait_until(lambda: node.ownership.alive("test"), 10, 0.005)
            node.tick()  # the first state, for a controller to answer (drives inactive)
            yield Rig(node, board, hub)
        finally:
            node.shutdown()


def _drives_on(board) -> bool:
    """Whether any ESCON's enable line is high (the BeagleBone driver's enable pins)."""
    return any(board.pins.values())


def _counts(node: BridgeNode, rad: float) -> int:
    return int(rad / (2 * math.pi) * node.driver.counts_per_rev)  # pyright: ignore[reportAttributeAccessIssue]


# -- an encoder glitch before a hold (finding 1) ---------------------------------------------------


@pytest.mark.parametrize("glitch_ticks", [1, 3])
def test_an_encoder_glitch_before_a_hold_does_not_set_its_forces(board, params, glitch_ticks):
    """Motor 1's encoder reads 1e4 rad off for a few ticks (what no motor can turn), then normal
    again; the controller then goes silent. The hold that follows holds the neck's rest forces,
    not those of the glitched angles (70.6 N on cable 1 for the whole hold, before the fix)."""
    with _rig(board, params, command_timeout_s=0.010) as rig:
        node = rig.node
        assert wait_until(lambda: node.hold.ready(time.monotonic()) is not None, 2.0)
        rest = node.hold.ready(time.monotonic())
        assert rest is not None
        rig.answered_ticks(rest, 60)  # active on the rest hold forces, the neck at rest
        computed = node.hold.computed
        board.counts[1] = _counts(node, 1e4)
        for k in range(glitch_ticks):
            rig.send(rest)
            node.tick()
            if k == 0:  # give the hold worker the time to see the glitched angles, if it is shown them
                wait_until(lambda: node.hold.computed > computed, 0.1, 0.002)
        board.counts[1] = 0  # reads normal again
        rig.answered_ticks(rest, 1)
        forces = []
        for _ in range(150):  # the controller is silent: 300 ms
            node.tick()
            forces.append(node.force.tolist())
            time.sleep(DT)
        assert node.mode == "hold" and node.speed.bad_readings >= 2
        f = np.array(forces)
        assert np.abs(f - np.array(rest)).max() < 1.0, f"the hold went to {f[-1].round(2).tolist()} N, rest {rest}"


def test_hold_forces_are_ready_only_for_angles_near_those_read_now():
    worker = HoldWorker(lambda theta: np.full(4, 10.0) + theta, 4, tolerance_rad=0.2, max_age_s=0.1)
    assert worker.compute([1e4, 0.0, 0.0, 0.0])  # a glitch's angles
    now = time.monotonic()
    assert worker.ready(now) is not None  # fresh, of some angles
    assert worker.ready(now, [0.0] * 4, [0.0] * 4) is None  # not of these
    assert worker.ready(now, [1e4 + 0.1, 0.0, 0.0, 0.0], [0.0] * 4) is not None
    assert worker.ready(now, [math.nan, 0.0, 0.0, 0.0]) is None
    # A neck that moves on: the tolerance grows with what each motor turns in the forces' age.
    assert worker.compute([0.0] * 4)
    assert worker.ready(now + 0.05, [1.0, 0.0, 0.0, 0.0], [30.0, 0.0, 0.0, 0.0]) is not None  # 1.5 rad in 50 ms
    assert worker.ready(now + 0.05, [1.0, 0.0, 0.0, 0.0], [0.0] * 4) is None


def test_a_reading_is_trusted_again_only_some_readings_after_a_glitch():
    speed = MotorSpeed(4, DT)
    t = 0.0
    for _ in range(3):
        t += DT
        speed.update([0.0] * 4, t)
    assert speed.trusted
    seen = []
    for theta in ([1e4, 0, 0, 0], [1e4, 0, 0, 0], [1e4, 0, 0, 0], [0.0] * 4, *[[0.0] * 4] * 5):
        t += DT
        speed.update([float(x) for x in theta], t)
        seen.append(speed.trusted)
    # the glitch's plateau (consistent with itself) and the jump back are not trusted; 5 readings later they are
    assert seen == [False] * 3 + [False] * 5 + [True]


# -- failed encoder reads (finding 2) --------------------------------------------------------------


class HealthOf:
    """The bridge's Health messages, as the hub receives them."""

    def __init__(self, hub, node: BridgeNode) -> None:
        self.items: list[bus.Health] = []
        self._sub = hub.declare_subscriber(bus.health_key("bridge", node.instance),
                                           lambda s: self.items.append(bus.decode(bus.Health, s.payload.to_bytes())))


def test_a_failed_encoder_read_keeps_the_drives_and_too_many_in_a_row_trip_them(board, params, caplog):
    """One read of the encoders that fails (the board library raises OSError) had ended the loop
    and dropped every cable from 30 N to 0 (audit of 2026-11-29). A few in a row reuse the last
    angles and keep the forces; one more than ``max_read_errors`` in a row ends the loop as before,
    the drives off, the reason in the log and the bridge's Health."""
    with _rig(board, params, command_timeout_s=5.0) as rig:  # no watchdog between these ticks
        node = rig.node
        now = [0.0]  # the log limit's clock: one line a second (bridge.log_limit), whatever the machine's speed
        node._read_errors_logged = LogLimit(1.0, clock=lambda: now[0])
        health = HealthOf(rig.hub, node)
        rig.answered_ticks([30.0] * 4, 40)
        assert node.mode == "active" and node.force.tolist() == pytest.approx([30.0] * 4)
        theta, states = node.theta.copy(), node._seq["state"]
        board.failing_reads = 1
        rig.send([30.0] * 4)
        node.tick()
        assert node.mode == "active" and node.force.tolist() == pytest.approx([30.0] * 4) and _drives_on(board)
        assert node.read_errors == 1 and node.theta.tolist() == theta.tolist()
        assert node._seq["state"] == states  # no state of angles not read
        rig.answered_ticks([30.0] * 4, 3)  # reads again
        assert node.mode == "active" and node.force.tolist() == pytest.approx([30.0] * 4)
        n = node.config.max_read_errors
        board.failing_reads = n
        for _ in range(n):
            node.tick()
        assert node.mode == "active" and node.force.tolist() == pytest.approx([30.0] * 4) and node.read_errors == 1 + n
        read_lines = [r.getMessage() for r in caplog.records if "encoder read failed" in r.getMessage()]
        assert len(read_lines) == 1 and node._read_errors_logged.suppressed == n, read_lines  # counted, not logged
        board.failing_reads = 1  # one more in a row
        with pytest.raises(OSError, match="EIO"):
            node.tick()
        node.shutdown()  # what run_realtime's caller does then
        assert node.mode == "disabled" and not _drives_on(board)
        assert wait_until(lambda: any("encoder" in h.last_reject_reason and h.rejected.get("encoder_read") == n + 2
                                      for h in health.items), 2.0), [h.last_reject_reason for h in health.items]


# -- a flood of e-stop messages (finding 3) --------------------------------------------------------


@pytest.mark.parametrize("releases", [3, 64])
def test_an_estop_engage_is_never_lost_to_the_messages_after_it(board, params, releases):
    """An engage followed, before the next tick, by 64 more e-stop messages had been dropped from
    the bounded queue, the drives left driving 30 N (audit of 2026-11-29). The tick after an
    engage shows it (drives disabled) whatever came after it; the releases count from the next."""
    with _rig(board, params, command_timeout_s=5.0) as rig:
        node = rig.node
        rig.answered_ticks([30.0] * 4, 40)
        base = node.estop_received
        rig.estop.put(bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="operator pressed e-stop"))
        for k in range(releases):
            rig.estop.put(bus.EStop(seq=2 + k, stamp_s=time.time(), engaged=False, reason="release spam"))
        assert wait_until(lambda: node.estop_received >= base + 1 + releases, 5.0)
        rig.send([30.0] * 4)
        node.tick()
        assert node.mode == "disabled" and node.safety.estop_engaged and not _drives_on(board)
        assert node.safety.estop_reason == "operator pressed e-stop" and node.force.tolist() == [0.0] * 4
        node.tick()  # then the releases that came after it
        assert node.mode == "inactive" and not _drives_on(board) and node.force.tolist() == [0.0] * 4


# -- commands that answer no recent state (finding 4) ----------------------------------------------


def test_a_command_answering_no_recent_state_is_no_command(board, params):
    """A command carries the stamp of the state it answers (bridge.bus.ForceCommand). One of this
    run answering a state 5 s old, or one never published (1e9 s ahead), had been obeyed (audit of
    2026-11-29): now it is refused, counted with its reason, and the watchdog holds as for silence."""
    with _rig(board, params, command_timeout_s=0.010) as rig:
        node = rig.node
        health = HealthOf(rig.hub, node)
        rig.answered_ticks([30.0] * 4, 40)
        assert node.mode == "active"
        for label, stamp in (("5 s old", node.last_state_stamp_s - 5.0), ("never published", node.last_state_stamp_s + 1e9)):
            for _ in range(10):
                assert not rig.put(rig.command([40.0] * 4, stamp_s=stamp)), label
                node.tick()
                time.sleep(DT)
            assert node.mode == "hold" and max(node.force.tolist()) < 35.0, (label, node.mode, node.force.tolist())
            assert "answers no state" in node.commands.stats.last_reject_reason
            rig.answered_ticks([30.0] * 4, 60)  # answers to real states: active again
            assert node.mode == "active" and node.force.tolist() == pytest.approx([30.0] * 4)
        node.publish_health()
        # each of the 20 refused (a copy re-put on a slow route is refused and counted too)
        assert wait_until(lambda: any(h.rejected.get("command_stale_state", 0) >= 20 for h in health.items), 2.0)


def test_a_state_says_why_the_drives_stay_off_when_every_command_answers_a_state_gone(board, params):
    """A controller behind a link whose round trip exceeds the 50 ms a command may lag (32 ms one
    way in benchmarks/lab_network.py) had every command refused, and said only "drives inactive",
    forever: the bridge's states now say why the drives stay off (``hold_reason`` beside
    ``inactive``, or after a hold's own reason), for a second after the last such command."""
    with _rig(board, params, command_timeout_s=0.010) as rig:
        node = rig.node
        for _ in range(30):  # states the controller's answers are 60 ms late for
            node.tick()
            time.sleep(DT)
        late = node.last_state_stamp_s - 0.060
        for _ in range(5):
            assert not rig.put(rig.command([30.0] * 4, stamp_s=late))
            node.tick()
        assert node.mode == "inactive" and not _drives_on(board)
        assert node.hold_reason.startswith("commands refused: they answer no state of the last 50 ms"), node.hold_reason
        said = node.hold_reason
        node.tick()
        assert node.hold_reason == said  # one text while it lasts: the journal writes a line per change
        rig.answered_ticks([30.0] * 4, 20)  # answers on time: active, nothing to say
        assert node.mode == "active" and node.hold_reason == ""
        assert not rig.put(rig.command([30.0] * 4, stamp_s=node.last_state_stamp_s - 1.0))
        for _ in range(10):  # then only late answers: the watchdog's hold says both why
            node.tick()
            time.sleep(DT)
        assert node.mode == "hold" and "no valid command" in node.hold_reason, node.hold_reason
        assert node.hold_reason.endswith(f"; {said}"), node.hold_reason


def test_a_controller_answering_a_state_a_few_ticks_old_is_obeyed(board, params):
    """The states a command may lag without a hold (the watchdog's 5 at 500 Hz) are answered."""
    with _rig(board, params, command_timeout_s=5.0) as rig:
        node = rig.node
        stamps = []
        for k in range(60):
            node.tick()
            stamps.append(node.last_state_stamp_s)
            if k >= 5:
                assert rig.put(rig.command([20.0] * 4, stamp_s=stamps[-6])), node.commands.stats.last_reject_reason
        assert node.mode == "active" and node.commands.stats.rejected == 0
