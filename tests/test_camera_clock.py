"""A live camera's stamps on the bridge's clock (docs/camera.md, "One clock").

On the robot the bridge stamps its states with the BeagleBone's wall clock (no RTC battery: off by
seconds until NTP syncs) and the USB camera grabbed on the PC's: nothing measured the offset, and
`xneck identify` paired α_IP with the states by those stamps. Here a real bridge node on the fake
board (rcpy faked at its lowest layer, tests/test_bridge_driver.py's FakeBoard) whose stamp clock
runs 1000 s ahead serves its clock on a real loopback bus; the camera's sync finds the offset, and
a USB camera (cv2.VideoCapture faked at the lowest layer) publishes α_IP captured on the bridge's
clock. Without a bridge, `xneck camera --source usb:0` says so in one line and exits 1.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from busutil import bus_pair, wait_until

from bridge import bus
from bridge.clock_service import ClockService, query_clock
from bridge.drivers.beaglebone import BeagleBoneConfig, BeagleBoneDriver
from bridge.node import BridgeConfig

AHEAD_S = 1000.0


class ShiftedBoardDriver(BeagleBoneDriver):
    """The BeagleBone driver with the board's wall clock ``shift_s`` ahead of this machine's."""

    shift_s = AHEAD_S

    def stamp_s(self) -> float:
        return time.time() + self.shift_s


@pytest.fixture
def bridge(board, params):
    """(hub endpoint, hub session, factory of sessions, the bridge node on the hub's session)."""
    from server.cli.processes import bridge_node

    with bus_pair() as (hub, session, connect):
        driver = ShiftedBoardDriver.from_params(BeagleBoneConfig(), params)
        node = bridge_node(session, driver, params, BridgeConfig(command_timeout_s=5.0, instance="beaglebone-1"))
        try:
            yield hub, session, connect, node
        finally:
            node.shutdown()


def test_the_camera_finds_the_bridge_clock_1000_s_ahead_within_a_few_ms(bridge) -> None:
    from twin.camera.clock import BridgeClock

    _hub, _session, connect, node = bridge
    clock = BridgeClock(connect(), burst=16)
    clock.sync(wait_s=5.0)
    assert (clock.bridge, clock.epoch) == ("beaglebone-1", node.epoch)
    error = clock.wall_offset_s() - AHEAD_S
    assert abs(error) < 0.005 and abs(error) <= clock.uncertainty_s + 1e-4, (error, clock.uncertainty_s)
    # on the monotonic clock the camera stamps its grabs with, the offset maps it onto the bridge's
    assert time.monotonic() + clock.offset_s == pytest.approx(node.driver.stamp_s(), abs=0.005)
    received, rejected = clock.health()
    assert received["clock_offset_us"] == pytest.approx(AHEAD_S * 1e6, abs=5000)
    assert 0 <= received["clock_uncertainty_us"] < 5000 and received["clock_steps"] == 0
    assert received[f"clock_run/beaglebone-1/{node.epoch}"] == 1 and rejected == {"clock_replies": 0, "clock_bursts": 0}
    assert node.clock.answered >= 16  # the bridge's health counts them (bus.BRIDGE_CLOCK)


def test_a_clock_set_on_the_board_is_a_step_and_a_restarted_bridge_is_synchronised_afresh(bridge, params, board) -> None:
    from server.cli.processes import bridge_node
    from twin.camera.clock import BridgeClock

    _hub, session, connect, node = bridge
    clock = BridgeClock(connect(), burst=4)
    clock.sync(wait_s=5.0)
    # NTP sets the board's clock 3 s forward: the next burst takes the new offset, counted as a step.
    node.driver.shift_s = AHEAD_S + 3.0  # type: ignore[attr-defined]
    assert clock.burst_once() == ""
    assert clock.tracker.steps == 1 and clock.wall_offset_s() == pytest.approx(AHEAD_S + 3.0, abs=0.005)
    # The bridge restarts (a new run of the same instance, the clock back where it was): re-synchronised.
    node.shutdown()
    driver = ShiftedBoardDriver.from_params(BeagleBoneConfig(), params)
    second = bridge_node(session, driver, params, BridgeConfig(command_timeout_s=5.0, instance="beaglebone-1"))
    try:
        assert wait_until(lambda: clock.burst_once() == "", 5.0, 0.05)
        assert (clock.bridge, clock.epoch) == (second.instance, second.epoch) and clock.resyncs == 1
        assert clock.tracker.steps == 1  # a new run is not a step of the old one
        assert clock.wall_offset_s() == pytest.approx(AHEAD_S, abs=0.005)
    finally:
        second.shutdown()


def test_another_bridge_answering_alone_is_foreign_and_never_adopted() -> None:
    """Audit of 2026-11-29 (a2_benign.py): the robot's link drops for one burst while a twin bridge
    on the hub answers alone: the camera had taken the twin's clock for a restart and kept it once
    the robot was back. Only a new run of the followed instance is a restart."""
    from twin.camera.clock import BridgeClock

    with bus_pair() as (_hub, _session, connect):
        robot_session = connect()
        robot = ClockService(robot_session, lambda: time.time() + AHEAD_S, "aaaa11112222", "beaglebone-1")
        camera = BridgeClock(connect(), burst=4)
        camera.sync(wait_s=5.0)
        twin = ClockService(connect(), lambda: 5.0, "bbbb33334444", "twin-7")
        try:
            assert wait_until(lambda: len(query_clock(camera.session).replies) == 2, 5.0, 0.05)
            robot.close()  # the link drops
            assert wait_until(lambda: len(query_clock(camera.session).replies) == 1, 5.0, 0.05)
            why = camera.burst_once()
            assert "twin-7 (run bbbb33334444) answers alone" in why and "not followed" in why, why
            assert (camera.bridge, camera.epoch) == ("beaglebone-1", "aaaa11112222") and camera.resyncs == 0
            assert camera.foreign >= 4 and camera.wall_offset_s() == pytest.approx(AHEAD_S, abs=0.005)
            robot = ClockService(robot_session, lambda: time.time() + AHEAD_S, "aaaa11112222", "beaglebone-1")
            assert wait_until(lambda: len(query_clock(camera.session).replies) == 2, 5.0, 0.05)
            assert camera.burst_once() == "" and camera.bridge == "beaglebone-1"
            assert camera.wall_offset_s() == pytest.approx(AHEAD_S, abs=0.005)
            # a new run of the followed instance alone is a restart: synchronised afresh
            robot.close()
            robot = ClockService(robot_session, lambda: time.time() + AHEAD_S + 2.0, "cccc55556666", "beaglebone-1")
            twin.close()
            assert wait_until(lambda: [r.reading.epoch for r in query_clock(camera.session).replies] == ["cccc55556666"],
                              5.0, 0.05)
            assert camera.burst_once() == "" and (camera.bridge, camera.epoch) == ("beaglebone-1", "cccc55556666")
            assert camera.resyncs == 1 and camera.wall_offset_s() == pytest.approx(AHEAD_S + 2.0, abs=0.005)
        finally:
            twin.close()
            robot.close()


def test_two_bridges_without_a_name_are_refused_and_a_name_picks_one(bridge) -> None:
    from twin.camera.clock import BridgeClock, ClockSyncError

    _hub, _session, connect, _node = bridge
    stray = ClockService(connect(), lambda: 5.0, "e0e0e0", "twin-7")  # a twin bridge on the same hub
    try:
        camera = connect()
        assert wait_until(lambda: len({r.reading.bridge for r in query_clock(camera).replies}) == 2, 5.0, 0.05)
        with pytest.raises(ClockSyncError, match=r"2 bridges answer on xneck/bridge/clock: beaglebone-1 \(run \w+\), "
                                                 r"twin-7 \(run e0e0e0\); name the robot's with --clock bridge:NAME"):
            BridgeClock(camera, burst=2).sync(wait_s=0.5)
        named = BridgeClock(camera, "beaglebone-1", burst=4)
        named.sync(wait_s=5.0)
        assert named.bridge == "beaglebone-1" and named.wall_offset_s() == pytest.approx(AHEAD_S, abs=0.005)
    finally:
        stray.close()


def test_hostile_replies_are_counted_and_never_used(bridge) -> None:
    """Any peer may declare a queryable on the key: garbage, a NaN stamp, an error reply, an
    oversized payload, another key's reply. None moves the offset; each is counted."""
    from twin.camera.clock import BridgeClock

    _hub, _session, connect, _node = bridge
    liar = connect()
    answers = [b"not json", b'{"v":1,"seq":1,"stamp_s":NaN,"epoch":"x","bridge":"y"}',
               b'{"v":2,"seq":1,"stamp_s":1.0,"epoch":"x","bridge":"y"}',
               b'{"v":1,"seq":1,"stamp_s":1.0,"epoch":"x","bridge":"has space"}', b" " * 5000]
    turn = [0]

    def lie(query) -> None:
        k = turn[0] = turn[0] + 1
        if k % 3 == 0:
            query.reply_err(b"no clock here")
        else:
            query.reply(bus.BRIDGE_CLOCK, answers[k % len(answers)])

    queryable = liar.declare_queryable(bus.BRIDGE_CLOCK, lie)
    try:
        camera = connect()
        assert wait_until(lambda: query_clock(camera).rejected != [], 5.0, 0.05)
        clock = BridgeClock(camera, burst=8)
        clock.sync(wait_s=5.0)
        assert clock.bridge == "beaglebone-1" and clock.wall_offset_s() == pytest.approx(AHEAD_S, abs=0.005)
        assert clock.refused >= 8 and clock.last_problem
        _received, rejected = clock.health()
        assert rejected["clock_replies"] == clock.refused
    finally:
        queryable.undeclare()


def test_a_peer_crowding_each_query_with_junk_replies_does_not_hide_the_bridge() -> None:
    """Audit of 2026-11-29 (c_crowd.py, c2_crowd.py): 16 junk replies per query counted toward the
    16 replies taken, so the bridge's reply after them was refused and the camera could not start,
    told that no bridge answered. The cap is per replier and on valid replies; the error says what
    was refused."""
    from twin.camera.clock import BridgeClock, ClockSyncError

    with bus_pair() as (_hub, _session, connect):
        camera = connect()
        liar = connect()

        def spam(query) -> None:
            for _ in range(16):
                query.reply(bus.BRIDGE_CLOCK, b"x")

        queryable = liar.declare_queryable(bus.BRIDGE_CLOCK, spam)
        try:
            assert wait_until(lambda: query_clock(camera).rejected != [], 5.0, 0.05)
            with pytest.raises(ClockSyncError) as err:  # the junk alone: said as such
                BridgeClock(camera, burst=2).sync(wait_s=0.3)
            assert "no bridge answered" not in str(err.value) and "no valid reply" in str(err.value), err.value
            assert "replies refused" in str(err.value) and "start the bridge first" not in str(err.value), err.value
            robot = ClockService(connect(), lambda: time.time() + 0.002 + AHEAD_S, "aaaa11112222", "beaglebone-1")
            try:
                assert wait_until(lambda: query_clock(camera).replies != [], 5.0, 0.05)
                got = sum(len(query_clock(camera).replies) for _ in range(10))
                assert got == 10
                clock = BridgeClock(camera, burst=8)
                clock.sync(wait_s=3.0)
                assert clock.bridge == "beaglebone-1" and clock.refused >= 8
            finally:
                robot.close()
        finally:
            queryable.undeclare()


def test_a_peer_claiming_the_followed_run_is_told_and_never_moves_the_offset() -> None:
    """Audit of 2026-11-29 (b_spoof.py): a queryable answering with the followed bridge's name and
    epoch (readable in any MotorState) and a stamp 40 ms off, nearer the camera, won every burst.
    The run is known by the replier's Zenoh id too: two peers claiming one run refuse the burst
    (said), and the impostor alone is not followed."""
    from twin.camera.clock import BridgeClock

    with bus_pair() as (_hub, _session, connect):
        robot = ClockService(connect(), lambda: time.time() + AHEAD_S, "aaaa11112222", "beaglebone-1")
        camera = BridgeClock(connect(), burst=4)
        camera.sync(wait_s=5.0)
        liar = ClockService(connect(), lambda: time.time() + AHEAD_S + 0.040, "aaaa11112222", "beaglebone-1")
        try:
            assert wait_until(lambda: len(query_clock(camera.session).replies) == 2, 5.0, 0.05)
            why = camera.burst_once()
            assert "2 peers answer as bridge beaglebone-1 run aaaa11112222" in why, why
            assert camera.impostors == 1 and camera.wall_offset_s() == pytest.approx(AHEAD_S, abs=0.005)
            assert camera.health()[0]["clock_impostors"] == 1
            robot.close()
            assert wait_until(lambda: len(query_clock(camera.session).replies) == 1, 5.0, 0.05)
            why = camera.burst_once()
            assert "answers as bridge beaglebone-1 run aaaa11112222 from another peer" in why, why
            assert camera.wall_offset_s() == pytest.approx(AHEAD_S, abs=0.005) and camera.resyncs == 0
        finally:
            liar.close()
            robot.close()


def test_a_flood_of_queries_is_bounded_by_the_bridge(bridge) -> None:
    """The bridge's own bucket (200 a second, bursts of 64) and a slow one, whose refusals a loaded
    machine cannot hide: replies never exceed the burst plus the rate over the time taken."""
    _hub, session, connect, node = bridge
    camera = connect()
    assert wait_until(lambda: query_clock(camera).replies != [], 5.0, 0.05)
    slow = ClockService(session, time.time, "f00d", "slow-1", rate_per_s=5.0, burst=4)
    try:
        assert wait_until(lambda: len(query_clock(camera).replies) == 2, 5.0, 0.05)  # both reached
        before, t0 = node.clock.answered, time.monotonic()
        for _ in range(150):
            query_clock(camera, 0.2)
        took = time.monotonic() - t0
        assert node.clock.answered - before <= 64 + 200 * took + 1
        assert slow.answered <= 4 + 5 * (took + 5.0) + 1 and slow.refused > 0
    finally:
        slow.close()


# --- the USB camera's α_IP on the bridge's clock ---------------------------------------------------


def test_a_usb_camera_publishes_alpha_ip_captured_on_the_bridge_clock(bridge, monkeypatch, params, model) -> None:
    cv2 = pytest.importorskip("cv2")
    from test_camera_sources import FakeCamera

    from twin.camera.calibration import twin_calibration
    from twin.camera.clock import BridgeClock
    from twin.camera.detect import Detector
    from twin.camera.process import CameraNode
    from twin.camera.render import Renderer
    from twin.camera.source import UsbSource

    grabs: list[float] = []  # the board's clock at each grab

    class Grabbing(FakeCamera):
        image = Renderer(model, seed=1).render(np.radians([10.0, -20.0, 30.0]))

        def grab(self) -> bool:
            time.sleep(1 / 30)
            grabs.append(time.time() + AHEAD_S)
            return True

    monkeypatch.setattr(cv2, "VideoCapture", Grabbing)
    _hub, session, connect, _node = bridge
    got: list[bus.CameraAlpha] = []
    lock = threading.Lock()

    def collect(sample) -> None:
        with lock:
            got.append(bus.decode(bus.CAMERA_ALPHA, sample.payload.to_bytes()))

    sub = session.declare_subscriber(bus.CAMERA_ALPHA, collect)
    camera_session = connect()
    clock = BridgeClock(camera_session, burst=8)
    clock.sync(wait_s=5.0)
    cal = twin_calibration()
    source = UsbSource("0", cal.width, cal.height, latency_s=0.05, clock=time.monotonic)
    camera = CameraNode(camera_session, Detector(params.n_joints, params.geometry.L, params.geometry.b, cal), clock=clock)
    try:
        camera.run_source(source, threading.Event(), max_frames=40)
        assert wait_until(lambda: len(got) >= 10, 5.0)
    finally:
        sub.undeclare()
        camera.close()
        source.close()
    with lock:
        seen = sorted(got, key=lambda m: m.seq)
    for msg in seen:
        bus.check_camera_alpha(msg, 3)  # the capture not after its publication: one offset for both
        grab = grabs[msg.seq - 1]
        assert msg.capture_stamp_s == pytest.approx(grab - 0.05, abs=0.005), (msg.seq, msg.capture_stamp_s - grab)
        assert msg.source == "usb:0" and all(a is not None for a in msg.alpha_ip_rad)
    assert not math.isnan(clock.offset_s)


def test_the_states_of_the_bridge_show_a_clock_set_at_once_and_no_alpha_ip_is_stamped_with_the_old_offset(
        bridge, monkeypatch, params, model) -> None:
    """Audit of 2026-11-29 (e_steplag.py): the board's clock set 3 s forward left α_IP on the old
    offset until the next burst, up to 10 s later. The camera watches the bridge's MotorStates: the
    jump is seen at once, a burst run, and no frame goes out stamped with the old offset."""
    cv2 = pytest.importorskip("cv2")
    from test_camera_sources import FakeCamera

    from twin.camera.calibration import twin_calibration
    from twin.camera.clock import BridgeClock
    from twin.camera.detect import Detector
    from twin.camera.process import CameraNode
    from twin.camera.render import Renderer
    from twin.camera.source import UsbSource

    _hub, session, connect, node = bridge
    driver = node.driver
    grabs: list[float] = []  # the board's clock at each grab
    stepped: list[float] = []  # time.monotonic() when the board's clock was set

    class Grabbing(FakeCamera):
        image = Renderer(model, seed=1).render(np.radians([10.0, -20.0, 30.0]))

        def grab(self) -> bool:
            time.sleep(1 / 30)
            if len(grabs) == 15:  # NTP sets the board's clock 3 s forward while the camera runs
                driver.shift_s = AHEAD_S + 3.0  # type: ignore[attr-defined]
                stepped.append(time.monotonic())
                time.sleep(0.02)  # the grab is timed after the step
            grabs.append(time.time() + driver.shift_s)  # type: ignore[attr-defined]
            return True

    monkeypatch.setattr(cv2, "VideoCapture", Grabbing)
    got: list[bus.CameraAlpha] = []
    lock = threading.Lock()

    def collect(sample) -> None:
        with lock:
            got.append(bus.decode(bus.CAMERA_ALPHA, sample.payload.to_bytes()))

    stop = threading.Event()

    def ticking() -> None:  # the bridge's loop at 500 Hz: its MotorStates on the bus
        while not stop.is_set():
            node.tick()
            time.sleep(0.002)

    loop = threading.Thread(target=ticking, daemon=True)
    loop.start()
    sub = session.declare_subscriber(bus.CAMERA_ALPHA, collect)
    camera_session = connect()
    clock = BridgeClock(camera_session, burst=8)  # a burst every 10 s (the default)
    clock.sync(wait_s=5.0)
    clock.start()
    cal = twin_calibration()
    source = UsbSource("0", cal.width, cal.height, latency_s=0.05, clock=time.monotonic)
    camera = CameraNode(camera_session, Detector(params.n_joints, params.geometry.L, params.geometry.b, cal), clock=clock)
    try:
        camera.run_source(source, threading.Event(), max_frames=40)
        assert wait_until(lambda: len(got) >= 40, 5.0)
    finally:
        stop.set()
        loop.join(2.0)
        clock.stop()
        sub.undeclare()
        camera.close()
        source.close()
    with lock:
        seen = sorted(got, key=lambda m: m.seq)
    assert len(seen) == 40
    for msg in seen:  # every α_IP published on the board's clock at its grab, before the step or after
        bus.check_camera_alpha(msg, 3)
    # frames may be dropped meanwhile (counted): each published one matches its grab on the board's clock
    errors = [min(abs(msg.capture_stamp_s - (g - 0.05)) for g in grabs) for msg in seen]
    assert max(errors) < 0.005, errors
    assert stepped and clock.tracker.steps == 1 and clock.jumps >= 1  # long before the next burst, 10 s on
    assert clock.wall_offset_s() == pytest.approx(AHEAD_S + 3.0, abs=0.005)
    assert camera.clock_dropped == len(grabs) - 40  # frames not published meanwhile, counted
    assert -1.0 < seen[-1].capture_stamp_s - (time.time() + AHEAD_S + 3.0) < 0.0


def test_a_jump_of_the_states_stamps_holds_the_offset_until_a_burst_begun_after_it() -> None:
    """The state watcher on its own (no bus): one state ahead is a jump, states behind only when
    STATE_WINDOW in a row are (a delay spike is not), a new run of the followed bridge is one; the
    offset is withheld from the jump until a burst begun after it is used."""
    from bridge.clock_sync import OffsetEstimate
    from twin.camera.clock import STATE_WINDOW, BridgeClock

    now = [100.0]
    clock = BridgeClock(None, local=lambda: now[0])  # type: ignore[arg-type]  # no bus: note_state fed by hand
    clock._burst_started = 99.0
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(1000.0, 0.0005, 99.0, 8))
    assert clock.offset_for(99.5) == 1000.0
    t = 100.0
    for k in range(50):  # states 1 ms late, and a 200 ms delay spike of 5 states
        t += 0.002
        late = 0.2 if 20 <= k < 25 else 0.001
        assert not clock.note_state("beaglebone-1", "e1", t + 1000.0 - late, t)
    assert not clock.note_state("twin-7", "x", t + 5.0, t)  # another bridge's states say nothing
    assert clock.jumps == 0 and clock.offset_for(t) == 1000.0
    # the board's clock set 3 s back: STATE_WINDOW states in a row behind
    good = t
    for k in range(STATE_WINDOW):
        t += 0.002
        assert clock.note_state("beaglebone-1", "e1", t + 997.0, t) == (k == STATE_WINDOW - 1)
    assert clock.jumps == 1 and clock.offset_for(good - 0.5) is None and clock.offset_for(t) is None
    assert clock.health()[0]["clock_resyncing"] == 1
    # a burst begun before the jump does not clear it; one begun after does, from its start
    clock._burst_started = good - 1.0
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(997.0, 0.0005, t, 8))
    assert clock.offset_for(t) is None
    clock._burst_started = t + 0.01
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(997.0, 0.0005, t + 0.01, 8))
    assert clock.offset_for(t) is None  # captured before the re-sync began: its offset was the old one
    assert clock.offset_for(t + 0.02) == 997.0 and clock.health()[0]["clock_resyncing"] == 0
    # one state ahead by more than a step is a jump; so is a new run of the followed instance
    t += 0.05
    assert clock.note_state("beaglebone-1", "e1", t + 997.0 + 0.2, t) and clock.jumps == 2
    clock._burst_started = t + 0.01
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(997.2, 0.0005, t + 0.01, 8))
    assert clock.note_state("beaglebone-1", "e2", t + 997.2, t + 0.02) and clock.jumps == 3


