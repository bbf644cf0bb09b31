"""The operator's console routes (issue 18): jog, trajectory library, comparison of campaigns.

One function for :func:`server.app.create_app` to call, so the console's routers are included
before ``/api/campaigns/{id}`` (which would otherwise take ``/api/campaigns/compare``).
"""

from __future__ import annotations

from fastapi import FastAPI

from server import routes_compare, routes_jog, routes_trajectories
from server.guard import document_responses


def include_console_routes(app: FastAPI) -> None:
    for router in (routes_compare.router, routes_jog.router, routes_trajectories.router):
        document_responses(router.routes)
        app.include_router(router)
