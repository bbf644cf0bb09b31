"""The bridge's motor drivers (issue 7): the BeagleBone Blue driver against a fake of rcpy at its
lowest layer (encoder counts in, duty cycles and enable levels out), the lifecycle rules every
driver obeys, the twin and replay drivers."""

from __future__ import annotations

import logging
import math
import os
import re
import sys
import types

import numpy as np
import pytest

from bridge import bus
from bridge.driver import DriverError, Lifecycle, config_from_dict
from bridge.drivers.beaglebone import BeagleBoneConfig, BeagleBoneDriver, Transmission
from bridge.drivers.replay import ReplayConfig, ReplayDriver
from twin.sim.driver import TwinDriver, TwinDriverConfig


class FakeBoard:
    """What librobotcontrol would see: four quadrature counters, four motor outputs, GPIO levels.
    It refuses what the C library refuses (bad channel, duty outside [-1, 1])."""

    def __init__(self) -> None:
        self.counts = {ch: 0 for ch in range(1, 5)}
        self.duty: dict[int, float] = {}
        self.pins: dict[int, int] = {}
        self.motors_enabled = False
        self.calls: list[tuple] = []
        self.failing_reads = 0  # the next this many encoder reads raise OSError (EIO), as a flaky eQEP may

    def modules(self) -> dict[str, types.ModuleType]:
        rcpy = types.ModuleType("rcpy")
        encoder = types.ModuleType("rcpy.encoder")
        motor = types.ModuleType("rcpy.motor")
        gpio = types.ModuleType("rcpy.gpio")

        def enc_get(channel):
            if channel not in self.counts:
                raise ValueError(f"no encoder channel {channel}")
            if self.failing_reads > 0:
                self.failing_reads -= 1
                raise OSError(5, "EIO: encoder read failed (fake board)")
            return self.counts[channel]

        def motor_set(channel, duty):
            if channel not in range(1, 5) or not -1.0 <= duty <= 1.0:
                raise ValueError(f"motor.set({channel}, {duty}) refused")
            self.calls.append(("motor.set", channel, duty))
            self.duty[channel] = duty

        def set_value(pin, value=0):
            self.calls.append(("gpio.set_value", pin, value))
            self.pins[pin] = int(value)

        def enable():
            self.motors_enabled = True

        def disable():
            self.motors_enabled = False

        encoder.get = enc_get
        encoder.set = lambda channel, count: self.counts.__setitem__(channel, count)
        motor.set, motor.enable, motor.disable = motor_set, enable, disable
        gpio.set_value, gpio.get_value = set_value, lambda pin: self.pins.get(pin, 0)
        rcpy.encoder, rcpy.motor, rcpy.gpio = encoder, motor, gpio
        return {"rcpy": rcpy, "rcpy.encoder": encoder, "rcpy.motor": motor, "rcpy.gpio": gpio}


PINS = (57, 49, 116, 113)
# Prototype constants by hand (prototype_3x.toml): r_d = 0.020 m, R = 25, k_t = 0.0367 N·m/A; no gear
# efficiency (its losses are in the identified friction f_s).
AMPS_PER_N = 0.020 / (25 * 0.0367)  # 2.1798e-2 A/N


def _driver(params, **config) -> BeagleBoneDriver:
    return BeagleBoneDriver.from_params(BeagleBoneConfig(**config), params)


def test_force_to_current_to_duty_matches_hand_computation(board, params):
    drv = _driver(params, direction=(1, -1, 1, 1))
    assert drv.transmission == Transmission(r_d=0.020, R=25.0, k_t=0.0367, current_max=5.0)
    assert drv.transmission.amps_per_newton == pytest.approx(AMPS_PER_N)
    drv.configure()
    drv.activate()
    applied = drv.write(np.array([50.0, 50.0, 0.0, 250.0]))
    i50 = 50 * AMPS_PER_N  # 1.0899 A
    # Default ESCON map: PWM 10 % -> -5 A, 90 % -> +5 A, i.e. duty = 0.1 + (I + 5)·0.08.
    expected = [0.1 + (i50 + 5) * 0.08,   # 0.58719
                0.1 + (-i50 + 5) * 0.08,  # motor 2 turns the other way
                0.5,                      # zero force: zero current
                0.9]                      # 250 N needs 5.45 A > 5 A: clamped
    assert [board.duty[ch] for ch in (1, 2, 3, 4)] == pytest.approx(expected, abs=1e-12)
    assert expected[0] == pytest.approx(0.58719, abs=1e-5)
    assert applied == pytest.approx([50.0, 50.0, 0.0, 5.0 / AMPS_PER_N])  # 229.4 N at 5 A