def test_without_syncs_the_uncertainty_grows_and_after_a_minute_the_clock_is_stale(caplog) -> None:
    """Audit of 2026-11-29 (f_stale.py): with the bridge gone the camera stamped on the last offset
    forever with its fresh uncertainty. It now grows by 100 ppm of its age; after STALE_S a warning
    (once) and ``clock_stale`` in the health, which the console's camera card shows."""
    from bridge.clock_sync import OffsetEstimate
    from server.camera_feed import clock_status
    from twin.camera.clock import STALE_S, BridgeClock

    now = [100.0]
    clock = BridgeClock(None, local=lambda: now[0])  # type: ignore[arg-type]  # no bus
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(1000.0, 0.0002, 100.0, 8))
    assert clock.uncertainty_s == pytest.approx(0.0002) and not clock.stale() and not clock.check_stale()
    now[0] += 50.0
    assert clock.uncertainty_s == pytest.approx(0.0002 + 100e-6 * 50.0)  # 5.2 ms after 50 s
    received, _ = clock.health()
    assert received["clock_uncertainty_us"] == 5200 and received["clock_stale"] == 0
    now[0] += STALE_S
    with caplog.at_level("WARNING", logger="xneck.camera"):
        assert clock.check_stale() and not clock.check_stale()  # said once
    assert [r.getMessage() for r in caplog.records if "no sync with bridge beaglebone-1" in r.getMessage()]
    received, _ = clock.health()
    assert received["clock_stale"] == 1 and received["clock_age_s"] == 110

    class Presence:  # the console's view of the camera process's health
        def health(self, kind: str):
            assert kind == "camera"
            return [("cam-1", bus.Health(seq=1, stamp_s=0.0, process="camera", instance="cam-1", uptime_s=1.0,
                                         received=received, rejected={}))]

    status = clock_status(Presence())  # type: ignore[arg-type]
    assert status == {"offset_us": received["clock_offset_us"], "uncertainty_us": 11200, "age_s": 110, "stale": True,
                      "resyncing": False, "uncertain": False, "bridge": "beaglebone-1"}
    # a sync makes it fresh again
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(1000.0, 0.0003, now[0], 8))
    assert not clock.stale() and clock.uncertainty_s == pytest.approx(0.0003) and clock.health()[0]["clock_stale"] == 0


