"""`xneck bus ...`: the bus's access, for a bridge that listens on the lab network: credentials
that keep strangers off it, and viewers who may watch and not act (bridge.bus_credentials)."""

from __future__ import annotations

from pathlib import Path

import typer

from server.cli.options import check_endpoints, fail


def link_report(endpoint: str) -> tuple[str, str]:
    """Whether this machine's processes could link to ``endpoint`` now (bridge.session.probe_link,
    with this environment's credentials and TLS): the state and a sentence that says why not, for
    the commissioning mistakes that otherwise look alike (a peer that never appears)."""
    from bridge import bus_tls
    from bridge.bus_credentials import ENV_CREDENTIALS, from_env
    from bridge.session import LINKED, NO_LISTENER, probe_link

    state = probe_link(endpoint)
    if state == LINKED:
        return state, f"{endpoint}: linked"
    if state == NO_LISTENER:
        return state, f"nothing listens at {endpoint}"
    creds = from_env()
    here = f"{ENV_CREDENTIALS}={creds.path}" if creds is not None else f"no {ENV_CREDENTIALS}"
    tls = ""
    if endpoint.startswith("tls/"):
        folder = bus_tls.from_env()
        tls = (" or the TLS folders (another authority, or a certificate that does not name this address: here "
               f"{', '.join(folder.hosts) if folder else 'none'})")
    return state, (f"{endpoint} answers but refuses this machine's bus session: the bus credentials differ{tls} "
                   f"(here: {here}), or it is not an xneck process")


#: What every change to the lab's credentials file needs: Zenoh reads it once, at start.
REDISTRIBUTE = "copy the file to every machine of the stack again and restart its xneck processes (the bridge's too)"


def make_parent(path: Path) -> None:
    """Create the missing folder ``path`` goes into (mode 700: it holds secrets), as ``mkdir -p``
    would; or fail naming what is in the way. On a fresh PC ``~/.config/xneck`` does not exist, and
    the docs' first distributed step writes there (audit of 2026-11-29)."""
    parent = path.parent
    if parent.is_dir():
        return
    for above in (parent, *parent.parents):
        if above.exists() or above.is_symlink():
            if not above.is_dir():
                raise fail(f"{above} is not a directory (the folder of {path})")
            break
    try:
        parent.mkdir(mode=0o700, parents=True)
    except OSError as exc:
        raise fail(f"cannot create the folder {parent}: {exc.strerror or exc}") from None

bus_app = typer.Typer(help="The bus's access: credentials that keep strangers on the network off it.",
                      no_args_is_help=True, add_completion=False)


@bus_app.command("credentials")
def credentials(
    path: Path = typer.Argument(..., help="File to create (never replaced; a missing folder is created, mode 700), e.g. "
                                   "~/.config/xneck/bus-credentials."),
    user: str = typer.Option("xneck", "--user", help="The entry's user name (letters, digits, _.-)."),
) -> None:
    """Create a credentials file (one user and a random 256-bit password, mode 600). Copy it to every
    machine of the stack (the bridge's board too) and set XNECK_ZENOH_CREDENTIALS to its path there:
    processes then link only with processes that hold the same file. xneck bus add-user adds users
    (viewer-<name>: may watch, not act), xneck bus export-user writes one user's entry alone."""
    from bridge.bus_credentials import ENV_CREDENTIALS, CredentialsError, write_new

    path = path.expanduser()
    make_parent(path)
    try:
        made = write_new(path, user)
    except FileExistsError:
        raise fail(f"{path} exists: credentials are never replaced (remove the file to make new ones; every "
                   "machine then needs the new file)") from None
    except (CredentialsError, OSError) as exc:
        raise fail(str(exc)) from None
    typer.echo(f"wrote {made.path} (user {made.user!r}, mode 600)\n"
               f"on every machine of the stack: copy it (scp; keep it mode 600) and set\n"
               f"  export {ENV_CREDENTIALS}={made.path.resolve()}\n"
               f"(the bridge's unit: Environment={ENV_CREDENTIALS}=/etc/xneck/bus-credentials)")


@bus_app.command("add-user")
def add_user(
    path: Path = typer.Argument(..., help="The lab's credentials file (xneck bus credentials)."),
    user: str = typer.Argument(..., help="The new entry's user name; viewer or viewer-<name> for a viewer, who "
                                         "may watch the robot and not act on it."),
) -> None:
    """Add a user with a new random password to a credentials file (replaced at once, mode 600).
    A viewer's machine gets its entry alone (xneck bus export-user); every other machine needs the
    updated file, and its processes a restart (credentials are read at start)."""
    from bridge.bus_credentials import CredentialsError, add_entry

    try:
        made = add_entry(path.expanduser(), user)
    except (CredentialsError, OSError) as exc:
        raise fail(str(exc)) from None
    typer.echo(f"added {made.user!r} ({made.role}) to {made.path}; users: {', '.join(made.users)}\n{REDISTRIBUTE}"
               + (f"; the viewer's machine: xneck bus export-user {made.path} {made.user} FILE" if made.role == "viewer"
                  else ""))