def test_analog_mode_maps_current_to_volts_then_to_duty(board, params):
    drv = _driver(params, set_value_mode="analog", set_value_1=0.0, current_1_A=0.0, set_value_2=10.0,
                  current_2_A=5.0, set_value_min=-10.0, set_value_max=10.0, analog_full_scale_V=12.0)
    drv.configure()
    drv.activate()
    drv.write(np.array([50.0, 100.0, 0.0, 10.0]))
    volts = np.array([50.0, 100.0, 0.0, 10.0]) * AMPS_PER_N * 2.0  # 2 V per A
    assert [board.duty[ch] for ch in (1, 2, 3, 4)] == pytest.approx(volts / 12.0)
    assert board.duty[1] == pytest.approx(2.1798 / 12.0, abs=1e-4)  # 50 N: 1.0899 A, 2.1798 V


def test_counts_in_angles_out_zeroed_at_configure(board, params):
    board.counts.update({1: 100, 2: -40, 3: 0, 4: 7})
    drv = _driver(params, encoder_channels=(2, 1, 3, 4), direction=(1, 1, -1, 1))
    drv.configure()
    assert drv.read() == pytest.approx(np.zeros(4))
    board.counts.update({1: 100 + 512, 2: -40 - 1024, 3: 2048, 4: 7})
    theta = drv.read()  # motor 1 reads channel 2, motor 3 counts the other way
    assert theta == pytest.approx([-math.pi, math.pi / 2, -2 * math.pi, 0.0])


def test_lifecycle_refuses_out_of_order_calls(board, params):
    drv = _driver(params)
    assert drv.state is Lifecycle.UNCONFIGURED
    with pytest.raises(DriverError, match="configured"):
        drv.read()
    with pytest.raises(DriverError, match="refused"):
        drv.write(np.full(4, 10.0))
    with pytest.raises(DriverError, match="activate"):
        drv.activate()
    drv.configure()
    with pytest.raises(DriverError, match="configure"):
        drv.configure()
    with pytest.raises(DriverError, match="inactive"):
        drv.write(np.full(4, 10.0))  # states readable, commands refused
    drv.activate()
    with pytest.raises(DriverError, match="finite"):
        drv.write(np.array([10.0, math.nan, 10.0, 10.0]))
    with pytest.raises(DriverError, match="4 finite"):
        drv.write(np.full(3, 10.0))
    drv.deactivate()
    assert drv.read().shape == (4,)  # encoders still readable
    drv.close()
    assert drv.state is Lifecycle.CLOSED
    with pytest.raises(DriverError):
        drv.read()
    drv.close()  # idempotent


def test_enable_lines_follow_the_lifecycle_and_close_disables(board, params):
    drv = _driver(params)
    drv.configure()
    # Configure forces every drive off: enable low, zero-current set value (PWM 50 %).
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 0)
    assert all(board.duty[ch] == pytest.approx(0.5) for ch in (1, 2, 3, 4))
    drv.activate()
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 1) and board.motors_enabled
    drv.write(np.full(4, 30.0))
    board.calls.clear()
    drv.deactivate()
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 0)
    assert all(board.duty[ch] == pytest.approx(0.5) for ch in (1, 2, 3, 4))
    # The enable lines go low before the set values move: the ESCON stops at once.
    first_motor = next(i for i, c in enumerate(board.calls) if c[0] == "motor.set")
    assert all(c[0] == "gpio.set_value" for c in board.calls[:first_motor]) and first_motor == 4
    drv.activate()
    drv.write(np.full(4, 30.0))
    drv.close()  # from ACTIVE, as on Ctrl-C or a crash
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 0)
    assert all(board.duty[ch] == pytest.approx(0.5) for ch in (1, 2, 3, 4))
    assert not board.motors_enabled