def test_a_camera_node_on_the_bridge_clock_times_its_usb_source_on_the_clocks_local_time(monkeypatch, params) -> None:
    """Audit of 2026-11-29 (i_footgun.py): CameraNode with a BridgeClock trusted the source to time
    its grabs on the clock's monotonic time, but UsbSource's default is the wall clock: captures
    went out ~1.8e9 s after their publication. The node sets the source's clock."""
    cv2 = pytest.importorskip("cv2")
    from test_camera_sources import FakeCamera

    from twin.camera.calibration import twin_calibration
    from twin.camera.clock import BridgeClock
    from twin.camera.detect import Detector
    from twin.camera.process import CameraNode
    from twin.camera.source import UsbSource

    monkeypatch.setattr(cv2, "VideoCapture", FakeCamera)
    with bus_pair() as (_hub, session, connect):
        robot = ClockService(connect(), lambda: time.time() + AHEAD_S, "aaaa11112222", "beaglebone-1")
        got: list[bus.CameraAlpha] = []
        sub = session.declare_subscriber(bus.CAMERA_ALPHA,
                                         lambda smp: got.append(bus.decode(bus.CAMERA_ALPHA, smp.payload.to_bytes())))
        camera_session = connect()
        clock = BridgeClock(camera_session, burst=4)
        clock.sync(wait_s=5.0)
        cal = twin_calibration()
        source = UsbSource("0", cal.width, cal.height, latency_s=0.05)  # the default clock: the wall clock
        camera = CameraNode(camera_session, Detector(params.n_joints, params.geometry.L, params.geometry.b, cal),
                            clock=clock)
        try:
            camera.run_source(source, threading.Event(), max_frames=3)
            assert source.clock is clock.local
            assert wait_until(lambda: len(got) >= 3, 5.0)
            for msg in got:
                bus.check_camera_alpha_stamps(msg)
                assert msg.capture_stamp_s == pytest.approx(time.time() + AHEAD_S, abs=1.0)
        finally:
            sub.undeclare()
            camera.close()
            source.close()
            robot.close()


