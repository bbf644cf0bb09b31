"""``/api/params``: parameter sets — list, get (TOML), upload (validated), choose the active one."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Request, status
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from pydantic import BaseModel, Field
from starlette.concurrency import run_in_threadpool

from server.auth import require_token
from server.paramsets import MAX_UPLOAD_BYTES, ParameterStore, UnknownParameterSet, check_name
from twin.model.params import ParameterError

router = APIRouter(prefix="/api/params", tags=["parameter sets"])


def _store(request: Request) -> ParameterStore:
    return request.app.state.params


def _unprocessable(loc: list[str], msg: str) -> JSONResponse:
    return JSONResponse(status_code=422, content={"detail": [{"loc": loc, "msg": msg, "type": "value_error"}]})


@router.get("")
def list_params(request: Request) -> dict[str, Any]:
    """The sets and the active one; ``fallback_from`` and ``reason``: the set named active that
    did not load when the console started (``prototype_3x`` stands in), else null."""
    store = _store(request)
    return {**store.active_status(), "parameter_sets": store.names()}


class ActiveChoice(BaseModel):
    name: str = Field(description="Name of an existing parameter set.")


@router.get("/active")
def get_active(request: Request) -> dict[str, str | None]:
    return _store(request).active_status()


@router.put("/active", dependencies=[Depends(require_token)])
def set_active(body: ActiveChoice, request: Request) -> Any:
    """Choose the parameter set campaigns use by default; 422 if it is unknown or does not load."""
    try:
        _store(request).set_active(body.name)
    except UnknownParameterSet:
        return _unprocessable(["body", "name"], f"unknown parameter set {body.name!r}; known: "
                              f"{', '.join(_store(request).names())}")
    except ParameterError as exc:
        return _unprocessable(["body", "name"], f"parameter set {body.name!r} cannot be chosen: {exc}")
    return {"active": body.name}


@router.get("/{name}", response_class=PlainTextResponse, responses={200: {"content": {"application/toml": {}}}})
def get_params(name: str, request: Request) -> PlainTextResponse:
    """The parameter file (TOML, SI units); 422 if the file on disk is not text."""
    missing = HTTPException(status.HTTP_404_NOT_FOUND, f"no parameter set {name!r}")
    try:
        check_name(name)
    except ParameterError:
        raise missing from None
    try:
        text = _store(request).text(name)
    except UnknownParameterSet:
        raise missing from None
    except ParameterError as exc:
        raise HTTPException(422, f"parameter set {name!r}: {exc}") from None
    return PlainTextResponse(text, media_type="application/toml")


@router.put("/{name}", status_code=status.HTTP_201_CREATED, dependencies=[Depends(require_token)],
            openapi_extra={"requestBody": {"required": True, "content": {"application/toml": {
                "schema": {"type": "string"}}}}},
            responses={422: {"description": "Not a valid parameter file; msg names the key and the reason"}})
async def upload_params(name: str, request: Request) -> Any:
    """Upload a parameter file (the request body is the TOML text), validated as ``--params`` is."""
    try:
        check_name(name)
    except ParameterError as exc:
        return _unprocessable(["path", "name"], str(exc))
    body = await request.body()
    if not body:
        return _unprocessable(["body"], "empty body: send the TOML text of a parameter file")
    if len(body) > MAX_UPLOAD_BYTES:
        return _unprocessable(["body"], f"{len(body)} bytes: more than {MAX_UPLOAD_BYTES} for a parameter file")
    try:
        # Parsed, checked and written (fsync of the file and its folder) off the event loop: on it
        # they held every other request, the e-stop's too (review of session 53).
        params = await run_in_threadpool(_store(request).save, name, body)
    except ParameterError as exc:
        return _unprocessable(["body"], str(exc))
    return {"name": name, "n_joints": params.n_joints, "n_cables": params.n_cables}


@router.delete("/{name}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response, dependencies=[Depends(require_token)],
               responses={409: {"description": "Built in, or the active set: choose another one first"}})
def delete_params(name: str, request: Request) -> Response:
    try:
        _store(request).delete(name)
    except UnknownParameterSet:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no parameter set {name!r}") from None
    except ParameterError as exc:
        raise HTTPException(status.HTTP_409_CONFLICT, str(exc)) from None
    return Response(status_code=status.HTTP_204_NO_CONTENT)