def test_active_low_enable_lines(board, params):
    drv = _driver(params, enable_active_high=False)
    drv.configure()
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 1)
    drv.activate()
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 0)
    drv.close()
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 1)


def _wrap_set_value(monkeypatch, wrapper) -> None:
    """Replace the fake board's ``rcpy.gpio.set_value`` by ``wrapper(original, pin, value)``: an
    rcpy that fails, or misreports, the way a test needs."""
    original = sys.modules["rcpy.gpio"].set_value
    monkeypatch.setattr(sys.modules["rcpy.gpio"], "set_value", lambda pin, value=0: wrapper(original, pin, value))


def test_close_keeps_disabling_when_one_line_fails(board, params, monkeypatch):
    drv = _driver(params)
    drv.configure()
    drv.activate()
    def flaky(original, pin, value=0):
        if pin == PINS[0]:
            raise OSError("gpio write failed")
        original(pin, value)

    _wrap_set_value(monkeypatch, flaky)
    drv.close()  # never raises; logs
    assert {p: board.pins[p] for p in PINS[1:]} == dict.fromkeys(PINS[1:], 0)
    assert drv.state is Lifecycle.CLOSED


def test_an_activate_that_fails_half_way_leaves_every_drive_disabled(board, params, monkeypatch):
    """Audit of 2026-11-26: the third enable line failed to go high; activate() raised with the
    driver INACTIVE ("drives disabled") while lines 57 and 49 stayed high, and deactivate() was a
    no-op that left them so: only close() lowered them. A failed enable now disables again."""
    drv = _driver(params)
    drv.configure()
    def flaky(original, pin, value=0):
        if pin == PINS[2] and value == 1:
            raise OSError("gpio write failed")
        original(pin, value)

    _wrap_set_value(monkeypatch, flaky)
    with pytest.raises(DriverError, match=r"enable line 116 reads 0 after writing 1 \(rcpy raised: gpio write failed"):
        drv.activate()
    assert drv.state is Lifecycle.INACTIVE
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 0)


def test_an_rcpy_that_raises_on_success_still_drives_and_disables(board, params, monkeypatch, caplog):
    """rcpy's _gpio.c raises "Failed to set gpio value" when librobotcontrol returns its success
    code (its check is inverted, docs/bridge.md): every enable looked failed and no drive could be
    enabled. The line read back is the truth: the driver drives, warns once, and disables."""
    def inverted(original, pin, value=0):
        original(pin, value)
        raise RuntimeError("Failed to set gpio value")

    _wrap_set_value(monkeypatch, inverted)
    drv = _driver(params)
    with caplog.at_level(logging.WARNING, logger="xneck.bridge"):
        drv.configure()
        drv.activate()
        assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 1)
        drv.write(np.full(4, 10.0))
        drv.deactivate()
    assert {p: board.pins[p] for p in PINS} == dict.fromkeys(PINS, 0)
    assert sum("raised" in r.getMessage() and "taken as done" in r.getMessage() for r in caplog.records) == 1
    drv.close()


def test_an_rcpy_that_is_silent_on_a_failed_write_is_caught_by_the_read_back(board, params, monkeypatch):
    """The same _gpio.c is silent when librobotcontrol fails: a drive left enabled looked off."""
    drv = _driver(params)
    drv.configure()
    drv.activate()
    def stuck_high(original, pin, value=0):
        if pin != PINS[1]:
            original(pin, value)  # PINS[1] stays as it was, and nothing is raised

    _wrap_set_value(monkeypatch, stuck_high)
    with pytest.raises(DriverError, match=r"enable line 49 reads 1 after writing 0 \(rcpy reported no error\)"):
        drv.deactivate()
    assert board.pins[PINS[1]] == 1 and all(board.pins[p] == 0 for p in PINS if p != PINS[1])


