"""``xneck server``: the experiment console (REST API, dashboard, live views, archive)."""

from __future__ import annotations

from pathlib import Path

import typer

from server.cli.options import PORT_MAX, check_credentials, check_endpoints, fail


def server(
    host: str | None = typer.Option(None, "--host", help="Bind address (default 127.0.0.1, $XNECK_HOST)."),
    port: int | None = typer.Option(None, "--port", min=0, max=PORT_MAX,
                                    help="HTTP port, 0-65535 (default 8000, $XNECK_PORT)."),
    data_dir: Path | None = typer.Option(None, "--data-dir", help="Archives and parameter sets (default ./data)."),
    pace: str | None = typer.Option(None, "--pace", help="Twin campaigns: realtime (default) or lockstep."),
    mode: str | None = typer.Option(None, "--mode", help="twin (default) or robot (drive the bridge on the bus)."),
    hub: str | None = typer.Option(None, "--hub", help="Zenoh endpoint to listen on (default a free loopback port)."),
    connect: list[str] | None = typer.Option(None, "--connect", help="Zenoh endpoint to connect to (robot mode)."),
    viser_port: int | None = typer.Option(None, "--viser-port", min=0, max=PORT_MAX,
                                          help="Port of the 3D view, 0-65535 (default: free)."),
    twin_truth: str | None = typer.Option(None, "--twin-truth", help="Truth of the stack's twin bridge, when a "
                                             "controller service is on the bus (xneck up passes it)."),
    stack: bool = typer.Option(False, "--stack", help="This console is an `xneck up` stack's (set by it): a campaign "
                               "with the stack's controller service away is refused, never run on a twin of its own."),
    twin_seed: int | None = typer.Option(None, "--twin-seed", help="Seed of the stack's twin bridge (likewise)."),
    twin_alpha_ip: str | None = typer.Option(None, "--twin-alpha-ip", help="α_IP of the stack's twin bridge, noise "
                                             "or camera (likewise): the one camera its campaigns record."),
    twin_camera: str | None = typer.Option(None, "--twin-camera", help="Instance of the stack's camera process "
                                           "(likewise): of two cameras of one source, the one recorded."),
    min_free_mb: float | None = typer.Option(None, "--min-free-mb", help="Free space a campaign needs (MB, "
                                                "default 64)."),
    allowed_host: list[str] | None = typer.Option(None, "--allowed-host", help="Host name the console answers "
                                                     "to besides its address and loopback (repeatable)."),
    allowed_origin: list[str] | None = typer.Option(None, "--allowed-origin", help="Web origin allowed to read "
                                                       "live data besides the console's own (repeatable)."),
) -> None:
    """Run the experiment console; prints the dashboard URL and, at first start, the token."""
    import logging

    import uvicorn
    from pydantic import ValidationError

    from server.app import create_app
    from server.datadir import DataDirError
    from server.routes_live import WS_MAX_BYTES
    from server.settings import Settings

    given = {"host": host, "port": port, "data_dir": data_dir, "pace": pace, "mode": mode, "hub": hub,
             "connect": connect, "viser_port": viser_port, "twin_truth": twin_truth, "twin_seed": twin_seed,
             "twin_alpha_ip": twin_alpha_ip, "twin_camera": twin_camera,
             "min_free_mb": min_free_mb, "allowed_hosts": allowed_host, "allowed_origins": allowed_origin,
             "stack": stack or None}
    try:
        settings = Settings(**{k: v for k, v in given.items() if v is not None})
    except ValidationError as exc:
        for err in exc.errors():
            typer.secho(f"error: --{'-'.join(map(str, err['loc'])).replace('_', '-')}: {err['msg']}", err=True, fg="red")
        raise typer.Exit(2) from None
    check_credentials(acts=False)  # a viewer's console watches; its routes that act refuse (server.auth.require_operator)
    # A malformed --hub/--connect or a --host that does not resolve: one line now, not a traceback
    # from the app's startup after the URL was printed.
    check_endpoints([settings.hub], list(settings.connect) or None)
    from server.cli.up import _port_taken, _tcp_address

    why = _port_taken(settings.host, 0)  # the host alone: a busy --port is uvicorn's own one-line error
    if why:
        raise fail(f"--host {settings.host}: cannot listen there ({why})")
    hub_address = _tcp_address(settings.hub)  # Zenoh's refusal came as a traceback from the app's startup
    if hub_address is not None and hub_address[1] > PORT_MAX:
        raise fail(f"--hub {settings.hub}: the port must be at most {PORT_MAX}")
    why = _port_taken(*hub_address) if hub_address is not None and hub_address[1] else ""
    if why:
        raise fail(f"--hub {settings.hub}: cannot listen there ({why})")
    # viser takes the next port when its own is busy, without a word: the 3D view then took the
    # console's --port when that was next, and uvicorn failed (audit of 2026-11-27). xneck up checks the same.
    if settings.viser_port and settings.viser_port == settings.port:
        raise fail(f"--viser-port {settings.viser_port} is the console's --port: choose another (0 = a free one)")
    why = _port_taken(settings.host, settings.viser_port) if settings.viser_port else ""
    if why:
        raise fail(f"--viser-port {settings.viser_port}: {settings.host}:{settings.viser_port} is {why}: "
                   f"choose another (0 = a free one)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        app = create_app(settings)
    except DataDirError as exc:  # one line, no traceback: another owner, read-only, missing rights
        typer.secho(f"error: {exc}", err=True, fg="red")
        raise typer.Exit(2) from None
    url = f"http://{settings.host}:{settings.port}/"
    typer.echo(f"xneck console: {url}  (API docs {url}docs, data in {Path(settings.data_dir).resolve()})")
    if app.state.token_generated:
        typer.echo(f"new API token (saved in {Path(settings.data_dir) / 'token'}): {app.state.token}")
    # ws_max_size: a live client's message is ignored, uvicorn's 16 MB default was read first (review of session 53)
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="warning", ws_ping_interval=20,
                ws_max_size=WS_MAX_BYTES, timeout_graceful_shutdown=5)
