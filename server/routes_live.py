"""Live data for browsers: WebSocket ``/api/live`` and SSE ``/api/live/sse`` (same frames,
see :mod:`server.live`). Each connection reads its own bounded queue; nothing here can block
the bus or another client."""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import APIRouter, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import StreamingResponse

router = APIRouter(tags=["live"])

KEEPALIVE_S = 15.0


@router.websocket("/api/live")
async def live_ws(ws: WebSocket) -> None:
    """Live frames as JSON text messages (see :mod:`server.live`); anything the browser sends is ignored."""
    await ws.accept()
    broadcaster = ws.app.state.broadcaster
    client = broadcaster.connect()

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
            responses={200: {"content": {"text/event-stream": {}}}})
async def live_sse(request: Request) -> StreamingResponse:
    """Server-sent events, one ``data:`` line per live frame."""
    broadcaster = request.app.state.broadcaster

    async def stream():
        client = broadcaster.connect()
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