@pytest.mark.parametrize("fields, message", [
    ({"direction": (1, 1, 1)}, "one per motor"),
    ({"direction": (1, 2, 1, 1)}, "direction"),
    ({"motor_channels": (1, 1, 2, 3)}, "distinct"),
    ({"encoder_channels": (1, 2, 3, 5)}, "distinct"),
    ({"set_value_2": 0.10}, "must differ"),
    ({"set_value_max": 1.2}, "within"),
    ({"set_value_mode": "analog", "set_value_min": -12.0, "set_value_max": 10.0}, "within"),
    ({"current_1_A": 1.0, "current_2_A": 5.0}, "zero current"),
    ({"set_value_mode": "voltage"}, "set_value_mode: Invalid enum"),
    ({"enable_pins": (1, 1, 2, 3)}, "enable_pins"),
    ({"bogus": 1}, "bogus"),
])
def test_bad_config_names_the_field(fields, message):
    with pytest.raises(DriverError, match=message):
        config_from_dict(BeagleBoneConfig, fields)


def test_a_config_for_another_motor_count_is_refused_before_the_board_is_touched(board, params):
    """Audit of 2026-11-27: a 3-motor config with the 4-cable prototype's parameter set was
    configured (three drives off, the board's encoders zeroed) and `--drives-off` reported "every
    drive disabled" while the fourth enable line was never written."""
    from server.cli.processes import make_driver

    table = {"n_motors": 3, "encoder_channels": [1, 2, 3], "motor_channels": [1, 2, 3], "direction": [1, 1, 1],
             "enable_pins": list(PINS[:3])}
    with pytest.raises(DriverError, match=r"n_motors = 3, the parameter set 4 cables"):
        make_driver("beaglebone", params, table)
    assert board.calls == [] and board.pins == {}


def test_missing_rcpy_is_a_clear_error(monkeypatch, params):
    monkeypatch.setitem(sys.modules, "rcpy", None)  # import rcpy raises ImportError
    drv = _driver(params)
    with pytest.raises(DriverError, match="rcpy"):
        drv.configure()
    assert drv.state is Lifecycle.UNCONFIGURED
    drv.close()


def test_cli_beaglebone_without_rcpy_fails_cleanly(xneck):
    run = xneck("bridge", "--driver", "beaglebone", timeout=60)
    assert run.returncode == 2
    assert "rcpy" in run.stderr and "not installed" in run.stderr
    assert "Traceback" not in run.stderr + run.stdout


def test_a_bridge_that_cannot_disable_a_drive_on_exit_says_so_and_fails(xneck, tmp_path):
    """Audit of 2026-11-27: an enable line stuck high when the bridge exits (tests/fake_rcpy:
    writes ignored, the line reads 1). Driver.close never raises, and the bridge logged "drives
    disabled" and exited 0, so `xneck up --robot` (which runs --drives-off after a non-zero exit
    only) told the operator nothing."""
    from pathlib import Path

    fake = Path(__file__).parent / "fake_rcpy"
    env = {"PYTHONPATH": os.pathsep.join([str(fake), os.environ.get("PYTHONPATH", "")]),
           "FAKE_RCPY_STUCK_HIGH": f"{PINS[3]}:2", "FAKE_RCPY_LOG": str(tmp_path / "rcpy.log")}
    # The first write of the line (configure: off) works; the one on exit does not.
    run = xneck("bridge", "--driver", "beaglebone", "--max-ticks", "5", "--listen", "tcp/127.0.0.1:0", env=env,
                timeout=120)
    out = run.stdout + run.stderr
    assert run.returncode != 0, out[-3000:]
    assert "DRIVES MAY BE ON" in out and f"enable line {PINS[3]} reads 1 after writing 0" in out, out[-3000:]
    assert "drives disabled" not in out, out[-3000:]
    # --drives-off, whose configure disables them and whose close disables them again, fails too
    off = xneck("bridge", "--driver", "beaglebone", "--drives-off", env={**env, "FAKE_RCPY_STUCK_HIGH": f"{PINS[3]}:2"},
                timeout=120)
    assert off.returncode != 0 and "every drive disabled" not in off.stdout + off.stderr


