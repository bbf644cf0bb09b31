"""`xneck bus ...`: the bus's access, for a bridge that listens on the lab network."""

from __future__ import annotations

from pathlib import Path

import typer

from server.cli.options import fail

bus_app = typer.Typer(help="The bus's access: credentials that keep strangers on the network off it.",
                      no_args_is_help=True, add_completion=False)


@bus_app.command("credentials")
def credentials(
    path: Path = typer.Argument(..., help="File to create (never replaced), e.g. ~/.config/xneck/bus-credentials."),
    user: str = typer.Option("xneck", "--user", help="The entry's user name (letters, digits, _.-)."),
) -> None:
    """Create a credentials file (one user and a random 256-bit password, mode 600). Copy it to every
    machine of the stack (the bridge's board too) and set XNECK_ZENOH_CREDENTIALS to its path there:
    processes then link only with processes that hold the same file."""
    from bridge.bus_credentials import ENV_CREDENTIALS, CredentialsError, write_new

    path = path.expanduser()
    if not path.parent.is_dir():
        raise fail(f"{path.parent} is not a directory")
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