def test_a_bridge_up_without_a_clock_is_named_with_update_it() -> None:
    """Audit of 2026-11-29 (j_oldbridge.py): a bridge of the previous version (alive, no clock
    served) got the hint 'start the bridge first'."""
    from bridge.session import liveliness_token
    from twin.camera.clock import BridgeClock, ClockSyncError

    with bus_pair() as (_hub, session, connect):
        token = liveliness_token(session, "bridge", "beaglebone-1")
        try:
            camera = connect()
            with pytest.raises(ClockSyncError) as err:
                BridgeClock(camera, burst=2, query_timeout_s=0.2).sync(wait_s=0.5)
            text = str(err.value)
            assert "bridge beaglebone-1 is up but serves no clock: update it, or use --clock local" in text, text
            assert "start the bridge first" not in text, text
        finally:
            token.undeclare()


# --- the command ----------------------------------------------------------------------------------

SHIM = """
import sys, time, cv2
class Still:  # a USB camera that never stops (the test ends the process by its clock sync)
    def __init__(self, *a): pass
    def isOpened(self): return True
    def set(self, *a): return True
    def get(self, prop): return 30.0 if prop == cv2.CAP_PROP_FPS else 0.0
    def grab(self): time.sleep(1 / 30); return True
    def retrieve(self): return True, __import__('numpy').zeros((720, 1280, 3), 'uint8')
    def release(self): pass
cv2.VideoCapture = Still
from server.cli import main
main()
"""