def test_twin_driver_steps_with_zero_force_unless_active(params):
    drv = TwinDriver(TwinDriverConfig(seed=1, camera=False), params)
    drv.configure()
    with pytest.raises(DriverError):
        drv.write(np.full(4, 20.0))
    drv.step()  # inactive: unpowered motors
    assert drv.stamp_s() == pytest.approx(0.002)
    drv.activate()
    f = np.array([20.0, 20.0, 20.0, 20.0])
    assert drv.write(f) == pytest.approx(f)
    for _ in range(50):
        drv.step()
    theta = drv.read()
    # Quantised like the encoders: whole counts of 2π/2048.
    assert np.allclose(theta / (2 * math.pi / 2048), np.round(theta / (2 * math.pi / 2048)))
    assert np.abs(theta).max() > 0
    keys = [k for k, _ in drv.extra_messages()]
    assert keys == [bus.TWIN_TRUTH]
    drv.close()


def test_replay_driver_replays_archived_angles(tmp_path):
    from bridge.archive import write_campaign

    states = [bus.MotorState(seq=k, stamp_s=0.002 * k, theta_rad=[0.1 * k, 0.0, -0.1 * k, 1.0],
                             force_applied_N=[10.0 + k, 10.0, 10.0, 10.0], drive="active", epoch="e0",
                             bridge="b0") for k in range(5)]
    path = write_campaign(tmp_path / "c.mcap", [(bus.MOTOR_STATE, k * 2_000_000, s) for k, s in enumerate(states)],
                          {"campaign_id": "r1", "kind": "control"})
    drv = ReplayDriver(ReplayConfig(path=str(path)))
    drv.configure()
    drv.activate()
    seen = []
    while not drv.exhausted:  # the bridge's order: write, step, read
        drv.write(np.full(4, 50.0))
        drv.step()
        seen.append(drv.read().tolist())
        assert drv.write(np.full(4, 50.0))[0] == 10.0 + len(seen) - 1  # accepted, ignored
    assert seen == [s.theta_rad for s in states]
    drv.close()
    with pytest.raises(DriverError, match="no such file"):
        ReplayDriver(ReplayConfig(path=str(tmp_path / "missing.mcap"))).configure()


def test_beaglebone_and_twin_apply_the_same_motor_torque_for_a_commanded_force(board, params):
    """Issue 13, finding 9: one force → torque convention for the robot and the twin. A cable force
    f is the motor torque seen at the cable, τ_m = f·r_d/R (eq. 29 of the twin); the gear losses
    are in the identified friction f_s (eq. 37), so the driver has no efficiency η either: the
    ESCON gets I = f·r_d/(R·k_t). Dividing by η = 0.81 again made the robot's forces 23 % high."""
    from twin.model.dynamics import accelerations
    from twin.model.numeric import build

    f = np.array([5.0, 20.0, 50.0, 100.0])
    drv = _driver(params, direction=(1, -1, 1, -1))
    drv.configure()
    drv.activate()
    drv.write(f)
    cfg = drv.config
    current_A = np.array([d * cfg.current_at(board.duty[ch]) for d, ch in zip(cfg.direction, cfg.motor_channels)])
    torque_robot = params.motors.torque_constant * current_A

    twin = TwinDriver(TwinDriverConfig(camera=False), params)
    twin.configure()
    twin.activate()
    applied = twin.write(f)  # the force the twin's motors get
    model = build(params, "linear")
    rest = (np.zeros(3), np.zeros(4), np.zeros(3), np.zeros(4))
    theta_ddot = accelerations(model, *rest, applied).theta_ddot - accelerations(model, *rest, np.zeros(4)).theta_ddot
    torque_twin = params.motors.I_a * theta_ddot  # eq. 29: I_a·θ̈ = (r_d/R)(f − f_friction − t)
    twin.close()

    assert torque_robot == pytest.approx(torque_twin, rel=1e-9)
    assert torque_robot == pytest.approx(f * params.geometry.r_d / params.geometry.R, rel=1e-9)


