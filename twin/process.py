"""The twin as a bus process (`xneck twin`): it speaks exactly the bridge's topics.

Publishes ``MotorState`` (encoder angles and applied forces) every tick, ``CameraAlpha`` frames
at 30 Hz, the twin-only ``Truth`` every tick and ``Health`` about once per second; obeys valid
``ForceCommand``s. Malformed or out-of-range commands (bad JSON, wrong schema version, NaN,
wrong length, a force below 0 or above f_max) are rejected with a logged reason and counted by
:class:`bridge.session.LatestSubscriber`; they never move the twin.

Two modes:
- real time: ticks paced by the clock at 500 Hz with the latest valid command held; a tick that
  starts late is an overrun, counted and reported in ``Health``;
- lockstep: one tick per new valid command, as fast as the controller goes; deterministic for a
  seed (the simulation depends only on the sequence of commands). While it waits, the twin
  re-publishes its current state every 50 ms so a controller that starts later still sees it.
"""

from __future__ import annotations

import gc
import logging
import math
import sys
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np
import zenoh

from bridge import bus
from bridge.session import liveliness_token, publisher, subscribe_latest
from twin.params import Params
from twin.sim import Tick, Twin, TwinConfig

log = logging.getLogger("xneck.twin")


@dataclass(frozen=True)
class TwinProcessConfig:
    lockstep: bool = False
    max_ticks: int | None = None  # stop after this many ticks (None: run until stopped)
    idle_timeout_s: float | None = None  # lockstep: stop when no command came for this long
    startup_timeout_s: float | None = None  # lockstep: the limit before the first command (default: idle's)
    republish_s: float = 0.05  # lockstep: re-publish the waiting state this often (wall clock)
    instance: str = ""


def _check_command(n_motors: int, f_max: float):
    def check(cmd: bus.ForceCommand) -> None:
        bus.check_force_command(cmd, n_motors, 0.0, f_max)

    return check


class TwinNode:
    """The twin bound to a Zenoh session: one :meth:`publish` per tick and the command input."""

    def __init__(self, session: zenoh.Session, params: Params, twin_config: TwinConfig, config: TwinProcessConfig):
        self.twin = Twin(params, twin_config)
        self.config = config
        self.instance = config.instance or f"twin-{uuid.uuid4().hex[:6]}"
        nc = self.twin.model.n_cables
        self.commands = subscribe_latest(session, bus.MOTOR_COMMAND, validate=_check_command(nc, params.limits.f_max))
        self._state = publisher(session, bus.MOTOR_STATE)
        self._camera = publisher(session, bus.CAMERA_ALPHA)
        self._truth = publisher(session, bus.TWIN_TRUTH)
        self._health = session.declare_publisher(bus.health_key("twin", self.instance))
        self._token = liveliness_token(session, "twin", self.instance)
        self.force = np.zeros(nc)
        self.overruns = 0
        self.flat_refusals = 0
        self._slack = np.zeros(nc, dtype=bool)
        self._seq = {"state": 0, "camera": 0, "truth": 0, "health": 0}
        self._started = time.monotonic()
        self.last_tick: Tick | None = None

    def _next(self, name: str) -> int:
        self._seq[name] += 1
        return self._seq[name]

    def publish_state(self, drive: str) -> None:
        tick = self.last_tick
        t_s = tick.t_s if tick else 0.0
        theta = tick.theta_meas if tick else self.twin.theta
        self._state.put(bus.MotorState(seq=self._next("state"), stamp_s=t_s, theta_rad=theta.tolist(),
                                       force_applied_N=self.force.tolist(), drive=drive))

    def step(self, force: np.ndarray) -> Tick:
        self.force = force
        tick = self.twin.tick(force)
        self.last_tick = tick
        if tick.flat:
            self.flat_refusals += 1
            log.warning("t = %.3f s: a joint reached its flat singularity (α = %s°); step refused",
                        tick.t_s, np.round(np.degrees(tick.alpha), 1).tolist())
        if np.any(tick.slack != self._slack):
            log.info("t = %.3f s: slack cables %s", tick.t_s, (np.nonzero(tick.slack)[0] + 1).tolist())
            self._slack = tick.slack
        for capture, alpha_ip in tick.frames:
            self._camera.put(bus.CameraAlpha(seq=self._next("camera"), stamp_s=tick.t_s,
                                             alpha_ip_rad=alpha_ip.tolist(), capture_stamp_s=capture))
        self._truth.put(bus.Truth(
            seq=self._next("truth"), stamp_s=tick.t_s, alpha_rad=tick.alpha.tolist(),
            alpha_dot_rad_s=tick.alpha_dot.tolist(), theta_rad=tick.theta.tolist(),
            theta_dot_rad_s=tick.theta_dot.tolist(), tension_N=tick.tension.tolist(),
            elongation_m=tick.elongation.tolist(), slack=tick.slack.tolist(), near_singular=tick.near_singular))
        return tick

    def publish_health(self) -> None:
        stats = self.commands.stats
        self._health.put(bus.encode(bus.Health(
            seq=self._next("health"), stamp_s=self.last_tick.t_s if self.last_tick else 0.0, process="twin",
            instance=self.instance, uptime_s=time.monotonic() - self._started,
            received={bus.MOTOR_COMMAND: stats.received, "overruns": self.overruns, "flat_refusals": self.flat_refusals},
            rejected={bus.MOTOR_COMMAND: stats.rejected}, last_reject_reason=stats.last_reject_reason)))

    def close(self) -> None:
        for closer in (self.commands.close, self._state.close, self._camera.close, self._truth.close,
                       self._health.undeclare, self._token.undeclare):
            try:
                closer()
            except Exception:  # noqa: BLE001 - closing a half-dead session must not mask the cause
                pass


