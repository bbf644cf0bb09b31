"""The `xneck` command line: one entry point, one subcommand per capability.

One module per group of commands (``model``, ``processes``, ``campaign``, ``identify``,
``kinematics``, ``serve``, ``up``); this file assembles them so that ``xneck --help`` lists
everything a lab can run. The modules import the packages they drive inside their commands, so the
bridge on a small board loads only the bridge.
"""

from __future__ import annotations

import os

import typer

from server.cli import (
    bus,
    calibrate,
    camera,
    campaign,
    estop,
    excitation,
    identify,
    kinematics,
    model,
    processes,
    serve,
    study,
    up,
)

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


app.command("model", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(model.model)
# `xneck twin` runs the twin; `xneck twin calibrate` fits a truth to recordings (issue 16).
twin_app = typer.Typer(help="Run the simulated robot on the bus, or calibrate its truth.", invoke_without_command=True)
twin_app.callback()(processes.twin)
twin_app.command("calibrate")(calibrate.calibrate)
app.add_typer(twin_app, name="twin")
app.command("bridge")(processes.bridge)
app.command("controller")(processes.controller)
campaign.campaign_app.command("control")(campaign.campaign_control)
campaign.campaign_app.command("identification")(campaign.campaign_identification)
app.add_typer(campaign.campaign_app, name="campaign")
app.add_typer(kinematics.kinematics_app, name="kinematics")
app.command("workspace")(kinematics.workspace)
app.command("identify")(identify.identify)
app.command("server")(serve.server)
app.command("up")(up.up)
app.add_typer(camera.camera_app, name="camera")
excitation.excitation_app.command("design")(excitation.design_command)
excitation.excitation_app.command("bound")(excitation.bound_command)
app.add_typer(excitation.excitation_app, name="excitation")
for _kind in ("control", "identification", "design"):
    study.study_app.command(_kind)(getattr(study, f"study_{_kind}"))
app.add_typer(study.study_app, name="study")
app.add_typer(bus.bus_app, name="bus")
app.add_typer(estop.estop_app, name="estop")


def quiet_opencv() -> None:
    """Silence OpenCV's own log and its FFmpeg's: a video that cannot be opened printed
    ``[mov,mp4,… @ 0x…] moov atom not found`` above xneck's error, an undecodable frame
    ``[mjpeg @ 0x…] No JPEG data found in image`` above its warning, a missing camera two
    ``[ WARN:0@0.19] global cap_v4l.cpp …`` lines (user audit). xneck says what failed itself
    (twin.camera.source). Environment variables, read when OpenCV starts logging and opens its
    first video, so OpenCV is not imported here (the bridge never loads it); one a user set
    (to debug OpenCV) is kept."""
    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


def main() -> None:
    from server.child_processes import die_with_parent_from_env

    die_with_parent_from_env()  # a child of `xneck up` stops when it dies
    quiet_opencv()
    app()


if __name__ == "__main__":
    main()