def test_the_bridge_on_the_beaglebone_driver_ramps_the_escon_currents_after_an_estop_release(board, params):
    """Issue 13 on the robot's path: the same bridge rules drive the ESCONs. After an e-stop the
    enable lines are low at once; after the release the set values move at most 1 N's worth of
    current per tick towards the first commands ([81, 22, 8, 28] N, finding 1), and only for the
    owning controller."""
    import time

    from busutil import bus_pair, wait_until

    from bridge.node import BridgeConfig
    from bridge.session import liveliness_token, publisher
    from server.cli.processes import bridge_node

    drv = _driver(params)
    cfg = drv.config
    amps_per_newton = drv.transmission.amps_per_newton

    def forces_at_the_escons():  # what the ESCONs drive, as forces; zero with the enable lines low
        if not all(board.pins[p] == 1 for p in cfg.enable_pins):
            return np.zeros(4)
        return np.array([cfg.current_at(board.duty[ch]) for ch in cfg.motor_channels]) / amps_per_newton

    with bus_pair() as (_hub, hub_session, connect):
        node = bridge_node(connect(), drv, params, BridgeConfig(command_timeout_s=5.0))
        _token = liveliness_token(hub_session, "controller", "ctl")
        cmd_pub, estop_pub = publisher(hub_session, bus.MOTOR_COMMAND), publisher(hub_session, bus.ESTOP)

        def command(seq, force, sender="ctl"):
            # The owner's command must be accepted: until the bridge has seen the owner's fresh
            # liveliness token it refuses it ("no liveliness token"), and a received-only wait
            # made the test flaky. The intruder's must merely arrive (it is refused).
            # Each identified by what it does, not by a count: a late copy of an earlier command,
            # re-put on a slow route, had counted as the intruder's arrival (review of session 45).
            def arrived(n_rejected=node.commands.stats.rejected):
                stats = node.commands.stats
                if sender == "ctl":
                    latest = node.commands.latest()
                    return latest is not None and latest.seq == seq and latest.sender == sender
                return stats.rejected > n_rejected and "owned by" in stats.last_reject_reason

            if math.isnan(node.last_state_stamp_s):
                node.publish_state()  # a state to answer
            msg = bus.ForceCommand(seq=seq, stamp_s=node.last_state_stamp_s, force_N=force, source="law2", sender=sender,
                                   epoch=node.epoch)
            for _ in range(250):  # the first messages on a fresh route may be lost
                cmd_pub.put(msg)
                if wait_until(arrived, 0.02, 0.002):
                    return
            raise AssertionError(f"command never arrived: {node.commands.stats}")

        seen = []
        try:
            command(1, [9.0] * 4)
            for _ in range(15):
                node.tick()
            assert forces_at_the_escons() == pytest.approx([9.0] * 4)
            engage = bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="button")
            # The first messages on a fresh route may be lost, so each is repeated until the bridge has
            # applied it. Copies still in flight must not land after the release (a loaded suite once
            # re-engaged the drives that way): wait until no more arrive before releasing.
            assert wait_until(lambda: (estop_pub.put(engage), node.tick(), node.safety.estop_engaged)[2], 5.0, 0.02)
            assert all(board.pins[p] == 0 for p in cfg.enable_pins) and node.mode == "disabled"
            quiet = [node.estop_received, time.monotonic()]

            def settled():
                if node.estop_received != quiet[0]:
                    quiet[:] = [node.estop_received, time.monotonic()]
                return time.monotonic() - quiet[1] > 0.2

            assert wait_until(settled, 5.0, 0.02)
            node.tick()
            release = bus.EStop(seq=2, stamp_s=time.time(), engaged=False, reason="cleared")
            assert wait_until(lambda: (estop_pub.put(release), node.tick(), not node.safety.estop_engaged)[2], 5.0,
                              0.02)
            seen.append(forces_at_the_escons())
            command(2, [81.0, 22.0, 8.0, 28.0])
            command(3, [60.0] * 4, sender="intruder")  # not the owner: refused, never applied
            assert node.commands.stats.rejected >= 1
            for _ in range(100):
                node.tick()
                seen.append(forces_at_the_escons())
            state = (node.mode, node.hold_reason, node.estop_received, node.commands.stats)  # for a failure's message
        finally:
            node.shutdown()
    steps = np.abs(np.diff(np.array(seen), axis=0))
    assert steps.max() <= 1.0 + 1e-9, steps.max()
    assert seen[-1] == pytest.approx([81.0, 22.0, 8.0, 28.0]), state
    assert all(board.pins[p] == 0 for p in cfg.enable_pins)  # shutdown disabled the drives


