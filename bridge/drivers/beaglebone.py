"""The 3-X prototype's motor driver: a BeagleBone Blue with four ESCON 50/5 in current mode.

Hardware path (3-X paper §2.2): four Maxon EC-max 40 motors with GP 42 C gearheads, each run by an
ESCON 50/5 in current (torque) mode; the BeagleBone Blue reads the four motor encoders and sends
each ESCON a current set value and an enable line.

- Encoders in: the Blue's four quadrature counters (``rcpy.encoder.get(channel)``, counts).
- Set values out: the Blue's four motor outputs (``rcpy.motor.set(channel, duty)``, duty in
  [-1, 1]), either read by the ESCON as a PWM duty cycle (``set_value_mode = "pwm"``, set value =
  duty) or low-pass filtered into the ESCON's differential analog input (``"analog"``, set value =
  volts = duty · ``analog_full_scale_V``).
- Enable lines out: one GPIO per ESCON (``rcpy.gpio.set_value(pin, level)``).

Force to set value::

    I   = f · r_d / (R · k_t)                motor current (A) for a cable force f (N)
    I_m = direction · min(I, current_max)     signed current the ESCON must drive
    s   = s1 + (I_m − I1) · (s2 − s1) / (I2 − I1)    the ESCON's linear set-value map
    s   clamped to [set_value_min, set_value_max]    the input range the ESCON accepts

with r_d (drum radius), R (gear ratio), k_t (torque constant) and current_max from the parameter
file (``geometry`` and ``motors``), and the two points (s1 → I1, s2 → I2) exactly as configured
in ESCON Studio, in :class:`BeagleBoneConfig`.

Convention (one for the robot, the twin and identification, issue 13 finding 9): a cable force f
is the motor torque seen at the cable, τ_m = k_t·I = f·r_d/R, exactly the twin's motor equation
I_a·θ̈ = (r_d/R)(f − f_friction − t) (eq. 29). The gearhead's losses are not a factor η here:
they are part of the dry friction f_s identified on the robot (eqs. 37, 44-45), which the
controller compensates. Dividing by η as well would count them twice (forces ~23 % high at
η = 0.81). ``motors.gear_efficiency`` of the parameter file is therefore not applied.

``rcpy`` (Python bindings of librobotcontrol) is imported only when this driver is configured, so
every other driver runs on machines without it. Importing ``rcpy`` installs its own SIGINT and
SIGTERM handlers: install the bridge's handlers after :meth:`Driver.configure`.
"""

from __future__ import annotations

import importlib
import logging
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from bridge.driver import Driver, DriverConfig, DriverError
from bridge.drivers import board_lock

log = logging.getLogger("xneck.bridge.beaglebone")

#: ESCON 50/5 analog set-value input range (V).
ESCON_ANALOG_RANGE_V = (-10.0, 10.0)
#: BeagleBone Blue GP0 header pins 3-6 (librobotcontrol pinmap: BLUE_GP0_PIN_3..6 = gpio 1_25,
#: 1_17, 3_20, 3_17); our wiring assumption for the four enable lines.
BLUE_GP0_PINS = (57, 49, 116, 113)


