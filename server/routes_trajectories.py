"""``/api/trajectories``: the library of user trajectories (list, get, put, delete) and the
validation the dashboard's editor calls as the operator types (issue 18).

A trajectory is JSON, or TOML with ``Content-Type: application/toml`` (the schema of
``--trajectory FILE``, :class:`controller.trajectory.TrajectoryFile`). Saving and validating run
the checks a campaign start runs (:func:`server.campaign_request.check_trajectory`: joint limits,
speed, acceleration, forces on the nominal path) against the active parameter set (or
``?parameter_set=``) and ``?law=`` (default 2), and answer with the checker's message.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Depends, HTTPException, Query, Request, status
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from controller.laws import LawConfig
from controller.trajectory import NAMED_TRAJECTORIES, Trajectory, TrajectoryError
from server.auth import require_token
from server.campaign_request import check_trajectory
from server.paramsets import UnknownParameterSet
from server.trajectory_library import LibraryError, NotInLibrary, TrajectoryLibrary, check_name, parse, preview
from twin.model.params import ParameterError

router = APIRouter(prefix="/api/trajectories", tags=["trajectories"])

BODY = {"requestBody": {"required": True, "content": {
    "application/json": {"schema": {"type": "object"}}, "application/toml": {"schema": {"type": "string"}}}}}


def _library(request: Request) -> TrajectoryLibrary:
    state = request.app.state
    lib = getattr(state, "trajectories", None)
    if lib is None:
        lib = state.trajectories = TrajectoryLibrary(state.settings.data_dir)
    return lib


def _unprocessable(loc: list[str], msg: str) -> JSONResponse:
    return JSONResponse(status_code=422, content={"detail": [{"loc": loc, "msg": msg, "type": "value_error"}]})


async def _parsed(request: Request) -> Trajectory:
    """The body as a trajectory (JSON, or TOML by its content type); raises :class:`LibraryError`
    or :class:`TrajectoryError`. Parsed off the event loop, as the checks and the library's
    reads and writes are: on it a parse held every other request, the e-stop's too (review of
    session 53)."""
    return await run_in_threadpool(parse, await request.body(), request.headers.get("content-type", "application/json"))


async def _check(request: Request, traj: Trajectory, law: int, parameter_set: str | None) -> None:
    """The campaign checks on ``traj``; raises :class:`TrajectoryError` (the checker's message),
    :class:`UnknownParameterSet` or :class:`ParameterError`."""
    store = request.app.state.params
    params = await run_in_threadpool(store.load, parameter_set or store.active())
    await run_in_threadpool(check_trajectory, traj, params, LawConfig(law=law))


@router.get("")
def list_trajectories(request: Request) -> dict[str, Any]:
    """Built-in trajectories (read-only) and the library's, with their size and duration."""
    return {"trajectories": _library(request).list()}


@router.post("/validate", dependencies=[Depends(require_token)], openapi_extra=BODY)
async def validate_trajectory(request: Request, law: int = Query(2, ge=1, le=3),
                              parameter_set: str | None = Query(None, max_length=64)) -> dict[str, Any]:
    """Check a trajectory as a campaign start would: ``{"ok", "message", "preview"}``; the preview
    (α^d(t), degrees) comes whenever the waypoints are well formed, even when a check fails."""
    try:
        traj = await _parsed(request)
    except (LibraryError, TrajectoryError) as exc:
        return {"ok": False, "message": str(exc), "preview": None}
    try:
        await _check(request, traj, law, parameter_set)
        ok, message = True, f"ok: {traj.n_waypoints} waypoints, {traj.duration_s:.3g} s"
    except (TrajectoryError, UnknownParameterSet, ParameterError) as exc:
        ok, message = False, str(exc)
    return {"ok": ok, "message": message, "preview": preview(traj)}


@router.post("/preview3d", dependencies=[Depends(require_token)], openapi_extra=BODY,
             responses={409: {"description": "The 3D view is off"}, 422: {"description": "Not a trajectory of this "
                                                                              "neck"}})
async def preview_in_3d(request: Request) -> Any:
    """Play the trajectory once in the 3D view as a violet ghost (nothing moves); its duration."""
    try:
        traj = await _parsed(request)
    except (LibraryError, TrajectoryError) as exc:
        return _unprocessable(["body"], str(exc))
    scene = getattr(request.app.state, "scene", None)
    if scene is None:
        raise HTTPException(status.HTTP_409_CONFLICT, "the 3D view is off (the console runs without viser)")
    if traj.n_joints != scene.drawing.n_joints:
        return _unprocessable(["body", "waypoints_deg"], f"{traj.n_joints} joints for a neck of {scene.drawing.n_joints}")
    return {"duration_s": scene.preview(traj)}


@router.get("/{name}", responses={404: {"description": "No such trajectory"},
                                  422: {"description": "The stored file does not read as a trajectory; detail says why"}})
def get_trajectory(name: str, request: Request) -> dict[str, Any]:
    """A trajectory in the user-file schema (JSON, degrees), with its duration."""
    missing = HTTPException(status.HTTP_404_NOT_FOUND, f"no trajectory {name!r}")
    if name not in NAMED_TRAJECTORIES:
        try:
            check_name(name)
        except LibraryError:
            raise missing from None
    try:
        traj = _library(request).get(name)
    except NotInLibrary:
        raise missing from None
    except (LibraryError, TrajectoryError) as exc:  # a file there that does not read: say so, not "no trajectory"
        raise HTTPException(422, f"stored trajectory {name!r}: {exc}") from None
    return {**traj.to_dict(), "duration_s": traj.duration_s}


@router.put("/{name}", status_code=status.HTTP_201_CREATED, dependencies=[Depends(require_token)],
            openapi_extra=BODY, responses={422: {"description": "Bad name, or a trajectory the checks refuse "
                                                                "(msg is the checker's)"}})
async def put_trajectory(name: str, request: Request, law: int = Query(2, ge=1, le=3),
                         parameter_set: str | None = Query(None, max_length=64)) -> Any:
    """Save a trajectory to the library under ``name`` once it passes the campaign checks."""
    lib = _library(request)
    try:
        check_name(name)
    except LibraryError as exc:
        return _unprocessable(["path", "name"], str(exc))
    try:
        traj = await _parsed(request)
        await _check(request, traj, law, parameter_set)
    except (LibraryError, TrajectoryError, UnknownParameterSet, ParameterError) as exc:
        return _unprocessable(["body"], str(exc))
    try:
        await run_in_threadpool(lib.put, name, traj)
    except LibraryError as exc:
        return _unprocessable(["path", "name"], str(exc))
    return {"name": name, "waypoints": traj.n_waypoints, "duration_s": traj.duration_s}


@router.delete("/{name}", status_code=status.HTTP_204_NO_CONTENT, response_class=Response,
               dependencies=[Depends(require_token)], responses={409: {"description": "A built-in trajectory"}})
def delete_trajectory(name: str, request: Request) -> Response:
    try:
        _library(request).delete(name)
    except NotInLibrary:
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no trajectory {name!r}") from None
    except LibraryError as exc:
        code = status.HTTP_409_CONFLICT if "built-in" in str(exc) else status.HTTP_404_NOT_FOUND
        raise HTTPException(code, str(exc)) from None
    return Response(status_code=status.HTTP_204_NO_CONTENT)
