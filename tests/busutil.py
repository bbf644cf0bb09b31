"""Helpers for tests on a real Zenoh bus over loopback."""

from __future__ import annotations

import contextlib
import threading
import time

from bridge.session import free_tcp_port, open_session


@contextlib.contextmanager
def bus_pair():
    """Two peer sessions on 127.0.0.1: (hub endpoint, hub session, factory for more sessions)."""
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as a:
        opened = []

        def connect():
            s = open_session(listen=["tcp/127.0.0.1:0"], connect=[hub])
            opened.append(s)
            return s

        try:
            yield hub, a, connect
        finally:
            for s in opened:
                s.close()


def run_in_thread(target, *args) -> tuple[threading.Thread, dict]:
    out: dict = {}

    def wrapper():
        try:
            out["result"] = target(*args)
        except BaseException as exc:  # noqa: BLE001 - reported to the test
            out["error"] = exc

    th = threading.Thread(target=wrapper, daemon=True)
    th.start()
    return th, out


def wait_until(predicate, timeout_s: float = 5.0, period_s: float = 0.01) -> bool:
    """Poll ``predicate`` until it holds or ``timeout_s`` passes; its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period_s)
    return bool(predicate())


def controller_status(campaign_id: str = "", alpha_hat_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> bytes:
    """An encoded ``ControllerStatus`` of a law-2 controller (a stand-in's, for the console)."""
    from bridge import bus

    return bus.encode(bus.ControllerStatus(
        seq=1, stamp_s=1.0, law="law2", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
        saturated=[False] * 4, alpha_hat_rad=list(alpha_hat_rad), alpha_d_rad=[0.0] * 3, e_rad=[0.0] * 3,
        holding=False, campaign_id=campaign_id))


def bridge_state(owner: str, epoch: str = "e-test", bridge: str = "b-test") -> bytes:
    """An encoded active ``MotorState`` of a bridge that obeys ``owner``."""
    from bridge import bus

    return bus.encode(bus.MotorState(seq=1, stamp_s=1.0, theta_rad=[0.0] * 4, force_applied_N=[10.0] * 4,
                                     drive="active", epoch=epoch, bridge=bridge, owner=owner))


@contextlib.contextmanager
def repeating(step, period_s: float):
    """While inside: ``step()`` every ``period_s`` in a daemon thread (a bridge's ticks, a peer's
    messages), stopped and joined on the way out."""
    quiet = threading.Event()

    def loop() -> None:
        while not quiet.is_set():
            step()
            time.sleep(period_s)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    try:
        yield
    finally:
        quiet.set()
        th.join(5)


def two_controllers(peer, state: bytes, owner: bytes, other: bytes, period_s: float = 0.01):
    """While inside: every ``period_s`` the bridge's ``state``, then the status of ``ctl-owner``
    and the status of ``ctl-other`` after it (each named by its attachment), published by ``peer``."""
    from bridge import bus
    from bridge.session import controller_attachment

    def send() -> None:
        peer.put(bus.MOTOR_STATE, state)
        peer.put(bus.CONTROLLER_STATUS, owner, attachment=controller_attachment("ctl-owner"))
        peer.put(bus.CONTROLLER_STATUS, other, attachment=controller_attachment("ctl-other"))

    return repeating(send, period_s)