@bus_app.command("remove-user")
def remove_user(
    path: Path = typer.Argument(..., help="The lab's credentials file."),
    user: str = typer.Argument(..., help="The entry to remove: a lost laptop, a viewer who left."),
) -> None:
    """Remove a user from a credentials file (replaced at once, mode 600). The user is refused once
    every machine of the stack has the updated file and its processes restarted (the file is read at
    start; a session already open stays open until then)."""
    from bridge.bus_credentials import CredentialsError, remove_entry

    try:
        left = remove_entry(path.expanduser(), user)
    except (CredentialsError, OSError) as exc:
        raise fail(str(exc)) from None
    typer.echo(f"removed {user!r} from {left.path}; users: {', '.join(left.users)}\n{REDISTRIBUTE}: until then "
               f"they still accept {user!r}")


@bus_app.command("export-user")
def export_user(
    path: Path = typer.Argument(..., help="The lab's credentials file."),
    user: str = typer.Argument(..., help="The entry to export."),
    out: Path = typer.Argument(..., help="File to create (never replaced), for the machine that presents USER."),
) -> None:
    """Write USER's entry alone to OUT (mode 600): the file for a machine that must not learn the
    other passwords, a viewer's. It links to the stack's processes by connecting to them (they list
    its entry); it cannot accept their links, nor present another user."""
    from bridge.bus_credentials import ENV_CREDENTIALS, CredentialsError, export_entry

    out = out.expanduser()
    make_parent(out)
    try:
        made = export_entry(path.expanduser(), user, out)
    except FileExistsError:
        raise fail(f"{out} exists: credentials are never replaced") from None
    except (CredentialsError, OSError) as exc:
        raise fail(str(exc)) from None
    typer.echo(f"wrote {made.path} ({made.user!r}, {made.role}, mode 600)\n"
               f"on that machine: export {ENV_CREDENTIALS}={made.path.resolve()}")


@bus_app.command("tls")
def tls(
    path: Path = typer.Argument(..., help="Folder to create (never replaced), e.g. ~/.config/xneck/bus-tls."),
    host: list[str] = typer.Option(..., "--host", help="An address peers connect to, IP or DNS name (repeatable): "
                                                         "the board's and the PC's, as they appear in tls/<host>:<port>."),
    days: int = typer.Option(825, "--days", help="Validity of the machines' certificate (days, 1-3650)."),
) -> None:
    """Create a TLS folder: the lab's certificate authority and one certificate for the stack's
    machines (keys mode 600). Copy it, without ca.key, to every machine and set XNECK_ZENOH_TLS to its
    path there; then tls/<host>:<port> endpoints encrypt the bus and both ends prove the lab's
    certificate (docs/safety.md, "Encrypting the bus")."""
    from bridge.bus_tls import CA_KEY, ENV_TLS, TlsError, write_new

    path = path.expanduser()
    make_parent(path)
    try:
        made = write_new(path, host, days)
    except FileExistsError:
        raise fail(f"{path} exists: a TLS folder is never replaced (make another; every machine then needs it)") from None
    except (TlsError, OSError) as exc:
        raise fail(str(exc)) from None
    typer.echo(f"wrote {made.path}: ca.pem, node.pem, node.key (names {', '.join(made.hosts)}; valid until "
               f"{made.not_after.date()}) and {CA_KEY} (keep it here, do not copy it)\n"
               f"on every machine of the stack: copy ca.pem, node.pem, node.key (node.key mode 600) and set\n"
               f"  export {ENV_TLS}={made.path.resolve()}\n"
               f"then listen and connect on tls/<host>:<port>, e.g. xneck bridge ... --listen tls/0.0.0.0:7447")


@bus_app.command("check")
def check(
    endpoint: list[str] = typer.Argument(None, help="Endpoints to try linking to, e.g. tls/<board-address>:7447."),
) -> None:
    """Say what this machine's bus settings are (XNECK_ZENOH_CREDENTIALS, XNECK_ZENOH_TLS) and
    whether it links to each ENDPOINT now, as xneck's processes would: before connecting the robot.
    Exit status 1 if an endpoint does not link, 2 if the settings cannot be used."""
    from bridge import bus_tls
    from bridge.bus_credentials import ENV_CREDENTIALS, CredentialsError, from_env
    from bridge.session import LINKED

    try:
        creds, folder = from_env(), bus_tls.from_env()
    except (CredentialsError, bus_tls.TlsError) as exc:
        raise fail(str(exc)) from None
    check_endpoints([], list(endpoint or []))
    if creds is None:
        typer.echo(f"credentials: none ({ENV_CREDENTIALS} unset): any Zenoh peer that reaches an exposed endpoint links")
    else:
        viewers = f"; drops what viewers publish: {', '.join(creds.viewers)}" if creds.viewers else ""
        typer.echo(f"credentials: {creds.path}, presenting {creds.user!r} ({creds.role}); accepts "
                   f"{', '.join(creds.users)}{viewers}")
    if folder is None:
        typer.echo(f"TLS: none ({bus_tls.ENV_TLS} unset): links are not encrypted; tls/ endpoints unavailable")
    else:
        typer.echo(f"TLS: {folder.path}, certificate names {', '.join(folder.hosts)}; valid until "
                   f"{folder.not_after.date()} ({folder.days_left():.0f} days left)")
    failed = 0
    for e in endpoint or []:
        state, sentence = link_report(e)
        failed += state != LINKED
        typer.echo(sentence)
    if failed:
        raise typer.Exit(1)
