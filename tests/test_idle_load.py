"""The idle console costs next to nothing while nobody watches (issue 21: the idle `xneck up` stack
below 40 % of one core). Counts of work done, not speed: the live broadcaster reads no value and
the 3D view redraws at its idle rate while no browser is connected, and both go back to their
full rate as soon as one is (a real viser server and a real viser client over WebSocket)."""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time

import msgspec
import numpy as np
import viser
from busutil import wait_until
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from bridge import bus
from bridge.session import free_tcp_port, open_session
from server.live import SERIES, Broadcaster, LatestValues, LiveBus
from server.scene import NeckScene
from twin.model.params import load_params


def _status(seq: int, alpha_deg: tuple[float, float, float]) -> bytes:
    a = np.radians(alpha_deg).tolist()
    return bus.encode(bus.ControllerStatus(
        seq=seq, stamp_s=seq * 0.002, law="law2", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
        saturated=[False] * 4, alpha_hat_rad=a, alpha_d_rad=a, e_rad=[0.0] * 3, holding=False, hold_reason="",
        campaign_id="", ticks=seq))


def test_the_live_broadcaster_reads_nothing_until_a_client_connects() -> None:
    values = LatestValues()
    pulls = [0]

    def ring() -> None:  # a Zenoh ring that has nothing new: counts how often the console looks
        pulls[0] += 1

    values.add_source("status", ring)
    values.put_raw("status", _status(1, (1.0, 0.0, 0.0)))
    broadcaster = Broadcaster(values, rate_hz=100.0)

    async def scenario() -> tuple[int, int, int, int]:
        task = asyncio.create_task(broadcaster.run())
        await asyncio.sleep(0.3)  # 30 periods without a client
        idle = pulls[0]
        client = broadcaster.connect()
        first = await asyncio.wait_for(client.queue.get(), 5)  # the current state at once
        values.put_raw("status", _status(2, (2.0, 0.0, 0.0)))
        second = await asyncio.wait_for(client.queue.get(), 5)  # and the next change at the broadcast rate
        broadcaster.disconnect(client)
        await asyncio.sleep(0.05)
        after = pulls[0]
        await asyncio.sleep(0.3)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        assert b'"seq":1' in first and b'"seq":2' in second
        return idle, after, pulls[0], broadcaster.frames_sent

    idle, after, end, frames = asyncio.run(scenario())
    assert idle == 0  # no client: no snapshot, no decode
    assert end - after <= 1  # the last client gone: at most the period under way
    assert frames >= 2


def _viser_client(port: int, stop: threading.Event) -> threading.Thread:
    """A minimal viser browser: connects with the server's protocol version, sends its camera (a
    client counts as connected from its first camera message) and reads what it is sent."""
    ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol(f"viser-v{viser.__version__}")], open_timeout=10,
                 max_size=None)
    ws.send(msgspec.msgpack.encode({
        "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, 0.1, 0.6], "fov": 0.9,
        "near": 0.01, "far": 100.0, "image_height": 480, "image_width": 640, "look_at": [0.0, 0.1, 0.0],
        "up_direction": [0.0, 1.0, 0.0]}))

    def read() -> None:
        with ws, contextlib.suppress(ConnectionClosed):
            while not stop.is_set():
                with contextlib.suppress(TimeoutError):
                    ws.recv(timeout=0.1)

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return thread


def test_the_3d_view_redraws_at_its_idle_rate_without_a_viewer_and_follows_one_at_once() -> None:
    values = LatestValues()
    scene = NeckScene(values, load_params(), rate_hz=30.0)
    stop = threading.Event()
    seq = [0]

    def feed() -> None:  # the controller's status at 500 Hz: the values change all the time
        while not stop.is_set():
            seq[0] += 1
            values.put_raw("status", _status(seq[0], (15.0, 0.0, 0.0)))
            time.sleep(0.002)

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    client = None
    try:
        bent = scene.drawing.geometry(np.radians([15.0, 0.0, 0.0])).bars
        # Without a viewer the scene still follows the neck (a viewer that connects, and readers of
        # the handles, find it current), but at the idle rate.
        assert wait_until(lambda: np.abs(np.asarray(scene.bars.points) - bent).max() < 1e-6, 3 / 1.0, 0.05)
        before = scene.updates
        time.sleep(2.0)
        assert scene.updates - before <= 2.0 * 1.0 + 1
        client = _viser_client(scene.port, stop)
        assert wait_until(lambda: len(scene.server.get_clients()) == 1, 10, 0.02)
        before = scene.updates
        time.sleep(1.0)
        assert scene.updates - before > 3 * 1.0  # watched: the full rate (30 Hz when quiet)
    finally:
        stop.set()
        feeder.join(2)
        if client is not None:
            client.join(2)
        scene.close()


def test_the_view_only_series_are_taken_from_the_bus_only_while_a_viewer_watches() -> None:
    """The twin's truth and the commands (500 Hz each) are for browsers and the 3D view: while none
    is connected the console does not subscribe to them (the bridge then sends them to nobody); the
    series the console checks itself (the bridge's state, the controller's status) stay."""
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_session(listen=[hub], connect=[]) as a, open_session(connect=[hub]) as b:
        live = LiveBus(b)
        pubs = {name: a.declare_publisher(SERIES[name][0]) for name in ("state", "truth", "command")}
        truth = bus.encode(bus.Truth(seq=1, stamp_s=0.5, alpha_rad=[0.1, 0.0, 0.0], alpha_dot_rad_s=[0.0] * 3,
                                     theta_rad=[0.0] * 4, theta_dot_rad_s=[0.0] * 4, tension_N=[5.0] * 4,
                                     elongation_m=[0.0] * 4, slack=[False] * 4, near_singular=False))

        def matching(name: str) -> bool:  # a remote subscriber takes this key (a MatchingStatus; typed bool)
            return bool(getattr(pubs[name].matching_status, "matching"))  # noqa: B009

        try:
            assert wait_until(lambda: matching("state"), 10, 0.02)  # declared with the others at start
            assert not matching("truth") and not matching("command")
            live.values.watch("browser", True)
            assert wait_until(lambda: matching("truth") and matching("command"), 10, 0.02)

            def arrived() -> bool:
                pubs["truth"].put(truth)
                return live.values.get("truth") is not None

            assert wait_until(arrived, 10, 0.02)
            live.values.watch("3d view", True)
            live.values.watch("browser", False)  # one viewer left: still taken
            time.sleep(0.2)
            assert matching("truth") and live.values.get("truth") is not None
            live.values.watch("3d view", False)
            assert wait_until(lambda: not matching("truth") and not matching("command"), 10, 0.02)
            assert live.values.get("truth") is None  # no stale value kept for the next viewer
            assert matching("state")
        finally:
            for pub in pubs.values():
                pub.undeclare()
            live.close()


def test_browsers_and_the_3d_view_are_the_viewers() -> None:
    values = LatestValues()
    seen: list[bool] = []
    values.on_watched(seen.append)
    broadcaster = Broadcaster(values, rate_hz=30.0)

    async def clients() -> None:
        one, two = broadcaster.connect(), broadcaster.connect()
        broadcaster.disconnect(one)
        broadcaster.disconnect(two)

    asyncio.run(clients())
    assert seen == [True, False]
    scene = NeckScene(values, load_params())
    stop = threading.Event()
    try:
        client = _viser_client(scene.port, stop)
        assert wait_until(lambda: seen == [True, False, True], 10, 0.02)
        stop.set()
        client.join(2)
        assert wait_until(lambda: seen == [True, False, True, False], 10, 0.02)
    finally:
        stop.set()
        scene.close()