def test_drives_off_switches_the_lines_off_when_the_encoders_fail_to_initialise(xneck, tmp_path):
    """Audit of 2026-11-28: rcpy's encoder module failing at import (upstream's C code returns NULL
    when rc_encoder_eqep_init fails: a SystemError, not an ImportError) made `--drives-off` end in a
    traceback before any enable line was written. The lines need rcpy.gpio alone."""
    from pathlib import Path

    fake = Path(__file__).parent / "fake_rcpy"
    rlog = tmp_path / "rcpy.log"
    env = {"PYTHONPATH": os.pathsep.join([str(fake), os.environ.get("PYTHONPATH", "")]),
           "FAKE_RCPY_ENCODER_INIT_FAILS": "1", "FAKE_RCPY_LOG": str(rlog)}
    off = xneck("bridge", "--driver", "beaglebone", "--drives-off", env=env, timeout=120)
    out = off.stdout + off.stderr
    assert off.returncode == 2 and "Traceback" not in out, out[-3000:]
    assert "rcpy.encoder failed to initialise" in out and "the enable lines are off" in out, out[-3000:]
    levels = {w[2]: w[3] for w in (line.split() for line in rlog.read_text().splitlines()) if w[1].startswith("gpio")}
    assert all(levels.get(str(pin)) == "0" for pin in PINS), levels  # every enable line low (active high)


@pytest.mark.parametrize(("table", "refused"), [
    # one-sided, as cable forces only pull: motors 2 and 4 wind the other way and could never pull
    ({"set_value_1": 0.10, "current_1_A": 0.0, "set_value_2": 0.90, "current_2_A": 5.0, "direction": [1, -1, 1, -1]},
     "motor 2 (direction -1)"),
    # ±0.5 A typed for ±5 A: the ESCONs would drive ten times the force the bridge reports
    ({"current_1_A": -0.5, "current_2_A": 0.5}, "motor 1 (direction +1)"),
])
def test_an_escon_map_that_cannot_reach_f_max_in_every_direction_is_refused(board, params, table, refused):
    """Audit of 2026-11-28: both configs were accepted and the drives enabled; commanding 100 N gave
    0 A on two motors, or at most 22.9 N reported while the drives drove up to 229 N."""
    from server.cli.processes import make_driver

    with pytest.raises(DriverError, match=rf"{re.escape(refused)} needs set value .* outside \[0.1, 0.9\]"):
        make_driver("beaglebone", params, {"n_motors": 4, **table})
    assert board.calls == [] and board.pins == {}  # before the board is touched
    make_driver("beaglebone", params, {"n_motors": 4, "direction": [1, -1, 1, -1]})  # the default map: both ways


@pytest.mark.parametrize("rate_hz", [20_000.0, 1e6, 10.0])
def test_a_driver_rate_out_of_range_is_refused(board, params, rate_hz):
    """Audit of 2026-11-28: `rate_hz` in escon.toml was taken up to 1 MHz: the bridge's 10 ms
    timeout became 200-1,000 unanswered states and its loop never slept."""
    from server.cli.processes import make_driver

    with pytest.raises(DriverError, match=r"rate_hz must be within \[50, 2000\] Hz"):
        make_driver("beaglebone", params, {"n_motors": 4, "rate_hz": rate_hz})
    assert board.calls == []


