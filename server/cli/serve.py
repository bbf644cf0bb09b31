"""``xneck server``: the experiment console (REST API, dashboard, live views, archive)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def server(
    host: Optional[str] = typer.Option(None, "--host", help="Bind address (default 127.0.0.1, $XNECK_HOST)."),
    port: Optional[int] = typer.Option(None, "--port", help="HTTP port (default 8000, $XNECK_PORT)."),
    data_dir: Optional[Path] = typer.Option(None, "--data-dir", help="Archives and parameter sets (default ./data)."),
    pace: Optional[str] = typer.Option(None, "--pace", help="Twin campaigns: realtime (default) or lockstep."),
    mode: Optional[str] = typer.Option(None, "--mode", help="twin (default) or robot (drive the bridge on the bus)."),
    hub: Optional[str] = typer.Option(None, "--hub", help="Zenoh endpoint to listen on (default a free loopback port)."),
    connect: Optional[list[str]] = typer.Option(None, "--connect", help="Zenoh endpoint to connect to (robot mode)."),
    viser_port: Optional[int] = typer.Option(None, "--viser-port", help="Port of the 3D view (default: free)."),
) -> None:
    """Run the experiment console; prints the dashboard URL and, at first start, the token."""
    import logging

    import uvicorn
    from pydantic import ValidationError

    from server.app import create_app
    from server.settings import Settings

    given = {"host": host, "port": port, "data_dir": data_dir, "pace": pace, "mode": mode, "hub": hub,
             "connect": connect, "viser_port": viser_port}
    try:
        settings = Settings(**{k: v for k, v in given.items() if v is not None})
    except ValidationError as exc:
        for err in exc.errors():
            typer.secho(f"error: --{'-'.join(map(str, err['loc'])).replace('_', '-')}: {err['msg']}", err=True, fg="red")
        raise typer.Exit(2) from None
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    app = create_app(settings)
    url = f"http://{settings.host}:{settings.port}/"
    typer.echo(f"xneck console: {url}  (API docs {url}docs, data in {Path(settings.data_dir).resolve()})")
    if app.state.token_generated:
        typer.echo(f"new API token (saved in {Path(settings.data_dir) / 'token'}): {app.state.token}")
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="warning", ws_ping_interval=20,
                timeout_graceful_shutdown=5)