def test_xneck_camera_on_a_usb_camera_without_a_bridge_says_so_and_exits_1() -> None:
    with bus_pair() as (hub, _session, _connect):
        done = subprocess.run([sys.executable, "-c", SHIM, "camera", "--source", "usb:0", "--frame-rate-hz", "0",
                               "--connect", hub], capture_output=True, text=True, timeout=120)  # it gives up: no hang
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert done.returncode == 1, done.stderr[-3000:]
    assert len(errors) == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert "no bridge answered on xneck/bridge/clock within 3 s" in errors[0], errors[0]
    assert "--clock local" in errors[0], errors[0]


def test_xneck_camera_logs_the_bridge_clock_offset_once_at_start(bridge) -> None:
    hub, *_ = bridge
    done = subprocess.run([sys.executable, "-c", SHIM, "camera", "--source", "usb:0", "--frame-rate-hz", "0",
                           "--max-frames", "3", "--connect", hub], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = [line for line in done.stderr.splitlines() if "camera clock: bridge beaglebone-1" in line]
    assert len(lines) == 1, done.stderr[-3000:]
    assert " is +1000.0" in lines[0] and " ms ahead of this PC's wall clock" in lines[0], lines[0]
    assert done.stderr.index(lines[0]) < done.stderr.index(" up: --source usb:0")  # synchronised before the first frame


def test_the_sync_thread_takes_a_step_by_itself_and_stops_promptly(bridge) -> None:
    from twin.camera.clock import BridgeClock

    _hub, _session, connect, node = bridge
    clock = BridgeClock(connect(), burst=4, period_s=0.2)
    clock.sync(wait_s=5.0)
    clock.start()
    try:
        node.driver.shift_s = AHEAD_S - 7.5  # type: ignore[attr-defined]  # the board's clock set back
        assert wait_until(lambda: clock.tracker.steps == 1, 5.0, 0.05)
        assert clock.wall_offset_s() == pytest.approx(AHEAD_S - 7.5, abs=0.005)
        assert clock.health()[0]["clock_steps"] == 1
    finally:
        clock.stop()
        # the thread ends by itself, within bounded time (a loaded machine may take longer than
        # stop's own 2 s join): the burst it may be in stops querying at the stop
        thread = clock._thread
        assert thread is not None
        thread.join(10.0)
        assert not thread.is_alive(), "the sync thread did not stop"


def test_beyond_its_uncertainty_budget_the_clock_stamps_no_frame_until_a_sync(caplog) -> None:
    """Session 37: a stale clock stamped for ever, its α_IP published as on time however uncertain
    its offset had grown. Past ``max_uncertainty_s`` (10 ms: about 100 s without a sync at 100 ppm)
    :meth:`offset_for` gives none, said once and in the health; a sync stamps again."""
    from bridge.clock_sync import OffsetEstimate
    from twin.camera.clock import MAX_UNCERTAINTY_S, BridgeClock

    now = [100.0]
    clock = BridgeClock(None, local=lambda: now[0])  # type: ignore[arg-type]  # no bus
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(1000.0, 0.0002, 100.0, 8))
    within = (MAX_UNCERTAINTY_S - 0.0002) / 100e-6  # s of age the budget allows
    now[0] += within - 1.0
    assert clock.offset_for(now[0]) == 1000.0  # stale (over 60 s) but within the budget: stamped
    assert clock.stale() and clock.health()[0]["clock_uncertain"] == 0
    now[0] += 2.0
    with caplog.at_level("WARNING", logger="xneck.camera"):
        assert clock.offset_for(now[0]) is None and clock.offset_for(now[0] + 0.03) is None
    said = [r.getMessage() for r in caplog.records if "no α_IP is stamped" in r.getMessage()]
    assert len(said) == 1 and "beyond 10 ms" in said[0], said
    assert clock.health()[0]["clock_uncertain"] == 1
    clock._take(("beaglebone-1", "e1"), OffsetEstimate(1000.001, 0.0003, now[0], 8))
    assert clock.offset_for(now[0] + 0.01) == 1000.001 and clock.health()[0]["clock_uncertain"] == 0
    with pytest.raises(ValueError, match="max_uncertainty_s"):
        BridgeClock(None, max_uncertainty_s=0.0)  # type: ignore[arg-type]