def test_an_estop_whose_disable_fails_leaves_no_claim_that_the_drives_are_off(tmp_path):
    """Audit of 2026-11-28: an enable line stuck high from its third write (configure off, enable
    on, then the e-stop's off): the bridge exited on the fault with its last state on the bus saying
    `disabled` and no line of its log saying DRIVES MAY BE ON."""
    import subprocess
    import sys
    import time
    from pathlib import Path

    from bridge import bus
    from bridge.session import free_tcp_port, liveliness_token, open_session, publisher

    fake = Path(__file__).parent / "fake_rcpy"
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "XNECK_REALTIME": "0", "FAKE_RCPY_STUCK_HIGH": f"{PINS[0]}:3",
           "PYTHONPATH": os.pathsep.join([str(fake), os.environ.get("PYTHONPATH", "")])}
    states: list[bus.MotorState] = []
    with open_session(listen=[hub], connect=[]) as s:
        sub = s.declare_subscriber(bus.MOTOR_STATE, lambda x: states.append(bus.decode(bus.MotorState, x.payload.to_bytes())))
        token = liveliness_token(s, "controller", "test-ctl")
        commands, estop = publisher(s, bus.MOTOR_COMMAND), publisher(s, bus.ESTOP)
        with open(tmp_path / "bridge.log", "wb") as log:
            proc = subprocess.Popen([sys.executable, "-m", "server.cli", "bridge", "--driver", "beaglebone", "--listen",
                                     "tcp/127.0.0.1:0", "--connect", hub], stdout=log, stderr=subprocess.STDOUT, env=env)
        try:
            deadline = time.monotonic() + 60
            while not states or states[-1].drive != "active":
                assert proc.poll() is None and time.monotonic() < deadline, (tmp_path / "bridge.log").read_text()[-3000:]
                if states:
                    commands.put(bus.ForceCommand(seq=len(states), stamp_s=states[-1].stamp_s, force_N=[20.0] * 4,
                                                  source="test", sender="test-ctl", epoch=states[-1].epoch))
                time.sleep(0.002)
            estop.put(bus.EStop(seq=1, stamp_s=time.time(), engaged=True, reason="operator"))
            proc.wait(20)
            time.sleep(0.3)  # the last state on its way
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            sub.undeclare()
            token.undeclare()
    out = (tmp_path / "bridge.log").read_text()
    assert proc.returncode != 0, out[-3000:]
    assert "DRIVES MAY BE ON" in out, out[-3000:]
    last = states[-1]
    assert last.drive != "disabled" and "DRIVES MAY BE ON" in last.hold_reason, last


def test_a_pru_encoder_reading_minus_one_at_start_is_warned(board, params, caplog):
    """Audit of 2026-11-28: channel 4 is the PRU's; without its firmware librobotcontrol reads -1
    every time, which the driver zeroed as a count and nothing flagged."""
    import logging

    board.counts[4] = -1
    drv = _driver(params)
    with caplog.at_level(logging.WARNING, logger="xneck"):
        drv.configure()
    assert any("encoder channel 4 reads -1" in r.getMessage() for r in caplog.records), caplog.text
    caplog.clear()
    drv.close()  # one bridge per board (bridge/drivers/board_lock.py)
    board.counts[4] = 0
    with caplog.at_level(logging.WARNING, logger="xneck"):
        _driver(params).configure()
    assert not any("reads -1" in r.getMessage() for r in caplog.records)


def test_a_second_driver_on_one_board_is_refused_before_it_touches_a_pin(board, params):
    """Session 37: a second ``xneck bridge --driver beaglebone`` on the board a bridge drives turned
    every drive off and zeroed its encoders in its ``configure`` while the first went on ``active``
    (then both wrote the same pins). The board's lock refuses it, naming the holder; the first
    bridge's drives stay on; once it closes, the board is free; ``--drives-off`` (an off switch)
    is not refused."""
    first = _driver(params)
    first.configure()
    first.activate()
    first.write(np.full(4, 20.0))
    first.step()
    assert [board.pins.get(p) for p in PINS] == [1, 1, 1, 1]
    calls = len(board.calls)
    second = _driver(params)
    with pytest.raises(DriverError, match=f"another xneck bridge drives this board \\(pid {os.getpid()}"):
        second.configure()
    assert len(board.calls) == calls and [board.pins.get(p) for p in PINS] == [1, 1, 1, 1]  # nothing written
    off = _driver(params)
    off.exclusive = False
    off.configure()  # the off switch acts
    assert [board.pins.get(p) for p in PINS] == [0, 0, 0, 0]
    off.close()
    first.close()
    third = _driver(params)
    third.configure()  # the board is free again
    third.close()