class BeagleBoneConfig(DriverConfig, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Wiring of the BeagleBone Blue to the four ESCON 50/5, and the ESCONs' set-value maps.

    Per-motor tuples are in motor order (the parameter file's). Defaults are our assumptions for
    the prototype: check them against the wiring and the ESCON Studio configuration.

    - ``encoder_channels``: quadrature counter of each motor (1-4).
    - ``counts_per_rev``: counts per motor-shaft turn in quadrature; 0 takes the parameter file's
      ``sensors.encoder_counts_per_rev``.
    - ``motor_channels``: Blue motor output (1-4) carrying each ESCON's set value.
    - ``direction``: +1 or -1 per motor, so that positive current winds the cable (pulls) and the
      encoder angle grows while winding.
    - ``set_value_mode``: ``"pwm"`` (set value = duty cycle in [0, 1]) or ``"analog"`` (set value
      in V, produced as duty · ``analog_full_scale_V`` through an RC filter).
    - ``set_value_1 → current_1_A`` and ``set_value_2 → current_2_A``: the two points of the ESCON's
      linear map (ESCON Studio: "current at PWM 1 / PWM 2" or "at voltage 1 / voltage 2").
    - ``set_value_min``, ``set_value_max``: the set values the ESCON accepts (PWM 10-90 %, or
      within ±10 V); commands are clamped into this range.
    - ``analog_full_scale_V``: analog mode only, the filtered output voltage at duty 1 (the Blue's
      motor supply).
    - ``enable_pins``: GPIO number of each ESCON's enable line; ``enable_active_high``: its polarity.
    """

    encoder_channels: tuple[int, ...] = (1, 2, 3, 4)
    counts_per_rev: int = 0
    motor_channels: tuple[int, ...] = (1, 2, 3, 4)
    direction: tuple[int, ...] = (1, 1, 1, 1)
    set_value_mode: Literal["pwm", "analog"] = "pwm"
    set_value_1: float = 0.10
    current_1_A: float = -5.0
    set_value_2: float = 0.90
    current_2_A: float = 5.0
    set_value_min: float = 0.10
    set_value_max: float = 0.90
    analog_full_scale_V: float = 12.0
    enable_pins: tuple[int, ...] = BLUE_GP0_PINS
    enable_active_high: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("encoder_channels", "motor_channels", "direction", "enable_pins"):
            self.per_motor(name, getattr(self, name))
        for name in ("encoder_channels", "motor_channels"):
            channels = getattr(self, name)
            if not all(1 <= c <= 4 for c in channels) or len(set(channels)) != len(channels):
                raise ValueError(f"{name} must be distinct Blue channels 1-4, got {channels}")
        if len(set(self.enable_pins)) != len(self.enable_pins) or min(self.enable_pins) < 0:
            raise ValueError(f"enable_pins must be distinct GPIO numbers, got {self.enable_pins}")
        if not all(d in (1, -1) for d in self.direction):
            raise ValueError(f"direction must be +1 or -1 per motor, got {self.direction}")
        if self.counts_per_rev < 0:
            raise ValueError(f"counts_per_rev must be > 0 (or 0 for the parameter file's), got {self.counts_per_rev}")
        if self.set_value_1 == self.set_value_2:
            raise ValueError(f"set_value_1 and set_value_2 must differ, both are {self.set_value_1}")
        if self.current_1_A == self.current_2_A:
            raise ValueError(f"current_1_A and current_2_A must differ, both are {self.current_1_A} A")
        if not self.set_value_min < self.set_value_max:
            raise ValueError(f"set_value_min = {self.set_value_min} must be below set_value_max = {self.set_value_max}")
        if self.set_value_mode == "pwm":
            lo, hi, unit = 0.0, 1.0, ""
        else:
            lo, hi, unit = max(ESCON_ANALOG_RANGE_V[0], -self.analog_full_scale_V), \
                min(ESCON_ANALOG_RANGE_V[1], self.analog_full_scale_V), " V"
            if not self.analog_full_scale_V > 0:
                raise ValueError(f"analog_full_scale_V must be > 0, got {self.analog_full_scale_V}")
        if not (lo <= self.set_value_min and self.set_value_max <= hi):
            raise ValueError(f"{self.set_value_mode} set values must lie within [{lo}, {hi}]{unit}, got "
                             f"[{self.set_value_min}, {self.set_value_max}]{unit}")
        zero = self.set_value_at(0.0)
        if not self.set_value_min <= zero <= self.set_value_max:
            raise ValueError(f"zero current needs set value {zero:.4g}, outside [{self.set_value_min}, "
                             f"{self.set_value_max}]: the drives could not be idled")

    def set_value_at(self, current_A: float) -> float:
        """The ESCON's linear map, unclamped: set value for a signed current (A)."""
        slope = (self.set_value_2 - self.set_value_1) / (self.current_2_A - self.current_1_A)
        return self.set_value_1 + (current_A - self.current_1_A) * slope

    def current_at(self, set_value: float) -> float:
        """Inverse of :meth:`set_value_at`: the signed current (A) the ESCON drives at a set value."""
        slope = (self.current_2_A - self.current_1_A) / (self.set_value_2 - self.set_value_1)
        return self.current_1_A + (set_value - self.set_value_1) * slope

    def duty_of(self, set_value: float) -> float:
        """Duty cycle of the Blue's motor output that produces ``set_value``."""
        return set_value if self.set_value_mode == "pwm" else set_value / self.analog_full_scale_V


@dataclass(frozen=True)
class Transmission:
    """Cable force to motor current, from the parameter file (``geometry``, ``motors``).

    ``r_d`` drum radius (m), ``R`` gear ratio, ``k_t`` torque constant (N·m/A), ``current_max`` (A)
    the motor controller's continuous current. No gear efficiency: see the module docstring.
    """

    r_d: float
    R: float
    k_t: float
    current_max: float

    @classmethod
    def from_params(cls, params: Any) -> Transmission:
        g, m = params.geometry, params.motors
        return cls(r_d=g.r_d, R=g.R, k_t=m.torque_constant, current_max=m.current_max)

    @property
    def amps_per_newton(self) -> float:
        """I/f = r_d / (R·k_t): the drum turns f into a torque f·r_d, the gearhead divides it by R,
        the motor makes k_t N·m per A (its losses are in the identified friction f_s)."""
        return self.r_d / (self.R * self.k_t)


#: The Blue's fourth quadrature counter is read by the PRU, not an eQEP (librobotcontrol).
PRU_ENCODER_CHANNEL = 4


class _Board:
    """The rcpy modules this driver calls, in one place (the layer the tests fake)."""

    def __init__(self) -> None:
        try:
            importlib.import_module("rcpy")  # initialises the board (librobotcontrol)
            self.gpio = importlib.import_module("rcpy.gpio")  # first: the enable lines are all drives-off needs
        except ImportError as exc:
            raise DriverError(
                "the beaglebone driver needs rcpy, the BeagleBone Blue's Python library (librobotcontrol), "
                f"which is not installed here ({exc}). Run it on the board after `pip install rcpy`, "
                "or choose --driver twin or --driver replay."
            ) from None
        # The encoder and motor modules initialise hardware when imported (rcpy's C code returns
        # NULL, a SystemError, when rc_encoder_eqep_init fails): a failure here must not stop the
        # enable lines from being switched off (audit of 2026-11-28: --drives-off touched no line).
        self.encoder: Any = None
        self.motor: Any = None
        self.failed: dict[str, str] = {}
        for name in ("encoder", "motor"):
            try:
                setattr(self, name, importlib.import_module(f"rcpy.{name}"))
            except Exception as exc:  # noqa: BLE001 - reported by the driver, after the lines are off
                self.failed[name] = f"rcpy.{name} failed to initialise ({type(exc).__name__}: {exc})"


class BeagleBoneDriver(Driver):
    """Four encoders in, four ESCON set values and enable lines out (module docstring)."""

    name = "beaglebone"

    def __init__(self, config: BeagleBoneConfig, transmission: Transmission, counts_per_rev: int = 2048) -> None:
        super().__init__(config)
        self.config: BeagleBoneConfig = config
        self.transmission = transmission
        self.counts_per_rev = config.counts_per_rev or counts_per_rev
        if self.counts_per_rev <= 0:
            raise DriverError(f"beaglebone: counts_per_rev must be > 0, got {self.counts_per_rev}")
        self._board: _Board | None = None
        self._offset = np.zeros(config.n_motors)
        self._offset_list = self._offset.tolist()
        self._sign = np.array(config.direction, dtype=float)
        self._sign_list = self._sign.tolist()
        self._zero_duty = config.duty_of(config.set_value_at(0.0))
        self._warned_inverted = False  # an rcpy whose gpio.set_value raises on success (_set_enable)
        # One bridge per board (bridge.drivers.board_lock); `--drives-off` only switches drives off
        # and may run beside a bridge, as an off switch
        self.exclusive = True
        self._lock_fd: int | None = None

    @classmethod
    def from_params(cls, config: BeagleBoneConfig, params: Any) -> BeagleBoneDriver:
        # Before the board is opened: a config for fewer motors than the robot has cables would
        # otherwise be configured (its drives off) and `--drives-off` would report "every drive
        # disabled" with the others' enable lines never written.
        if config.n_motors != params.n_cables:
            raise DriverError(f"beaglebone: the driver config has n_motors = {config.n_motors}, the parameter set "
                              f"{params.n_cables} cables: every drive must be wired in the config")
        transmission = Transmission.from_params(params)
        # Every motor must reach the current of f_max in its own direction within the set values
        # the ESCON accepts: the map is one for all four, the direction is per motor, and a map
        # that cannot (one-sided, or ±0.5 A typed for ±5 A) was accepted, so that two cables
        # never pulled, or the drives drove ten times the force reported (audit of 2026-11-28).
        f_max = float(params.limits.f_max)
        current = min(f_max * transmission.amps_per_newton, transmission.current_max)
        lo, hi = config.set_value_min, config.set_value_max
        for motor, sign in enumerate(config.direction, start=1):
            value = config.set_value_at(sign * current)
            if not lo - 1e-9 <= value <= hi + 1e-9:
                raise DriverError(
                    f"beaglebone: motor {motor} (direction {sign:+d}) needs set value {value:.4g} for {sign * current:.3g} A "
                    f"(f_max = {f_max:g} N), outside [{lo:g}, {hi:g}]: the ESCON map (set_value_1 -> current_1_A = "
                    f"{config.set_value_1:g} -> {config.current_1_A:g} A, set_value_2 -> current_2_A = "
                    f"{config.set_value_2:g} -> {config.current_2_A:g} A) must reach ±{current:.3g} A")
        return cls(config, transmission, params.sensors.encoder_counts_per_rev)

    # -- conversions (pure, unit-tested against hand computation) ------------------------------
    def set_values(self, force_N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Set values (duty or V) for cable forces (N), and the forces they actually produce. On
        plain floats, every tick: numpy on four values cost 60 µs on x86, more than the rest of
        the bridge's tick (issue 20)."""
        cfg, tr = self.config, self.transmission
        per_N, i_max, lo, hi = tr.amps_per_newton, tr.current_max, cfg.set_value_min, cfg.set_value_max
        s, applied = [], []
        for sign, f in zip(self._sign_list, np.asarray(force_N, dtype=float).tolist(), strict=True):
            current = f * per_N
            current = 0.0 if current < 0.0 else i_max if current > i_max else current
            value = cfg.set_value_at(sign * current)
            value = lo if value < lo else hi if value > hi else value
            s.append(value)
            f_applied = sign * cfg.current_at(value) / per_N
            applied.append(f_applied if f_applied > 0.0 else 0.0)
        return np.array(s), np.array(applied)

    # -- hooks ---------------------------------------------------------------------------------
    def _on_configure(self) -> None:
        if self.exclusive and self._lock_fd is None:
            self._lock_fd = board_lock.claim()  # before any pin: a second bridge writes nothing
        self._board = _Board()
        # Enable lines may float high at boot: force every drive off before anything else.
        self._drives_off()
        if self._board.failed:
            raise DriverError("beaglebone: " + "; ".join(self._board.failed.values())
                              + ": the enable lines are off; check the board (librobotcontrol) and rcpy")
        self._offset = self._counts()
        self._offset_list = self._offset.tolist()
        for ch, count in zip(self.config.encoder_channels, self._offset_list, strict=True):
            if ch == PRU_ENCODER_CHANNEL and count == -1:
                # librobotcontrol's rc_encoder_pru_read() answers -1 on every read when the PRU
                # firmware is not running (rcpy ignores the failed init): a dead encoder read as a
                # count, caught only once the neck moves (audit of 2026-11-28)
                log.warning("beaglebone: encoder channel %d reads -1 at start, what librobotcontrol returns when "
                            "the PRU encoder firmware is not running: check it (docs/bridge.md) before moving",
                            PRU_ENCODER_CHANNEL)
        log.info("beaglebone: encoders %s zeroed at %s counts (the neck must be straight now)",
                 self.config.encoder_channels, self._offset.astype(int).tolist())

    def _on_activate(self) -> None:
        # Each write that could drive checks the loop watchdog's latch just before it is made
        # (Driver.trip): a loop that wakes up in here after the trip enables nothing more.
        board, cfg = self._require_board(), self.config
        self._refuse_if_tripped("enable")
        board.motor.enable()
        for ch in cfg.motor_channels:  # zero current first, so enabling cannot jerk a cable
            board.motor.set(ch, self._zero_duty)
        for pin in cfg.enable_pins:
            self._refuse_if_tripped(f"enable line {pin}")
            self._set_enable(pin, True)

    def _on_deactivate(self) -> None:
        self._drives_off()

    def _on_close(self) -> None:
        self._drives_off()
        try:
            board = self._require_board()
            if board.motor is not None:
                board.motor.disable()
        except Exception:
            log.exception("beaglebone: could not put the motor outputs in standby")
        finally:
            board_lock.release(self._lock_fd)
            self._lock_fd = None

    def _on_read(self) -> np.ndarray:
        board, rad_per_count = self._require_board(), 2.0 * math.pi / self.counts_per_rev
        return np.array([sign * (float(board.encoder.get(ch)) - offset) * rad_per_count  # floats: every tick
                         for sign, ch, offset in zip(self._sign_list, self.config.encoder_channels,
                                                     self._offset_list, strict=True)])

    def _on_write(self, force_N: np.ndarray) -> np.ndarray:
        board, cfg = self._require_board(), self.config
        s, applied = self.set_values(force_N)
        for ch, value in zip(cfg.motor_channels, s):
            if self._tripped:  # the latch, before each set value (Driver.trip)
                self._refuse_if_tripped(f"motor output {ch}")
            board.motor.set(ch, float(cfg.duty_of(value)))
        return applied

    def _on_trip(self) -> None:
        # From the loop watchdog's thread, no lock: only writes that turn drives off, one library
        # call per line or output. A write of the loop's that lands between them (it passed its
        # latch check before the trip) is undone by the watchdog's second pass (Driver.trip).
        self._drives_off()

    # -- helpers -------------------------------------------------------------------------------
    def _drives_off(self) -> None:
        """Enable lines low first (the ESCON stops at once), then zero-current set values; every
        line is attempted even if one fails."""
        board, cfg = self._require_board(), self.config
        errors = []
        for pin in cfg.enable_pins:
            try:
                self._set_enable(pin, False)
            except Exception as exc:  # noqa: BLE001 - try every drive, then report all failures
                errors.append(f"enable pin {pin}: {exc}")
        motor = board.motor  # None when rcpy.motor failed to initialise: the lines off are what count
        for ch in cfg.motor_channels:
            if motor is None:
                break
            try:
                motor.set(ch, self._zero_duty)
            except Exception as exc:  # noqa: BLE001 - try every drive, then report all failures
                errors.append(f"motor output {ch}: {exc}")
        if errors:
            raise DriverError("beaglebone: could not disable every drive: " + "; ".join(errors))

    def _set_enable(self, pin: int, enabled: bool) -> None:
        """Write an enable line and read it back: the level read is what counts. rcpy versions
        disagree on librobotcontrol's return codes (docs/bridge.md, "Running on the BeagleBone
        Blue"): one raises on success (a set that worked looked failed, so no drive could be
        enabled and a drives-off reported failure), another is silent on failure (a drive left
        enabled looked off). :class:`DriverError` names the pin if the line does not read the
        level written; a write that raised while the line reads it is taken as done, warned once."""
        board, level = self._require_board(), self._level(enabled)
        raised: Exception | None = None
        try:
            board.gpio.set_value(pin, level)
        except Exception as exc:  # noqa: BLE001 - judged by the read-back below
            raised = exc
        read = board.gpio.get_value(pin)
        if read != level:
            raise DriverError(f"beaglebone: enable line {pin} reads {read} after writing {level}"
                              + (f" (rcpy raised: {raised})" if raised is not None else " (rcpy reported no error)"))
        if raised is not None and not self._warned_inverted:
            self._warned_inverted = True
            log.warning("beaglebone: rcpy.gpio.set_value(%s, %s) raised %r but the line reads %s: taken as done "
                        "(an rcpy that reads librobotcontrol's success code as a failure; docs/bridge.md)",
                        pin, level, raised, read)

    def _counts(self) -> np.ndarray:
        board = self._require_board()
        return np.array([float(board.encoder.get(ch)) for ch in self.config.encoder_channels])

    def _level(self, enabled: bool) -> int:
        return int(enabled == self.config.enable_active_high)

    def _require_board(self) -> _Board:
        if self._board is None:
            raise DriverError("beaglebone: the board is not open (configure() first)")
        return self._board


__all__ = ["BLUE_GP0_PINS", "ESCON_ANALOG_RANGE_V", "BeagleBoneConfig", "BeagleBoneDriver", "Transmission"]
