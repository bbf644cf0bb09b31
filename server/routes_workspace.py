"""``/api/workspace``: wrench-feasible workspace and stiffness maps of the active parameter set.

``design=3x`` (default): the 3-X prototype's maps for the ACTIVE parameter set, so the page
follows the set campaigns use. ``design=2x``: the 2-X paper's figures, which depend on no set.
Rendering (a few seconds the first time) runs in a worker thread; results are cached on disk
(:mod:`server.workspace_maps`), so later requests and other browsers get files.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Query, Request, status
from fastapi.responses import FileResponse
from starlette.concurrency import run_in_threadpool

from server.paramsets import ParameterStore, UnknownParameterSet
from server.workspace_maps import FIGURES, DesignName, Entry, UnsupportedParameterSet, WorkspaceCache, caption
from twin.model.params import ParameterError

router = APIRouter(prefix="/api/workspace", tags=["workspace"])

DESIGN = Query("3x", description="3x: the prototype's maps for the active parameter set; "
                                 "2x: the 2-X paper's figures (independent of the parameter set).")


def _cache(request: Request) -> WorkspaceCache:
    return request.app.state.workspace


async def _entry_3x(request: Request) -> tuple[str, Entry]:
    """(active set name, its rendered entry); 409 if the set cannot be loaded, 422 if the maps
    do not apply to it."""
    store: ParameterStore = request.app.state.params
    name = store.active()
    try:
        params = await run_in_threadpool(store.load, name)
    except (UnknownParameterSet, ParameterError) as exc:
        # E.g. deleted between reading the active name and loading it.
        raise HTTPException(status.HTTP_409_CONFLICT,
                            f"active parameter set {name!r} cannot be loaded: {exc}") from None
    try:
        return name, await run_in_threadpool(_cache(request).ensure_3x, params)
    except UnsupportedParameterSet as exc:
        raise HTTPException(422, f"{name!r}: {exc}") from None


def _figures(design: DesignName, entry_key: str, summary: dict[str, Any] | None) -> list[dict[str, str]]:
    # ?v=<key> changes with the parameter set, so a browser never shows a stale cached image.
    suffix = f"?design=2x&v={entry_key}" if design == "2x" else f"?v={entry_key}"
    return [{"name": n, "url": f"/api/workspace/{n}.png{suffix}", "caption": caption(design, n, summary)}
            for n in FIGURES[design]]


@router.get("")
async def workspace_summary(request: Request, design: DesignName = DESIGN) -> dict[str, Any]:
    """Summary of the maps and the URLs of their figures.

    3x: the active parameter set's name, the fraction of the α grid (|α_i| <= 90°) that is
    wrench-feasible (Z(α) f = g(α) with f_min <= f <= f_max), the same within the trajectory joint
    limit, the joint stiffness range over the feasible set (N·m/rad), the grid. Computes the maps
    if they are not cached (a few seconds). 2x: the figure list only; figures render on first
    request.
    """
    if design == "2x":
        cache = _cache(request)
        key = cache.key_2x()
        rendered = cache.peek("2x", key) is not None
        return {"design": "2x", "parameter_set": None, "key": key, "grid": {"points_per_axis": cache.grid_2x},
                "rendered": rendered, "figures": _figures("2x", key, None)}
    name, entry = await _entry_3x(request)
    s = entry.summary
    return {**s, "parameter_set": name, "cached": entry.hit, "render_s": round(entry.render_s, 3),
            "figures": _figures("3x", s["key"], s)}


@router.get("/{figure}.png", response_class=FileResponse,
            responses={200: {"content": {"image/png": {}}}, 404: {"description": "Unknown figure name"}})
async def workspace_figure(figure: str, request: Request, design: DesignName = DESIGN) -> FileResponse:
    """A figure as PNG: for 3x ``wfw`` (feasible slices and head positions) or ``stiffness``
    (K_ii at the lowest and highest antagonistic tension, α3 = 0); for 2x the paper's figures
    (see ``GET /api/workspace?design=2x``). Header ``X-Xneck-Cache``: ``hit`` or ``miss``."""
    if figure not in FIGURES[design]:
        raise HTTPException(status.HTTP_404_NOT_FOUND,
                            f"no {design} workspace figure {figure!r}; figures: {', '.join(FIGURES[design])}")
    if design == "2x":
        entry = await run_in_threadpool(_cache(request).ensure_2x)
    else:
        _, entry = await _entry_3x(request)
    # no-cache: the same URL without ?v= shows another set's maps after the active set changes.
    headers = {"X-Xneck-Cache": "hit" if entry.hit else "miss", "X-Xneck-Workspace-Key": entry.summary["key"],
               "Cache-Control": "no-cache"}
    return FileResponse(entry.figure(design, figure), media_type="image/png", headers=headers)
