"""`xneck camera ...`: α_IP from a camera (issue 15, docs/camera.md).

- ``xneck camera --source usb:N|/dev/videoN|file:VIDEO|twin``: the bus process publishing
  ``xneck/camera/alpha_ip`` from one detector (``twin.camera.detect``), and a few JPEG frames
  per second on ``xneck/camera/frame`` (``--frame-rate-hz``); composed here. A USB camera's
  exposures are stamped on the bridge's clock (``--clock bridge``, :mod:`twin.camera.clock`).
- ``xneck camera render --alpha A1 A2 A3 --out F.png``: the twin's camera view at α (degrees).
- ``xneck camera detect F.png [--calibration FILE] --json``: α measured on one frame.
- ``xneck camera markers --out sheet.png`` / ``board --out board.png``: printable marker sheet
  and calibration checkerboard (the calibration itself is twin.camera.calibration's functions,
  docs/camera.md: there is no ``calibrate`` command).
- ``xneck camera align VIDEO CAMPAIGN.mcap``: offline time alignment of a video with a campaign.

OpenCV is imported inside the commands (``xneck --help`` and the bridge never load it).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import typer

from server.cli.options import (
    CONNECT_OPTION,
    INSTANCE_OPTION,
    LISTEN_OPTION,
    NON_NEGATIVE,
    PARAMS_OPTION,
    POSITIVE,
    SET_OPTION,
    VERBOSE_OPTION,
    check_credentials,
    check_endpoints,
    check_input,
    check_output,
    echo_json,
    fail,
    load_cli_params,
    number,
    open_bus,
    write_failed,
)

camera_app = typer.Typer(
    help="α_IP from a camera: the bus process (--source), and render/detect/markers/board/align.",
    add_completion=False,
    invoke_without_command=True,
)

CALIBRATION_OPTION = typer.Option(None, "--calibration", help="Calibration file (JSON); default: the twin's nominal camera.")




def _calibration(path: Path | None):
    from twin.camera.calibration import CalibrationError, load_calibration, twin_calibration

    if path is None:
        return twin_calibration()
    check_input(path, "calibration file", "--calibration")
    try:
        return load_calibration(path)
    except CalibrationError as exc:
        raise fail(str(exc)) from None


def _check_image_out(path: Path) -> None:
    """An image ``--out`` checked before anything is rendered."""
    if path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise fail(f"{path}: the output must be a .png or .jpg file")
    check_output(path)


def _write_png(path: Path, image) -> None:
    import cv2

    from bridge.archive import atomic_write

    _check_image_out(path)
    # Encoded in memory, then written beside the file and renamed over it: never a truncated image.
    try:
        ok, data = cv2.imencode(path.suffix.lower(), image)
    except cv2.error as exc:
        raise fail(f"{path}: cannot encode ({exc})") from None
    if not ok:
        raise fail(f"{path}: cannot encode the image")
    try:
        atomic_write(path, data.tobytes())
    except OSError as exc:
        raise write_failed(path, exc) from None


def _angles(first: list[str], extra: list[str]) -> list[float]:
    """``--alpha 10 -20 30`` (Click gives the first value to the option and leaves the others as
    extra arguments), ``--alpha 10,-20,30`` or ``--alpha 10 --alpha -20 ...``."""
    values = []
    for item in [*first, *extra]:
        for part in item.split(","):
            if part.strip():
                try:
                    values.append(float(part))
                except ValueError:
                    raise fail(f"--alpha: {part!r} is not a number (degrees)") from None
    return values


OCCLUDE_OPTION = typer.Option(None, "--occlude", help="Cover a marker: BAR:SIDE, e.g. 3:0 (bar 0 = base; side 0 = left).")


def _occluded(occlude: list[str] | None, n_joints: int) -> tuple[tuple[int, int], ...]:
    covered = []
    for item in occlude or []:
        try:
            bar, side = (int(v) for v in item.split(":"))
        except ValueError:
            raise fail(f"--occlude {item!r}: expected BAR:SIDE, e.g. 3:0") from None
        if not (0 <= bar <= n_joints and side in (0, 1)):
            raise fail(f"--occlude {item!r}: bar in 0..{n_joints}, side 0 or 1")
        covered.append((bar, side))
    return tuple(covered)


def _clock_choice(clock: str | None, kind: str) -> str | None:
    """``--clock``: the bridge instance to synchronise with ('' for the one that answers), or None
    for this machine's clock. A live source defaults to the bridge's; a video's stamps are its
    own and the twin's its truth's, so those refuse the option."""
    from bridge.safety import INSTANCE_NAME

    if kind != "usb":
        if clock is not None:
            raise fail(f"--clock is for a live camera (usb:N): a {kind} source's stamps are "
                       f"{'the video' if kind == 'file' else 'the twin truth'}'s own clock")
        return None
    text = "bridge" if clock is None else clock.strip()
    if text == "local":
        return None
    if text == "bridge":
        return ""
    name = text.removeprefix("bridge:")
    if text.startswith("bridge:") and INSTANCE_NAME.fullmatch(name):
        return name
    raise fail(f"--clock {clock!r}: expected bridge, bridge:NAME (the bridge's --instance) or local")


@camera_app.callback()
def camera(
    ctx: typer.Context,
    source: str | None = typer.Option(None, "--source", help="usb:N, /dev/videoN, file:VIDEO or twin (frames rendered from xneck/twin/truth)."),
    calibration: Path | None = CALIBRATION_OPTION,
    rate: float = typer.Option(30.0, "--rate", callback=number(high=1000.0, unit=" frames per second"),
                               help="twin: frames per second of simulated time (at most 1000)."),
    latency: float | None = typer.Option(None, "--latency", help="s from exposure to publication (twin) or to grab (usb); default: the parameter file's sensors.camera_latency."),
    seed: int = typer.Option(0, "--seed", min=0, help="twin: seed of the sensor noise (≥ 0)."),
    noise: float = typer.Option(2.0, "--noise", callback=NON_NEGATIVE, help="twin: sensor noise σ, grey levels."),
    blur: float = typer.Option(0.8, "--blur", callback=NON_NEGATIVE, help="twin: defocus blur σ, pixels."),
    occlude: list[str] | None = OCCLUDE_OPTION,
    frame_rate_hz: float = typer.Option(5.0, "--frame-rate-hz", min=0.0, max=30.0, callback=NON_NEGATIVE, help="JPEG frames per second (of the source's clock) on xneck/camera/frame, for the console and campaign archives (0: none)."),
    jpeg_quality: int = typer.Option(75, "--jpeg-quality", min=10, max=95, help="JPEG quality of those frames."),
    realtime: bool = typer.Option(True, "--realtime/--fast", help="file: replay at the video's frame rate, or as fast as detection runs."),
    # beyond 1e10 s (the year 2286 as a Unix time) a float's resolution is no longer a frame's
    # (user audit of session 45: --t0 1e17 stamped every frame alike)
    t0: float = typer.Option(0.0, "--t0", callback=number(-1e10, strict=False, high=1e10, unit=" s"),
                             help="file: time stamp of the first frame (s, |t0| ≤ 1e10)."),
    max_frames: int | None = typer.Option(None, "--max-frames", min=1, help="Stop after this many frames."),
    idle_timeout: float | None = typer.Option(None, "--idle-timeout", callback=POSITIVE,
                                              help="twin: stop after this long without truth (s)."),
    clock: str | None = typer.Option(None, "--clock", help="usb: stamp exposures on the bridge's clock, measured over "
                                     "the bus (bridge, or bridge:NAME for the bridge --instance NAME; the default) or on "
                                     "this machine's (local: the bridge runs here). Not for file or twin sources."),
    instance: str = INSTANCE_OPTION,
    listen: list[str] | None = LISTEN_OPTION,
    connect: list[str] | None = CONNECT_OPTION,
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
    verbose: bool = VERBOSE_OPTION,
) -> None:
    """The camera on the bus: publish α_IP (xneck/camera/alpha_ip) measured on frames from --source.

    With --source twin, run the twin without its white-noise camera (`xneck twin --no-camera`);
    `xneck up --alpha-ip camera` starts this process beside its twin so."""
    if ctx.invoked_subcommand is not None:
        return
    if source is None:
        typer.echo(ctx.get_help())
        raise typer.Exit(0)
    import logging

    from bridge.runtime import setup_logging, stop_on_signals
    from twin.camera.clock import BridgeClock, ClockSyncError
    from twin.camera.detect import Detector
    from twin.camera.process import CameraNode
    from twin.camera.source import FileSource, SourceError, SourceLost, TwinShutter, UsbSource, parse_source

    try:
        kind, where = parse_source(source)
    except ValueError as exc:
        raise fail(str(exc)) from None
    clock_bridge = _clock_choice(clock, kind)  # None: this machine's clock
    setup_logging(verbose)
    check_endpoints(listen, connect)
    check_credentials()
    params = load_cli_params(params_file, overrides)
    cal = _calibration(calibration)
    lat = params.sensors.camera_latency if latency is None else latency
    if not (0.0 <= lat <= 1.0):
        raise fail("--latency must be between 0 and 1 s")
    detector = Detector(params.n_joints, params.geometry.L, params.geometry.b, cal)
    renderer = shutter = frames = None
    try:
        if kind == "twin":
            from twin.camera.render import Renderer, RenderOptions
            from twin.model.numeric import build

            shutter = TwinShutter(rate, lat)
            options = RenderOptions(noise_dn=noise, blur_px=blur, occlude=_occluded(occlude, params.n_joints))
            renderer = Renderer(build(params), cal, options=options, seed=seed)
        elif kind == "file":
            frames = FileSource(where, t0)
        else:
            # On the bridge's clock the grabs are stamped on the monotonic clock, which the offset maps.
            frames = UsbSource(where, cal.width, cal.height, latency_s=lat,
                               clock=time.time if clock_bridge is None else time.monotonic)
    except (SourceError, ValueError) as exc:
        raise fail(str(exc)) from None
    stop = stop_on_signals()
    log = logging.getLogger("xneck.camera")
    lost: SourceLost | None = None
    with open_bus(listen, connect) as session:
        bridge_clock = None
        if clock_bridge is not None:
            bridge_clock = BridgeClock(session, clock_bridge)
            try:
                bridge_clock.sync(stop=stop)
            except ClockSyncError as exc:  # no bridge to stamp on: nothing published, one line, exit 1
                assert frames is not None
                frames.close()
                typer.secho(f"error: {exc}", err=True, fg="red")
                raise typer.Exit(1) from None
            bridge_clock.start()
        node = CameraNode(session, detector, instance, frame_rate_hz=frame_rate_hz, jpeg_quality=jpeg_quality,
                          clock=bridge_clock)
        log.info("camera %s up: --source %s", node.instance, source)
        count = 0
        try:
            if renderer is not None and shutter is not None:
                count = node.run_twin(renderer, shutter, stop, max_frames, idle_timeout)
            else:
                assert frames is not None
                # A video has no live moment to miss, but its first frames would be lost while Zenoh
                # routes this new session to the subscribers: give it a moment first.
                if kind == "file" and stop.wait(0.5):
                    return
                count = node.run_source(frames, stop, max_frames, frames.fps if (kind == "file" and realtime) else None)
        except SourceLost as exc:  # a live camera gone for good: not a normal end (exit 1, after the counts)
            lost, count = exc, node.frames
        except RuntimeError as exc:
            raise fail(str(exc)) from None
        finally:
            if bridge_clock is not None:
                bridge_clock.stop()
            node.close()
            if frames is not None:
                frames.close()
        loss = frames.loss() if isinstance(frames, FileSource) else None
        if loss is not None:
            log.warning("%s", loss.text)
        log.info("camera %s: %d frames, %d missing joints, %d dropped, %d JPEG frames", node.instance, count,
                 node.missing_joints, node.dropped, node.images)
    if loss is not None and loss.damaged:
        # Everything that decoded was published, with its own time; the exit code is what tells a
        # script that this video was not whole (a frame the recorder dropped is not damage: exit 0).
        raise typer.Exit(1)
    if (isinstance(frames, FileSource) and stop.is_set() and not frames.ended
            and (max_frames is None or count < max_frames)):
        # Ctrl-C or SIGTERM before the video's end: not a replay that went through (user audit of
        # session 45: '49 frames', exit 0, like a whole one)
        declared = f" of the {frames.declared} it declares" if frames.declared else ""
        typer.secho(f"interrupted: {count} frames of {source} published{declared}", err=True, fg="yellow")
        raise typer.Exit(130)
    if kind == "file" and count == 0 and lost is None and not stop.is_set():
        # a video without one frame published nothing: not a replay that went well (user audit of
        # session 45: '0 frames', exit 0)
        typer.secho(f"error: {source}: no frame decoded: nothing was published", err=True, fg="red")
        raise typer.Exit(1)
    if lost is not None:
        typer.secho(f"error: {lost}", err=True, fg="red")
        raise typer.Exit(1)


@camera_app.command("render", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def render(
    ctx: typer.Context,
    alpha_text: list[str] = typer.Option(..., "--alpha", help="Joint angles in degrees, base to head: --alpha 10 -20 30.",
                                         show_default=False),
    out: Path = typer.Option(..., "--out", help="Output image (.png)."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the sensor noise (≥ 0)."),
    noise: float = typer.Option(2.0, "--noise", callback=NON_NEGATIVE, help="Sensor noise σ, grey levels."),
    blur: float = typer.Option(0.8, "--blur", callback=NON_NEGATIVE, help="Defocus blur σ, pixels."),
    occlude: list[str] | None = OCCLUDE_OPTION,
    calibration: Path | None = CALIBRATION_OPTION,
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Render the twin's camera view of the neck at --alpha (degrees)."""
    import numpy as np

    from twin.camera.render import Renderer, RenderOptions
    from twin.model.numeric import build

    alpha = _angles(alpha_text, list(ctx.args))
    _check_image_out(out)
    params = load_cli_params(params_file, overrides)
    if len(alpha) != params.n_joints:
        raise fail(f"--alpha needs {params.n_joints} angles (one per joint), got {len(alpha)}")
    limit = params.limits.alpha_max_deg
    if not all(math.isfinite(a) and abs(a) <= 90.0 for a in alpha):
        raise fail("every angle must be finite and within ±90°")
    if any(abs(a) > limit for a in alpha):
        typer.secho(f"warning: an angle is beyond the joint limit ±{limit:g}°", err=True, fg="yellow")
    try:
        options = RenderOptions(noise_dn=noise, blur_px=blur, occlude=_occluded(occlude, params.n_joints))
    except ValueError as exc:
        raise fail(str(exc)) from None
    renderer = Renderer(build(params), _calibration(calibration), options=options, seed=seed)
    _write_png(out, renderer.render(np.radians(alpha)))
    typer.echo(f"wrote {out}")


