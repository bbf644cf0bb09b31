"""What the console checks before any route runs (an ASGI middleware, so before a body is read).

In order, for HTTP and WebSocket requests:

1. **Host** (DNS-rebinding guard): the ``Host`` header must name the bind address, loopback, or
   one of ``allowed_hosts`` (bound to 0.0.0.0 with no list: any). A page of ``evil.example``
   whose name was re-pointed at 127.0.0.1 is thus refused (400) although the browser thinks it
   is talking to its own origin.
2. **Origin** of live data (``/api/live`` WebSocket and SSE): a browser's ``Origin`` must be the
   console's own (same host and port as the ``Host`` header) or in ``allowed_origins`` (403).
   Browsers send it on every WebSocket; clients without one (scripts) are not browsers.
3. **Token**: every mutating request (POST/PUT/PATCH/DELETE) needs the bearer token (401 without,
   403 wrong) checked *before its body is read*; live data too when the console listens beyond
   loopback (the token may come as ``?token=`` since a browser WebSocket cannot set headers).
4. **Body**: at most ``max_body_bytes`` (the e-stop's: :data:`ESTOP_MAX_BODY_BYTES`; 413 on a
   larger ``Content-Length`` at once, and as soon as a chunked body passes the limit, the rest
   unread; the e-stop's route gets the refusal instead, and engages); a JSON body nested deeper than
   :data:`MAX_JSON_DEPTH` is a 422 (Python's parser would recurse until it crashes), but the
   e-stop's, which its route reads and checks itself: a malformed e-stop request engages.

Every HTTP response carries :data:`SECURITY_HEADERS`: no page of the console may be framed (a page
on another port of 127.0.0.1 framed the dashboard invisibly over its own button and one click
released the e-stop: audit of 2026-11-26), nor its responses sniffed as another type, nor a
referrer sent, nor a script run that is not the console's own file (:data:`CSP`).

The routes keep their own ``require_token`` dependency (it documents the security scheme in
OpenAPI and holds if this middleware is ever left out).
"""

from __future__ import annotations

import ipaddress
import json
import secrets
from collections.abc import Awaitable, Callable, Iterable
from typing import Any
from urllib.parse import parse_qs, urlsplit

