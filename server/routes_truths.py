"""``/api/truths``: what a twin can simulate (issue 16) — list, get (TOML), upload (validated).
A campaign request names one of these in its ``truth`` field (server.campaign_request)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.responses import JSONResponse, PlainTextResponse
from starlette.concurrency import run_in_threadpool

from server.auth import require_token
from server.truthstore import MAX_TRUTH_BYTES, TruthStore, UnknownTruth
from twin.sim.truth import ROBOT_TRUTH_FILE, TruthError

router = APIRouter(prefix="/api/truths", tags=["truths"])


def _store(request: Request) -> TruthStore:
    return TruthStore(request.app.state.settings.data_dir)


@router.get("")
def list_truths(request: Request) -> dict[str, Any]:
    """Every truth a campaign may name; a stored file that no longer loads says why."""
    store = _store(request)
    out = []
    for name in store.names():
        try:
            out.append(store.summary(name))
        except (TruthError, UnknownTruth) as exc:
            out.append({"name": name, "error": str(exc)})
    return {"truths": out}


@router.get("/{name}", response_class=PlainTextResponse, responses={
    200: {"content": {"application/toml": {}}}, 404: {"description": "No such truth file"},
    422: {"description": "The stored file is not text; detail says why"}})
def get_truth(name: str, request: Request) -> PlainTextResponse:
    """The truth file (TOML); "model" has none (no effect: the parameter file as it is)."""
    if name == "robot":
        return PlainTextResponse(ROBOT_TRUTH_FILE.read_text(), media_type="application/toml")
    try:
        text = _store(request).path(name).read_bytes().decode("utf-8")
    except UnknownTruth:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no truth file {name!r}") from None
    except UnicodeDecodeError as exc:  # a file put there by hand: a 500 before (audit of 2026-11-27)
        raise HTTPException(422, f"truth file {name!r} is not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    return PlainTextResponse(text, media_type="application/toml")


@router.put("/{name}", status_code=status.HTTP_201_CREATED, dependencies=[Depends(require_token)],
            openapi_extra={"requestBody": {"required": True, "content": {"application/toml": {
                "schema": {"type": "string"}}}}},
            responses={422: {"description": "Not a valid truth file; msg names the key and the reason"}})
async def upload_truth(name: str, request: Request) -> Any:
    """Store a truth file (the body is its TOML text, e.g. from `xneck twin calibrate`), validated
    as ``--truth FILE`` is."""
    try:
        TruthStore.check_new_name(name)
    except TruthError as exc:
        return _unprocessable(["path", "name"], str(exc))
    body = await request.body()
    if not body:
        return _unprocessable(["body"], "empty body: send the TOML text of a truth file")
    if len(body) > MAX_TRUTH_BYTES:
        return _unprocessable(["body"], f"{len(body)} bytes: more than {MAX_TRUTH_BYTES} for a truth file")
    try:
        # Parsed, checked and written (fsync of the file and its folder) off the event loop: on it
        # they held every other request, the e-stop's too (review of session 53).
        truth = await run_in_threadpool(_store(request).save, name, body)
    except TruthError as exc:
        return _unprocessable(["body"], str(exc))
    return {"name": name, "effects": list(truth.enabled()), "calibrated": truth.calibration is not None}


def _unprocessable(loc: list[str], msg: str) -> JSONResponse:
    return JSONResponse(status_code=422, content={"detail": [{"loc": loc, "msg": msg, "type": "value_error"}]})