@camera_app.command("detect")
def detect(
    image: Path = typer.Argument(..., help="A frame (.png/.jpg) of the calibrated camera."),
    calibration: Path | None = CALIBRATION_OPTION,
    json_out: bool = typer.Option(False, "--json", help="Print JSON: {alpha_deg: [...], confidence: [...]}, null for a missing joint."),
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Measure α (degrees) on one frame."""
    from twin.camera.detect import Detector
    from twin.camera.imagefile import ImageFileError, read_frame

    params = load_cli_params(params_file, overrides)
    cal = _calibration(calibration)
    check_input(image, "image file")
    try:  # the header's size is checked against the calibration's before decoding (a bomb declares 32000×32000)
        frame = read_frame(image, cal.width, cal.height)
    except ImageFileError as exc:
        raise fail(f"{image}: {exc}") from None
    detector = Detector(params.n_joints, params.geometry.L, params.geometry.b, cal)
    try:
        result = detector.detect(frame)
    except ValueError as exc:
        raise fail(f"{image}: {exc}") from None
    if result.reason:  # every joint is missing, and not for a marker: say why (stderr, also with --json)
        typer.secho(f"warning: {image}: {result.reason}", err=True, fg="yellow")
    if json_out:
        echo_json(result.as_json(), indent=None)
        return
    for i, (a, c) in enumerate(zip(result.alpha_deg, result.confidence), start=1):
        typer.echo(f"alpha_{i} = {'missing' if a is None else f'{a:8.3f}°'}   confidence {c:.2f}")


@camera_app.command("markers")
def markers(
    out: Path = typer.Option(..., "--out", help="Output image (.png), an A4 sheet."),
    dpi: int = typer.Option(300, "--dpi", min=72, max=1200, help="Print resolution, dots per inch (print the sheet unscaled)."),
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """A printable sheet of the coloured markers at their true size (print at 100 %)."""
    from twin.camera.render import marker_sheet

    params = load_cli_params(params_file, overrides)
    _write_png(out, marker_sheet(params.n_joints, dpi=dpi))
    typer.echo(f"wrote {out} ({dpi} dpi, A4)")


BOARD_MAX_PX = 16384  # a side of `xneck camera board`'s image: 1.39 m at 300 dpi (A0 is 1.19 m), 0.8 GB at most


@camera_app.command("board")
def board(
    out: Path = typer.Option(..., "--out", help="Output image (.png)."),
    columns: int = typer.Option(9, "--columns", min=3, max=30, help="Inner corners per row."),
    rows: int = typer.Option(6, "--rows", min=3, max=30, help="Inner corners per column."),
    square: float = typer.Option(0.02, "--square", help="Square size, m."),
    dpi: int = typer.Option(300, "--dpi", min=72, max=1200, help="Print resolution, dots per inch (print the sheet unscaled)."),
) -> None:
    """A printable checkerboard for the intrinsic calibration."""
    from twin.camera.render import checkerboard

    if not (0.002 <= square <= 0.2):
        raise fail("--square must be between 0.002 and 0.2 m")
    # The image is (corners + 3) squares a side (margins included): at the options' upper ends it
    # asked numpy for 272 GiB, a MemoryError traceback. A sheet up to A0 at 300 dpi fits the limit.
    px = round(square * dpi / 0.0254)
    width, height = (columns + 3) * px, (rows + 3) * px
    if max(width, height) > BOARD_MAX_PX:
        raise fail(f"the board would be {width}×{height} px ({width / dpi * 0.0254:.2f}×{height / dpi * 0.0254:.2f} m "
                   f"at {dpi} dpi), more than {BOARD_MAX_PX} px a side: lower --square, --dpi, --columns or --rows")
    _write_png(out, checkerboard((columns, rows), square, dpi))
    typer.echo(f"wrote {out}")


@camera_app.command("align")
def align(
    video: Path = typer.Argument(..., help="Video of the campaign (any format OpenCV reads)."),
    campaign: Path = typer.Argument(..., help="The campaign's MCAP file."),
    out: Path | None = typer.Option(None, "--out", help="New MCAP file (default: CAMPAIGN.aligned.mcap); never overwritten."),
    reference: str = typer.Option("auto", "--reference", help="auto (the controller's α̂ if recorded, as on the prototype, else the twin's truth), truth or alpha_hat."),
    drift: bool = typer.Option(True, "--drift/--no-drift", help="Estimate the video clock's drift as well as the offset."),
    images: float = typer.Option(5.0, "--images", min=0.0, max=60.0, callback=NON_NEGATIVE, help="Frames per second (of video) archived as JPEG on /xneck/camera/image (0: none)."),
    calibration: Path | None = CALIBRATION_OPTION,
    json_out: bool = typer.Option(False, "--json", help="Print the provenance as JSON."),
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Align a video with a recorded campaign and write its α_IP into a copy of the campaign."""
    from bridge.archive import software_version
    from twin.camera.align import (
        AlignmentError,
        align,
        campaign_reference,
        measure_video,
        provenance_json,
        write_aligned,
    )
    from twin.camera.detect import Detector
    from twin.camera.source import SourceError

    params = load_cli_params(params_file, overrides)
    cal = _calibration(calibration)
    check_input(campaign, "campaign file")  # '.' or '/' have no name to derive the default --out from: say why now
    check_input(video, "video file")
    target = out or campaign.with_name(campaign.stem + ".aligned.mcap")
    if target.exists():
        raise fail(f"{target}: exists already (choose another --out)")
    check_output(target)  # before the video is measured, which takes a while
    try:
        ref = campaign_reference(campaign, reference)
        measured = measure_video(video, Detector(params.n_joints, params.geometry.L, params.geometry.b, cal), image_rate_hz=images)
        result = align(measured, ref, estimate_drift=drift)
        provenance = write_aligned(campaign, target, video, measured, result, ref.name, software_version())
    except (AlignmentError, SourceError) as exc:
        raise fail(str(exc)) from None
    except FileExistsError:  # another process wrote it meanwhile: it is kept, and so is nothing of ours
        raise fail(f"{target}: exists already (choose another --out)") from None
    except OSError as exc:
        raise write_failed(target, exc) from None
    if measured.loss:  # the alignment used the frames that decoded, each at its own time
        typer.secho(f"warning: {measured.loss.removeprefix('file:')}", err=True, fg="yellow")
    if json_out:
        # the archive's record holds strings (MCAP metadata); JSON has numbers (user audit: "offset_s": "4.321000")
        echo_json({**provenance_json(provenance), "out": str(target)}, indent=None)
        return
    typer.echo(f"offset {result.offset_s:+.4f} s, drift {result.drift * 1e6:+.1f} ppm, rms {result.rms_deg:.3f}° against {ref.name} "
               f"over {result.frames_used} frames (next best: {result.runner_up_offset_s:+.3f} s, {result.runner_up_rms_deg:.2f}°)")
    typer.echo(f"wrote {target}")
