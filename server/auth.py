"""Bearer-token check of mutating endpoints (reading endpoints stay open on the lab network)."""

from __future__ import annotations

import secrets

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

_bearer = HTTPBearer(auto_error=False, description="Token printed at the server's first start (or XNECK_TOKEN).")


# Both checks are async (they do no I/O): a plain def ran in anyio's default pool, which a flood of
# open GETs could fill, and the e-stop's POST waited for a thread to check its token (review of session 53).
async def require_token(request: Request, creds: HTTPAuthorizationCredentials | None = Depends(_bearer)) -> None:
    """401 without a bearer token, 403 with a wrong one."""
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "missing bearer token (Authorization: Bearer <token>)",
                            headers={"WWW-Authenticate": "Bearer"})
    if not secrets.compare_digest(creds.credentials.encode(), request.app.state.token.encode()):
        raise HTTPException(status.HTTP_403_FORBIDDEN, "wrong bearer token")


async def require_operator(request: Request) -> None:
    """403 on a viewer's console (its bus user is a viewer, bridge.bus_credentials): what it would
    publish (campaigns, jogs, e-stops, stops) reaches no process, so it is refused here, clearly."""
    access = getattr(request.app.state, "bus_access", None) or {}
    if access.get("role") == "viewer":
        raise HTTPException(status.HTTP_403_FORBIDDEN,
                            f"this console's bus user {access.get('user')!r} is a viewer: it watches the robot and "
                            "cannot act on it (campaigns, jogs, e-stops); use an operator's console or the e-stop "
                            "button")
