"""Replay of a recorded campaign as a motor driver: the archived ``MotorState`` angles, one per tick.

States only: :meth:`write` is accepted (so a controller can run against a replay) and ignored; the
forces reported are the archived ``force_applied_N`` of the state being replayed. Useful to test
the console, the recorder and a controller's estimator offline against real encoder data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bridge import bus
from bridge.driver import Driver, DriverConfig, DriverError


class ReplayConfig(DriverConfig, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``path`` of a finished campaign MCAP file; ``loop``: start over at the end instead of stopping."""

    path: str
    loop: bool = False


class ReplayDriver(Driver):
    name = "replay"

    def __init__(self, config: ReplayConfig) -> None:
        super().__init__(config)
        self.config: ReplayConfig = config
        self._theta = np.zeros((0, config.n_motors))
        self._force = np.zeros((0, config.n_motors))
        self._k = 0
        self._started = False

    def _on_configure(self) -> None:
        from bridge.archive import ArchiveError
        from bridge.archive_read import read_campaign

        try:
            campaign = read_campaign(Path(self.config.path), keys=(bus.MOTOR_STATE,))
        except ArchiveError as exc:
            raise DriverError(f"replay: {exc}") from None
        states = [m for _, m in campaign.messages(bus.MOTOR_STATE) if isinstance(m, bus.MotorState)]
        if not states:
            raise DriverError(f"replay: {self.config.path} holds no {bus.MOTOR_STATE} messages")
        n = self.n_motors
        bad = next((s for s in states if len(s.theta_rad) != n or len(s.force_applied_N) != n), None)
        if bad is not None:
            raise DriverError(f"replay: {self.config.path} has states with {len(bad.theta_rad)} motors, expected {n}")
        self._theta = np.array([s.theta_rad for s in states], dtype=float)
        self._force = np.array([s.force_applied_N for s in states], dtype=float)
        self._k, self._started = 0, False

    def _on_activate(self) -> None:
        pass

    def _on_deactivate(self) -> None:
        pass

    def _on_close(self) -> None:
        pass

    def _on_read(self) -> np.ndarray:
        return self._theta[self._k].copy()

    def _on_write(self, force_N: np.ndarray) -> np.ndarray:
        return self._force[self._k].copy()

    def step(self) -> None:
        """The first period shows the first state; each later one the next state."""
        if not self._started:
            self._started = True
        elif self._k + 1 < len(self._theta):
            self._k += 1
        elif self.config.loop:
            self._k = 0

    @property
    def exhausted(self) -> bool:
        """True once the last state has been stepped to (the bridge stops after publishing it)."""
        return not self.config.loop and self._started and self._k == len(self._theta) - 1


__all__ = ["ReplayConfig", "ReplayDriver"]
