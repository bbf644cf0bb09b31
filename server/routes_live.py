"""Live data for browsers: WebSocket ``/api/live`` and SSE ``/api/live/sse`` (same frames,
see :mod:`server.live`). Each connection reads its own bounded queue; nothing here can block
the bus or another client."""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import APIRouter, HTTPException, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import StreamingResponse

from server.live import LiveFull

router = APIRouter(tags=["live"])

KEEPALIVE_S = 15.0
#: A WebSocket message a client may send at most (uvicorn's ``ws_max_size``: server.cli.serve and
#: the tests' harness): the console ignores them all, and uvicorn's default of 16 MB was read and
#: decoded first; a larger one closes that client with 1009 (review of session 53).
WS_MAX_BYTES = 4096
#: The close code of a client refused because :data:`server.live.LIVE_MAX_CLIENTS` are connected
#: (1013, "try again later"), its reason saying so.
LIVE_FULL_CLOSE_CODE = 1013


@router.websocket("/api/live")
async def live_ws(ws: WebSocket) -> None:
    """Live frames as JSON text messages (see :mod:`server.live`); anything the browser sends is
    ignored (at most :data:`WS_MAX_BYTES` a message: a larger one closes the connection, 1009).
    Beyond :data:`server.live.LIVE_MAX_CLIENTS` live clients a new one is accepted and closed at
    once with :data:`LIVE_FULL_CLOSE_CODE` and the reason (review of session 53)."""
    await ws.accept()
    broadcaster = ws.app.state.broadcaster
    try:
        client = broadcaster.connect()
    except LiveFull as exc:  # accepted first: a refused handshake carries no reason a browser sees
        await ws.close(LIVE_FULL_CLOSE_CODE, str(exc))
        return

    async def until_disconnect() -> None:
        # Without a pending receive a closed socket goes unnoticed while no frame is due.
        while (await ws.receive())["type"] != "websocket.disconnect":
            pass

    closed = asyncio.create_task(until_disconnect())
    try:
        while True:
            get = asyncio.create_task(client.queue.get())
            done, _ = await asyncio.wait({get, closed}, return_when=asyncio.FIRST_COMPLETED)
            if closed in done:
                get.cancel()
                break
            await ws.send_text(get.result().decode())
    except (WebSocketDisconnect, RuntimeError, ConnectionError):
        pass
    finally:
        closed.cancel()
        broadcaster.disconnect(client)
        with contextlib.suppress(Exception):
            await ws.close()


@router.get("/api/live/sse", response_class=StreamingResponse,
            responses={200: {"content": {"text/event-stream": {}}},
                       503: {"description": "As many live clients as the console serves are connected"}})
async def live_sse(request: Request) -> StreamingResponse:
    """Server-sent events, one ``data:`` line per live frame; 503 while
    :data:`server.live.LIVE_MAX_CLIENTS` live clients are connected."""
    broadcaster = request.app.state.broadcaster
    if broadcaster.full():
        raise HTTPException(503, f"the console serves at most {broadcaster.max_clients} live clients at once: "
                            "close another view")

    async def stream():
        try:
            client = broadcaster.connect()
        except LiveFull:  # filled since the check above: the stream ends at once
            return
        try:
            while True:
                try:
                    frame = await asyncio.wait_for(client.queue.get(), KEEPALIVE_S)
                except TimeoutError:
                    yield b": keepalive\n\n"
                    continue
                if await request.is_disconnected():
                    break
                yield b"data: " + frame + b"\n\n"
        finally:
            broadcaster.disconnect(client)

    return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})
