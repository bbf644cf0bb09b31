"""The motor driver interface of the bridge: one class and one typed config per device.

A driver owns the motor hardware (or its stand-in) and nothing else: it reads the motor shaft
angles and applies cable forces. Safety (clamping, watchdog, e-stop) lives in
:class:`bridge.node.BridgeNode`, above every driver, so it is the same for the robot, the twin and
a replay.

Lifecycle (after ROS 2 managed nodes, reduced to what a motor driver needs)::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
                                   ^   |                      |
                                   |   +------close()----+    |
                                   +----deactivate()-----|----+
                                                         v
                                                       CLOSED

- ``INACTIVE``: the hardware is open, the encoders are readable, the drives are disabled;
  :meth:`Driver.write` raises.
- ``ACTIVE``: the drives are enabled and follow :meth:`Driver.write`.
- :meth:`Driver.close` disables the drives from any state and may be called any number of times;
  it must not raise, because it runs on the way out of a crash.
- :meth:`Driver.trip` disables the drives from another thread while the loop may be hung, and
  latches them off for good (the loop watchdog, :mod:`bridge.loop_watchdog`).

Units: angles in rad at the motor shaft, forces in N along the cable, one value per motor in the
motor order of the parameter file.
"""

from __future__ import annotations

import abc
import enum
import logging
import math
import threading
import time
from typing import TypeVar

import msgspec
import numpy as np

from bridge import bus

log = logging.getLogger("xneck.bridge")


class Lifecycle(enum.Enum):
    UNCONFIGURED = "unconfigured"
    INACTIVE = "inactive"
    ACTIVE = "active"
    CLOSED = "closed"


class DriverError(RuntimeError):
    """A driver cannot do what was asked (wrong lifecycle state, missing library, bad hardware
    reply); the message says why in words fit for an operator."""


#: Hz: the loop rates a driver may run at. The bridge turns its command timeout and ramps into
#: ticks at this rate: at 20 kHz the watchdog waited 200 states and most ticks overran, at 100 kHz
#: the loop never slept (on the board's one core, at FIFO priority, above its bus threads), at
#: 1 MHz the loop watchdog tripped (audit of 2026-11-28, a `rate_hz` in escon.toml).
RATE_HZ_RANGE = (50.0, 2000.0)


class DriverConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Base of every driver's configuration: typed, immutable, validated on construction.

    ``n_motors`` is the number of motors the driver exposes (4 on the 3-X prototype).
    ``rate_hz`` is the tick rate the driver is meant to run at (the bridge's loop rate).
    Subclasses validate their own fields in ``__post_init__`` and raise ``ValueError`` naming the
    field; :func:`config_from_dict` turns that into a :class:`DriverError`.
    """

    n_motors: int = 4
    rate_hz: float = 500.0

    def __post_init__(self) -> None:
        if self.n_motors < 1:
            raise ValueError(f"n_motors must be >= 1, got {self.n_motors}")
        if not (math.isfinite(self.rate_hz) and RATE_HZ_RANGE[0] <= self.rate_hz <= RATE_HZ_RANGE[1]):
            raise ValueError(f"rate_hz must be within [{RATE_HZ_RANGE[0]:g}, {RATE_HZ_RANGE[1]:g}] Hz (the controller's "
                             f"500 Hz by default), got {self.rate_hz}")
        for name in self.__struct_fields__:
            value = getattr(self, name)
            values = value if isinstance(value, tuple) else (value,)
            if any(isinstance(v, float) and not math.isfinite(v) for v in values):
                raise ValueError(f"{name} must be finite, got {value}")

    def per_motor(self, name: str, values: tuple) -> None:
        """Check that field ``name`` has one value per motor."""
        if len(values) != self.n_motors:
            raise ValueError(f"{name} has {len(values)} values, expected one per motor (n_motors = {self.n_motors})")


ConfigT = TypeVar("ConfigT", bound=DriverConfig)


def config_from_dict(config_type: type[ConfigT], data: dict) -> ConfigT:
    """A driver config from plain data (a TOML table), or a :class:`DriverError` naming the key."""
    try:
        return msgspec.convert(data, config_type, strict=False)
    except (msgspec.ValidationError, ValueError) as exc:
        message = str(exc)
        if " - at `$" in message:  # 'reason - at `$.key`' -> 'key: reason'
            reason, at = message.rsplit(" - at `$", 1)
            message = f"{at.rstrip('`').lstrip('.')}: {reason}"
        raise DriverError(f"{config_type.__name__}: {message}") from None


class Driver(abc.ABC):
    """Base of the motor drivers (module docstring). Subclasses implement the ``_on_*`` hooks;
    the public methods enforce the lifecycle, so no driver can drive from the wrong state.

    Thread safety: the bridge calls a driver from its loop thread only, except :meth:`close`,
    which may also come from an ``atexit`` hook (a lock serialises the transitions), and
    :meth:`trip`, which comes from the loop watchdog's thread while the loop may be hung
    anywhere, inside a transition too: it takes no lock.
    """

    #: Short name used on the command line and in logs.
    name: str = "driver"

    def __init__(self, config: DriverConfig) -> None:
        self.config = config
        self._state = Lifecycle.UNCONFIGURED
        self._lock = threading.RLock()
        self._tripped = False
        #: Why the last :meth:`close` could not disable every drive ('' if it could): close never
        #: raises, so a caller that reports the drives off must look here first.
        self.close_error = ""

    @property
    def state(self) -> Lifecycle:
        return self._state

    @property
    def tripped(self) -> bool:
        """True once :meth:`trip` was called: the drives stay off for good."""
        return self._tripped

    @property
    def n_motors(self) -> int:
        return self.config.n_motors

    @property
    def dt(self) -> float:
        """Tick period (s)."""
        return 1.0 / self.config.rate_hz

    # -- lifecycle ---------------------------------------------------------------------------
    def configure(self) -> None:
        """Open the hardware: encoders readable, drives disabled. UNCONFIGURED -> INACTIVE."""
        with self._lock:
            self._expect("configure", Lifecycle.UNCONFIGURED)
            self._on_configure()
            self._state = Lifecycle.INACTIVE

    def activate(self) -> None:
        """Enable the drives. INACTIVE -> ACTIVE (no-op when already ACTIVE)."""
        with self._lock:
            if self._state is Lifecycle.ACTIVE:
                return
            self._expect("activate", Lifecycle.INACTIVE)
            self._refuse_if_tripped("activate")
            try:
                self._on_activate()
            except BaseException:
                # Half-enabled is the worst state: INACTIVE promises the drives are off, and the
                # lines already raised would stay high (audit of 2026-11-26). Off again first.
                try:
                    self._on_deactivate()
                except Exception:
                    log.exception("%s: error while disabling the drives after a failed enable", self.name)
                raise
            self._state = Lifecycle.ACTIVE

    def deactivate(self) -> None:
        """Disable the drives; the encoders stay readable. ACTIVE -> INACTIVE (no-op when
        already INACTIVE)."""
        with self._lock:
            if self._state is Lifecycle.INACTIVE:
                return
            self._expect("deactivate", Lifecycle.ACTIVE)
            # The state changes first: even if the hardware call fails half-way, nothing may
            # believe the drives are still enabled and keep writing to them.
            self._state = Lifecycle.INACTIVE
            self._on_deactivate()

    def close(self) -> None:
        """Disable the drives and release the hardware, from any state. Never raises: a failure is
        logged and kept in :attr:`close_error`."""
        with self._lock:
            if self._state is Lifecycle.CLOSED:
                return
            was = self._state
            self._state = Lifecycle.CLOSED
            try:
                if was is not Lifecycle.UNCONFIGURED:
                    self._on_close()
            except Exception as exc:  # close runs on the way out of a crash
                self.close_error = f"{type(exc).__name__}: {exc}"
                log.exception("%s: error while closing the driver", self.name)

    def trip(self) -> str:
        """Disable the drives now, from any thread, and for good: the loop watchdog's way out of a
        hung loop (:mod:`bridge.loop_watchdog`). No lock is taken (the hung loop may hold it, in
        the middle of a transition or a write). The latch is set first: from then on
        :meth:`activate` and :meth:`write` refuse, and a driver's own hardware writes that would
        drive check it before each call (:meth:`_refuse_if_tripped`), so a loop that wakes up
        cannot enable or drive again; a write already past its check when the latch was set can
        still land, which a second call undoes. The lifecycle state is left as it is (the loop
        may be changing it). Callable any number of times; never raises: returns '' or why not
        every drive could be disabled."""
        self._tripped = True
        if self._state is Lifecycle.UNCONFIGURED:
            return ""  # nothing opened, nothing driven
        try:
            self._on_trip()
        except Exception as exc:  # noqa: BLE001 - reported to the caller, which exits the process either way
            return f"{type(exc).__name__}: {exc}"
        return ""

    def _refuse_if_tripped(self, what: str) -> None:
        """Raise if :meth:`trip` was called: for every hardware write that could drive."""
        if self._tripped:
            raise DriverError(f"{self.name}: {what} refused, the loop watchdog tripped the drives off for good")

    # -- I/O ---------------------------------------------------------------------------------
    def read(self) -> np.ndarray:
        """Motor shaft angles θ (rad), shape (n_motors,). INACTIVE or ACTIVE."""
        if self._state not in (Lifecycle.INACTIVE, Lifecycle.ACTIVE):
            raise DriverError(f"{self.name}: read() needs a configured driver, it is {self._state.value}")
        return self._on_read()

    def write(self, force_N: np.ndarray) -> np.ndarray:
        """Apply cable forces (N), shape (n_motors,); returns the forces actually applied after
        the device's own limits (e.g. the current limit of the motor controller). ACTIVE only:
        the caller has already validated and clamped ``force_N``."""
        if self._state is not Lifecycle.ACTIVE or self._tripped:
            self._refuse_if_tripped("write()")
            raise DriverError(f"{self.name}: write() refused, the drives are {self._state.value} (activate first)")
        f = np.asarray(force_N, dtype=float)
        # On plain floats: numpy's reduction costs more than the rest of a bridge tick (issue 20).
        if f.shape != (self.n_motors,) or not all(map(math.isfinite, f.tolist())):
            raise DriverError(f"{self.name}: write() needs {self.n_motors} finite forces (N), got {f.tolist()}")
        return self._on_write(f)

    def step(self) -> None:  # noqa: B027 - an optional hook, not abstract: hardware has nothing to do
        """Advance one tick. Simulated devices integrate here; hardware does nothing."""

    def stamp_s(self) -> float:
        """Time stamp of the last :meth:`read` (s): wall clock for hardware, simulated time for the twin."""
        return time.time()

    def steady_s(self) -> float:
        """A steady time of the last :meth:`read` (s), for the time between reads (the motors'
        speeds): monotonic for hardware, whose :meth:`stamp_s` is the wall clock (NTP steps it; a
        board without an RTC battery may boot before its clock is set), simulated time for the twin."""
        return time.monotonic()

    def extra_messages(self) -> list[tuple[str, bus.BusMessage]]:
        """Messages besides ``MotorState`` produced by the last step (the twin's ``Truth`` and
        camera frames); ``(key, message)`` pairs with their own ``seq``. Hardware: none."""
        return []

    @property
    def exhausted(self) -> bool:
        """True when the device has nothing more to give (end of a replay); the bridge stops."""
        return False

    def _expect(self, what: str, *states: Lifecycle) -> None:
        if self._state not in states:
            allowed = " or ".join(s.value for s in states)
            raise DriverError(f"{self.name}: {what}() needs the driver {allowed}, it is {self._state.value}")

    # -- device hooks ------------------------------------------------------------------------
    @abc.abstractmethod
    def _on_configure(self) -> None: ...

    @abc.abstractmethod
    def _on_activate(self) -> None: ...

    @abc.abstractmethod
    def _on_deactivate(self) -> None: ...

    @abc.abstractmethod
    def _on_close(self) -> None: ...

    @abc.abstractmethod
    def _on_read(self) -> np.ndarray: ...

    @abc.abstractmethod
    def _on_write(self, force_N: np.ndarray) -> np.ndarray: ...

    def _on_trip(self) -> None:
        """Every drive off, from another thread than the loop's, without the lock (:meth:`trip`).
        Default: :meth:`_on_deactivate`, which must then be safe to call that way (the twin's
        and the replay's are); a hardware driver overrides it if it is not."""
        self._on_deactivate()

    def __enter__(self) -> Driver:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


__all__ = ["Driver", "DriverConfig", "DriverError", "Lifecycle", "config_from_dict"]
