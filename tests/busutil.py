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
