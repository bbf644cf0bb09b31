"""Limits of the console's live endpoints (review of session 53): a cap on live clients, refused
with a close code and its reason, and on what a WebSocket client may send (the console ignores it
all; uvicorn read and decoded up to 16 MB of it first). A real server on 127.0.0.1."""

from __future__ import annotations

import json

import httpx
import pytest
from server_harness import running_server, wait_until
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect
from websockets.sync.connection import Connection

from bridge import bus
from server.live import LIVE_MAX_CLIENTS
from server.routes_live import LIVE_FULL_CLOSE_CODE


@pytest.fixture(scope="module")
def console(tmp_path_factory):
    with running_server(tmp_path_factory.mktemp("live-limits") / "data", viser=False) as (base, app):
        yield base, app


def _open(base: str) -> ClientConnection:
    return connect(base.replace("http", "ws") + "/api/live", open_timeout=5, close_timeout=1)


def _frame_with(ws: Connection, reason: str) -> bool:
    """Whether ``ws`` gets a live frame whose e-stop series says ``reason`` (older frames skipped)."""
    for _ in range(50):
        frame = json.loads(ws.recv(timeout=5))
        if frame["series"].get("estop", {}).get("reason") == reason:
            return True
    return False


def test_a_live_client_beyond_the_cap_is_refused_with_the_reason(console) -> None:
    """The (cap+1)th WebSocket is accepted and closed at once, 1013 and why; an SSE client gets a
    503; once one leaves a new one is served again."""
    base, app = console
    broadcaster = app.state.broadcaster
    opened = []
    try:
        for _ in range(LIVE_MAX_CLIENTS):
            opened.append(_open(base))
        assert wait_until(lambda: len(broadcaster.clients) == LIVE_MAX_CLIENTS, 10), len(broadcaster.clients)
        extra = _open(base)
        with pytest.raises(ConnectionClosed) as closed:
            extra.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == LIVE_FULL_CLOSE_CODE, closed.value
        assert f"at most {LIVE_MAX_CLIENTS} live clients" in closed.value.rcvd.reason, closed.value.rcvd
        with httpx.stream("GET", base + "/api/live/sse", timeout=10) as r:
            assert r.status_code == 503 and "live clients" in r.read().decode(), r.status_code
        assert len(broadcaster.clients) == LIVE_MAX_CLIENTS
        opened.pop().close()
        assert wait_until(lambda: len(broadcaster.clients) < LIVE_MAX_CLIENTS, 10)
        opened.append(_open(base))
        app.state.live.values.put("estop", bus.EStop(seq=1, stamp_s=1.0, engaged=False, reason="served again"))
        assert _frame_with(opened[-1], "served again")
    finally:
        for ws in opened:
            ws.close()
    assert wait_until(lambda: not broadcaster.clients, 10)


def test_a_large_client_message_closes_that_client_alone(console) -> None:
    """A 100 kB message from a client (uvicorn read up to 16 MB, the console ignores them) closes
    that connection (1009, too big); another client keeps its frames."""
    base, app = console
    with _open(base) as quiet, _open(base) as loud:
        loud.send("x" * 100_000)
        with pytest.raises(ConnectionClosed) as closed:
            for _ in range(50):  # any frame queued before the close
                loud.recv(timeout=10)
        assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009, closed.value
        quiet.send("a small message, ignored")
        app.state.live.values.put("estop", bus.EStop(seq=2, stamp_s=2.0, engaged=False, reason="still live"))
        assert _frame_with(quiet, "still live")
        assert wait_until(lambda: len(app.state.broadcaster.clients) == 1, 10)
