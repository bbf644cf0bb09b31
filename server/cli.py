"""The `xneck` command line: one entry point, one subcommand per capability.

Each package owns its commands in its own ``cli`` module; this file only assembles them so that
``xneck --help`` lists everything a lab can run.
"""

from __future__ import annotations

import typer

from bridge import cli as bridge_cli
from controller import cli as controller_cli
from server.serve import server
from server.up import up
from twin import cli as twin_cli
from twin.identification_cli import identify
from twin.kinematics_cli import kinematics_app, workspace

app = typer.Typer(
    name="xneck",
    help="Digital twin and experiment console for the X-joint cable-driven neck.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)



@app.callback()
def _root() -> None:
    """Digital twin and experiment console for the X-joint cable-driven neck."""


app.command(
    "model", context_settings={"allow_extra_args": True, "ignore_unknown_options": True}
)(twin_cli.model)
app.command("twin")(twin_cli.twin)
app.command("bridge")(bridge_cli.bridge)
app.command("controller")(controller_cli.controller)
controller_cli.campaign_app.command("control")(controller_cli.campaign_control)
controller_cli.campaign_app.command("identification")(controller_cli.campaign_identification)
app.add_typer(controller_cli.campaign_app, name="campaign")
app.add_typer(kinematics_app, name="kinematics")
app.command("workspace")(workspace)
app.command("identify")(identify)
app.command("server")(server)
app.command("up")(up)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
