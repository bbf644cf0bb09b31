"""Real console servers for tests: uvicorn on 127.0.0.1 and a free port, in a thread or in a
subprocess (the latter can be killed like a crashed server). Everything stops within bounded time."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import uvicorn
from busutil import wait_until  # re-exported for the server tests
from websockets.sync.client import connect

from bridge.session import free_tcp_port
from server.app import create_app
from server.routes_live import WS_MAX_BYTES
from server.settings import Settings

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def stop_xneck_up(up: subprocess.Popen) -> None:
    """Stop an ``xneck up`` started with ``start_new_session``: SIGTERM to the supervisor alone (it
    stops its children in the safe order), SIGKILL to its whole group if it has not ended in 40 s."""
    if up.poll() is not None:
        return
    up.send_signal(signal.SIGTERM)
    try:
        up.wait(40)
    except subprocess.TimeoutExpired:
        os.killpg(up.pid, signal.SIGKILL)
        up.wait(10)


def stop_process_groups(started: list[subprocess.Popen]) -> None:
    """SIGTERM to each process group started (``start_new_session``), newest first; SIGKILL to
    any still there 10 s later: what a stack's test leaves behind is gone within bounded time."""
    for p in reversed(started):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
    for p in reversed(started):
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(5)


@contextlib.contextmanager
def running_server(data_dir: Path, **overrides) -> Iterator[tuple[str, object]]:
    """A console in this process (uvicorn.Server in a thread); yields (base URL, app). uvicorn binds
    127.0.0.1 even when ``host`` says otherwise: the settings' host only sets the console's policy.
    The viser view binds the settings' host, so another host needs ``viser=False`` (tests bind
    127.0.0.1 only)."""
    host = overrides.get("host", "127.0.0.1")
    if host not in ("127.0.0.1", "localhost", "::1") and overrides.get("viser", True):
        raise ValueError(f"running_server(host={host!r}) would open the viser view there: pass viser=False")
    port = free_tcp_port()
    settings = Settings(**{"host": "127.0.0.1", "port": port, "data_dir": data_dir, "token": TOKEN, "pace": "lockstep",
                           "campaign_timeout_s": 120, **overrides})
    app = create_app(settings)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                                           ws_ping_interval=None, ws_max_size=WS_MAX_BYTES,  # as xneck server
                                           timeout_graceful_shutdown=5))
    thread = threading.Thread(target=server.run, name="uvicorn-test", daemon=True)
    thread.start()
    try:
        if not wait_until(lambda: server.started, 30):
            raise RuntimeError("the console did not start within 30 s")
        yield f"http://127.0.0.1:{port}", app
    finally:
        server.should_exit = True
        thread.join(40)
        assert not thread.is_alive(), "uvicorn did not stop within 40 s"


@contextlib.contextmanager
def server_process(data_dir: Path) -> Iterator[tuple[str, subprocess.Popen]]:
    """``xneck server`` as a subprocess leading its own process group (so the twin and controller
    it spawns can be killed with it, as a crash would). Yields (base URL, process)."""
    port = free_tcp_port()
    env = {**os.environ, "XNECK_TOKEN": TOKEN, "XNECK_CAMPAIGN_TIMEOUT_S": "120", "PYTHONUNBUFFERED": "1"}
    log = open(Path(data_dir).parent / f"server-{port}.log", "wb")  # noqa: SIM115 - the server's stdout while it runs
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "server", "--port", str(port), "--data-dir", str(data_dir),
         "--pace", "lockstep"], stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
        start_new_session=True)
    base = f"http://127.0.0.1:{port}"

    def up() -> bool:
        try:
            return httpx.get(base + "/api/system/health", timeout=1).status_code == 200
        except httpx.HTTPError:
            return False

    try:
        if not wait_until(up, 40, 0.2):
            raise RuntimeError(f"xneck server did not start: {Path(log.name).read_text()[-2000:]}")
        yield base, proc
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
        log.close()


def start_campaign(client: httpx.Client, body: dict | None = None, progress: float = 0.0,
                   timeout_s: float = 60) -> str:
    """POST a campaign (a 201 is asserted), wait until its progress reaches ``progress``; its id."""
    r = client.post("/api/campaigns", json=body if body is not None else {"kind": "control", "law": 2},
                    headers=AUTH)
    assert r.status_code == 201, r.text
    cid = r.json()["id"]
    assert wait_until(lambda: client.get(f"/api/campaigns/{cid}").json()["progress"] >= progress, timeout_s, 0.2)
    return cid


class LiveSocket:
    """The console's live WebSocket (``/api/live``) read in a thread: :meth:`on_frame` gets every
    frame as it came (a test's subclass keeps what it checks); :meth:`close` within 3 s."""

    def __init__(self, base: str) -> None:
        self._stop = threading.Event()
        self._ws = connect(base.replace("http", "ws") + "/api/live", open_timeout=5)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def on_frame(self, frame: dict[str, Any]) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                raw = self._ws.recv(timeout=0.5)
            except TimeoutError:
                continue
            except Exception:  # noqa: BLE001 - closed
                return
            self.on_frame(json.loads(raw))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(3)
        self._ws.close()
