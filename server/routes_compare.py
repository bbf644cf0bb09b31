"""``GET /api/campaigns/compare?ids=a,b[,c,d]``: a Table-3-shaped table of 2-4 archived campaigns
with their parameter sets and truths (``server.compare``), and with ``traces=true`` their series
for overlaid plots (α^d, α̂, α_IP, e, e_α, forces). Included before ``/api/campaigns/{id}``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Query, Request, status

from server.archive_reads import archive_reads, read_failure
from server.campaigns import NotFound
from server.compare import UnreadableMetrics, cached_traces, compare_table
from server.records import valid_id

router = APIRouter(prefix="/api/campaigns", tags=["campaigns"])

MIN_RUNS, MAX_RUNS = 2, 4


@router.get("/compare", responses={404: {"description": "An unknown campaign"},
                                   409: {"description": "A campaign still running"},
                                   422: {"description": "Not 2-4 distinct ids, or a record whose metrics "
                                                         "are not numbers"}})
async def compare(request: Request, ids: str = Query(..., max_length=600, description="2-4 campaign ids, comma "
                                                      "separated"),
                  traces_: bool = Query(False, alias="traces", description="Also the series of each run.")) -> Any:
    """Compare archived campaigns: ``{"table", "campaigns", "traces"?}`` (module docstring)."""
    chosen = list(dict.fromkeys(i.strip() for i in ids.split(",") if i.strip()))
    if not MIN_RUNS <= len(chosen) <= MAX_RUNS:
        raise HTTPException(422, f"choose {MIN_RUNS} to {MAX_RUNS} distinct campaigns, "
                            f"got {len(chosen)}")
    manager = request.app.state.campaigns
    records = []
    for cid in chosen:
        try:
            if not valid_id(cid):
                raise NotFound(cid)
            rec = manager.get(cid)
        except NotFound:
            raise HTTPException(status.HTTP_404_NOT_FOUND, f"no campaign {cid!r}") from None
        if rec.status == "running":
            raise HTTPException(status.HTTP_409_CONFLICT, f"campaign {cid} is still running")
        records.append(rec)
    try:
        table = compare_table(records)
    except UnreadableMetrics as exc:
        raise HTTPException(422, str(exc)) from None
    out: dict[str, Any] = {"table": table,
                           "campaigns": [{"id": r.id, "law": r.law, "parameter_set": r.parameter_set, "truth": r.truth,
                                          "trajectory": r.trajectory, "status": r.status} for r in records]}
    if traces_:
        # one read per archive at a time, two at most, on threads of their own: a flood of these
        # open GETs had taken the pool the e-stop's POST needs (review of session 53)
        reads = archive_reads(request.app.state)
        series = {}
        for rec in records:
            mcap = manager.index.mcap(rec.id)
            try:
                series[rec.id] = await reads.run(mcap, cached_traces, mcap, manager.index.figures(rec.id))
            except Exception as exc:  # noqa: BLE001 - a damaged archive is a 422, not a crash
                # never the exception's text: it named the data directory (review of session 53)
                raise HTTPException(422, read_failure(rec.id, mcap, exc)) from None
        out["traces"] = series
    return out