def run_lockstep(node: TwinNode, stop: threading.Event) -> int:
    """One tick per new valid command. Returns the number of ticks run."""
    cfg = node.config
    last_seq = None
    ticks = 0
    idle_since = time.monotonic()
    node.publish_state("inactive")
    while not stop.is_set() and (cfg.max_ticks is None or ticks < cfg.max_ticks):
        cmd = node.commands.wait(cfg.republish_s, lambda c: c.seq != last_seq)
        if cmd is None or cmd.seq == last_seq:
            limit = cfg.idle_timeout_s
            if last_seq is None and cfg.startup_timeout_s is not None:
                limit = cfg.startup_timeout_s
            if limit is not None and time.monotonic() - idle_since > limit:
                log.info("no command for %.1f s: stopping", limit)
                break
            node.publish_state("inactive" if last_seq is None else "active")
            continue
        last_seq, idle_since = cmd.seq, time.monotonic()
        node.step(np.asarray(cmd.force_N))
        ticks += 1
        node.publish_state("active")
        if ticks % 500 == 0:
            node.publish_health()
    node.publish_health()
    return ticks


def run_realtime(node: TwinNode, stop: threading.Event) -> int:
    """Ticks paced by the clock; the latest valid command is held between commands."""
    cfg, dt = node.config, node.twin.dt
    ticks = 0
    gc.collect()
    gc.freeze()  # long-lived objects out of the collector's way: no full collection mid-tick
    sys.setswitchinterval(0.0005)  # Zenoh callback threads share the GIL: hand it over quickly
    start = time.perf_counter()
    next_health = start + 1.0
    while not stop.is_set() and (cfg.max_ticks is None or ticks < cfg.max_ticks):
        cmd = node.commands.latest()
        node.step(np.asarray(cmd.force_N) if cmd is not None else np.zeros_like(node.force))
        ticks += 1
        node.publish_state("active" if cmd is not None else "inactive")
        now = time.perf_counter()
        deadline = start + ticks * dt
        if now > deadline + dt:
            node.overruns += 1
            start += math.floor((now - deadline) / dt) * dt  # skip, do not try to catch up
        elif now < deadline:
            time.sleep(deadline - now)
        if now >= next_health:
            node.publish_health()
            next_health = now + 1.0
    node.publish_health()
    return ticks