Scope = dict[str, Any]
Message = dict[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

MAX_JSON_DEPTH = 32
TOO_LARGE = "xneck.body_too_large"  # the scope key of a refused body's detail, for the e-stop's route
ESTOP_PATH = "/api/system/estop"  # checks its body's depth itself (server.routes_system.estop)
#: The e-stop's body at most (``{"engaged": false, "reason": <200 characters>}`` is far less): a
#: larger one engages it unread (413), its parse on the event loop bounded (review of session 53).
ESTOP_MAX_BODY_BYTES = 4096
#: Scripts only from the console itself, no plugins, no <base>: an injected value that ever reached
#: the page as HTML could run nothing (the dashboard writes every value as text; defence in depth,
#: audit of 2026-11-27). Styles are not limited (the page sets widths inline).
CSP = b"script-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
#: FastAPI's /docs and /redoc load their scripts from a CDN and start them inline: framing alone is
#: refused there. They act only with a token typed into them.
CSP_API_DOCS = b"frame-ancestors 'none'"
API_DOCS_PATHS = ("/docs", "/docs/oauth2-redirect", "/redoc")
SECURITY_HEADERS: tuple[tuple[bytes, bytes], ...] = (
    (b"x-frame-options", b"DENY"),
    (b"content-security-policy", CSP),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
)
LIVE_PATHS = ("/api/live", "/api/live/sse")
MUTATING = ("POST", "PUT", "PATCH", "DELETE")
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def json_depth_exceeds(body: bytes, limit: int = MAX_JSON_DEPTH) -> bool:
    """Whether a JSON text nests arrays/objects deeper than ``limit`` (brackets inside strings do
    not count). A linear scan: no parsing, so no recursion."""
    depth, in_string, escaped = 0, False, False
    for byte in body:
        if in_string:
            if escaped:
                escaped = False
            elif byte == 0x5C:  # backslash
                escaped = True
            elif byte == 0x22:  # quote
                in_string = False
        elif byte == 0x22:
            in_string = True
        elif byte in (0x5B, 0x7B):  # [ {
            depth += 1
            if depth > limit:
                return True
        elif byte in (0x5D, 0x7D):
            depth -= 1
    return False


def _split_host(value: str) -> str:
    """Host name of a ``Host`` header value (``name:port``, ``[v6]:port``), lower case."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1:value.find("]")] if "]" in value else value
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


class ConsoleGuard:
    """The checks of the module docstring around an ASGI app. ``token`` is read per request (a
    callable, so the app's state stays the one source)."""

    def __init__(self, app: ASGIApp, *, bind_host: str, token: Callable[[], str], max_body_bytes: int,
                 allowed_hosts: Iterable[str] = (), allowed_origins: Iterable[str] = ()) -> None:
        self.app = app
        self.token = token
        self.max_body_bytes = max_body_bytes
        self.allowed_origins = {o.rstrip("/").lower() for o in allowed_origins}
        self.exposed = not is_loopback(bind_host)
        hosts = {h.lower() for h in allowed_hosts}
        if bind_host in ("0.0.0.0", "::", ""):
            self.allowed_hosts: set[str] | None = (hosts | set(LOOPBACK_NAMES)) if hosts else None
        else:
            self.allowed_hosts = hosts | set(LOOPBACK_NAMES) | {bind_host.lower()}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}
        if scope["type"] == "http":
            send = _with_security_headers(send, docs=scope.get("path", "") in API_DOCS_PATHS)
        refusal = self._refusal(scope, headers)
        if refusal is not None:
            await _deny(scope, receive, send, *refusal)
            return
        if scope["type"] == "http" and scope["method"] in MUTATING:
            await self._with_bounded_body(scope, receive, send, headers)
            return
        await self.app(scope, receive, send)

    def _refusal(self, scope: Scope, headers: dict[str, str]) -> tuple[int, str, dict[str, str]] | None:
        host = headers.get("host", "")
        if self.allowed_hosts is not None and _split_host(host) not in self.allowed_hosts:
            return 400, (f"Host header {host!r} is not this console's (DNS-rebinding guard); a lab name for it goes "
                         f"in XNECK_ALLOWED_HOSTS"), {}
        path = scope.get("path", "")
        live = path in LIVE_PATHS
        origin = headers.get("origin")
        if live and origin is not None:
            parts = urlsplit(origin)
            if parts.netloc.lower() != host.lower() and origin.rstrip("/").lower() not in self.allowed_origins:
                return 403, f"origin {origin!r} may not read live data (same origin or XNECK_ALLOWED_ORIGINS)", {}
        if (scope["type"] == "http" and scope["method"] in MUTATING) or (live and self.exposed):
            return self._token_refusal(scope, headers)
        return None

    def _token_refusal(self, scope: Scope, headers: dict[str, str]) -> tuple[int, str, dict[str, str]] | None:
        scheme, _, given = headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not given.strip():
            given = (parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token") or [""])[0]
        if not given:
            return 401, "missing bearer token (Authorization: Bearer <token>)", {"WWW-Authenticate": "Bearer"}
        if not secrets.compare_digest(given.strip().encode(), self.token().encode()):
            return 403, "wrong bearer token", {}
        return None

    async def _with_bounded_body(self, scope: Scope, receive: Receive, send: Send, headers: dict[str, str]) -> None:
        """Read the body up to the limit (413 beyond, without reading on), check JSON depth, then
        hand the app the same body."""
        limit = ESTOP_MAX_BODY_BYTES if scope.get("path") == ESTOP_PATH else self.max_body_bytes
        declared = headers.get("content-length")
        if declared is not None and (not declared.strip().isdigit() or int(declared) > limit):
            await self._too_large(scope, receive, send, f"request body of {declared} bytes: at most {limit} bytes")
            return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                await self._too_large(scope, receive, send, f"request body larger than {limit} bytes")
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        # the e-stop's route reads its body itself: one too deep engages it (a 422 here sent nothing)
        if "json" in headers.get("content-type", "") and scope.get("path") != ESTOP_PATH and json_depth_exceeds(body):
            await _send_json(send, 422, {"detail": [{"loc": ["body"], "msg": f"JSON nested deeper than "
                                                     f"{MAX_JSON_DEPTH} levels", "type": "value_error"}]}, {})
            return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _too_large(self, scope: Scope, receive: Receive, send: Send, detail: str) -> None:
        """A 413, the rest of the body unread; the e-stop's route gets an empty body and the
        refusal in ``scope[TOO_LARGE]`` instead, so that it engages (a 413 here had sent nothing)."""
        if scope.get("path") != ESTOP_PATH:
            await _deny(scope, receive, send, 413, detail, {})
            return

        async def nothing() -> Message:
            return {"type": "http.request", "body": b"", "more_body": False}

        await self.app({**scope, TOO_LARGE: detail}, nothing, send)


def document_responses(routes: Iterable[Any]) -> None:
    """Add what this guard (and the storage handler) may answer to each route's OpenAPI responses,
    so that clients, and the schema-driven fuzz test, know every status code they can get."""
    detail = {"application/json": {"schema": {"type": "object", "properties": {"detail": {}}}}}
    for route in routes:
        responses = getattr(route, "responses", None)
        if responses is None:
            continue
        extra = {400: "Host header not this console's (DNS-rebinding guard)"}
        if "{" in route.path:
            extra[404] = "No such item"
        if set(getattr(route, "methods", ())) & set(MUTATING):
            extra.update({401: "Missing bearer token", 403: "Wrong bearer token",
                          413: "Body larger than the limit", 422: "Invalid body; loc names the field",
                          507: "Storage fault: the data directory cannot be written"})
        for code, text in extra.items():
            responses.setdefault(code, {"description": text, "content": detail})


async def _send_json(send: Send, status: int, content: object, headers: dict[str, str], ws: bool = False) -> None:
    body = json.dumps(content).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    raw += [(k.lower().encode(), v.encode()) for k, v in headers.items()]
    prefix = "websocket.http.response" if ws else "http.response"
    await send({"type": f"{prefix}.start", "status": status, "headers": raw})
    await send({"type": f"{prefix}.body", "body": body})


def _with_security_headers(send: Send, docs: bool = False) -> Send:
    """``send`` that adds :data:`SECURITY_HEADERS` to the response's start (those not set); on
    the API's own documentation pages (``docs``) the policy that only refuses framing."""
    security = [(k, CSP_API_DOCS if docs and k == b"content-security-policy" else v) for k, v in SECURITY_HEADERS]

    async def sending(message: Message) -> None:
        if message["type"] == "http.response.start":
            present = {k.lower() for k, _ in message.get("headers", [])}
            extra = [(k, v) for k, v in security if k not in present]
            message = {**message, "headers": [*message.get("headers", []), *extra]}
        await send(message)

    return sending


async def _deny(scope: Scope, receive: Receive, send: Send, status: int, detail: str,
                headers: dict[str, str]) -> None:
    if scope["type"] == "websocket":
        await receive()  # websocket.connect: the handshake request
        if "websocket.http.response" in scope.get("extensions", {}):
            await _send_json(send, status, {"detail": detail}, headers, ws=True)
        else:  # the server cannot send a status: closing before accepting is a 403
            await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
        return
    await _send_json(send, status, {"detail": detail}, headers)
