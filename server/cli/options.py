"""Options shared by the ``xneck`` commands: endpoints, the twin's options, the parameter set."""

from __future__ import annotations

import contextlib
import math
import tempfile
from pathlib import Path

import typer

from bridge.safety import INSTANCE_NAME
from twin.model.params import ParameterError, Params, load_params, parse_override

LISTEN_OPTION = typer.Option(
    None, "--listen", help="Zenoh endpoint to listen on (repeatable), e.g. tcp/127.0.0.1:7447. "
    "Default: $XNECK_ZENOH_LISTEN or an ephemeral loopback port.")
CONNECT_OPTION = typer.Option(
    None, "--connect", help="Zenoh endpoint to connect to (repeatable). Default: $XNECK_ZENOH_CONNECT.")
AUTOCONNECT_OPTION = typer.Option(
    True, "--autoconnect/--no-autoconnect",
    help="Link to the peers the bus's gossip names (default), or only to --connect's, the others linking to this "
    "process (xneck up's bridge and controller: docs/safety.md, 'Peers that stop reading').")
VERBOSE_OPTION = typer.Option(False, "--verbose", "-v", help="Debug logging.")


def fail(message: str) -> typer.Exit:
    """Print one ``error:`` line; the caller raises the returned Exit (status 2, a usage error)."""
    typer.secho(f"error: {message}", err=True, fg="red")
    return typer.Exit(2)


def _check_instance(ctx: typer.Context, value: str) -> str:
    """An ``--instance`` is a key chunk and a file name: refused here, not as a traceback when the
    process declares its token."""
    if value and not ctx.resilient_parsing and not INSTANCE_NAME.fullmatch(value):
        raise fail(f"--instance {value!r}: 1-64 letters, digits, '_', '.' or '-'")
    return value


INSTANCE_OPTION = typer.Option("", "--instance", callback=_check_instance,
                               help="Name on the bus (default: a random one).")


def number(low: float = 0.0, *, strict: bool = True, inf: bool = False, high: float = math.inf, unit: str = ""):
    """Typer callback for a float option: a number above ``low`` (at least ``low`` unless
    ``strict``) and at most ``high``, finite unless ``inf``; None (an unset option) passes. Click's
    own ``min`` lets NaN through (every comparison with it is false), which silently disabled
    checks such as ``--threshold nan`` or made ``--idle-timeout nan`` wait for ever."""

    def callback(ctx: typer.Context, param: typer.CallbackParam, value: float | None) -> float | None:
        if value is None or ctx.resilient_parsing:
            return value
        if (math.isnan(value) or not (value > low if strict else value >= low) or (math.isinf(value) and not inf)
                or value > high):
            bound = "" if low == -math.inf else f" {'>' if strict else '≥'} {low:g}"
            bound += "" if high == math.inf else f"{' and' if bound else ''} ≤ {high:g}{unit}"
            raise fail(f"{param.opts[0] if param.opts else param.name}: must be a {'' if inf else 'finite '}"
                       f"number{bound}, got {value}")
        return value

    return callback


POSITIVE = number()  # durations, rates, thresholds: finite and > 0
NON_NEGATIVE = number(strict=False)  # amounts that may be zero (noise, pretension)
FINITE = number(-math.inf, strict=False)  # a time stamp, a coordinate
PORT_MAX = 65535


def output_problem(path: Path, *, directory: bool = False) -> str:
    """Why ``path`` cannot be written ('' if it can): an output file (``directory=False``) or an
    output directory. Its folder must exist or be creatable, be a directory and take a new file;
    a trial file proves it (permissions, read-only mounts, /proc), so a long fit or campaign is not
    lost at its end. Folders created for the trial are removed again: a refused command leaves nothing."""
    if directory and path.exists() and not path.is_dir():
        return f"{path} exists and is not a directory"
    if not directory and path.is_dir():
        return f"{path} is a directory"
    folder = path if directory else path.parent
    missing = []
    existing = folder
    while not existing.exists() and existing != existing.parent:
        missing.append(existing)
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a directory"
    created: list[Path] = []
    try:
        for p in reversed(missing):
            p.mkdir()
            created.append(p)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        from bridge.archive import storage_reason

        return f"cannot write in {folder}: {storage_reason(exc)}"
    finally:
        for p in reversed(created):
            with contextlib.suppress(OSError):
                p.rmdir()
    return ""


def check_output(path: Path, option: str = "--out", *, directory: bool = False) -> None:
    """:func:`output_problem` as a usage error, to be called before any long work starts."""
    problem = output_problem(path, directory=directory)
    if problem:
        raise fail(f"{option}: {problem}")


def input_problem(path: Path, what: str = "file") -> str:
    """Why ``path`` cannot be read as an input ``what`` (e.g. "video file"), '' if it can be
    opened as one: missing, a directory (which was reported as "no such file", user audit), or
    not a regular file (a FIFO would block the command, a device never ends). Permissions and
    content are the loader's to judge."""
    a = "an" if what[:1] in "aeiou" else "a"
    if path.is_dir():
        return f"{path}: is a directory, not {a} {what}"
    if not path.exists():
        return f"{path}: no such {what}"
    if not path.is_file():
        return f"{path}: not a regular file ({a} {what} is expected)"
    return ""


def check_input(path: Path, what: str = "file", option: str = "") -> None:
    """:func:`input_problem` as a usage error (``option``, e.g. "--calibration", leads the line)."""
    problem = input_problem(path, what)
    if problem:
        raise fail(f"{option}: {problem}" if option else problem)


def write_failed(path: Path, exc: OSError) -> typer.Exit:
    """A write that failed despite :func:`check_output` (disk full, a folder removed meanwhile):
    one line naming the file; the writes are atomic, so no half-written file is left."""
    from bridge.archive import storage_reason

    return fail(f"cannot write {path}: {storage_reason(exc)}")


def atomic_write_text(path: Path, text: str) -> None:
    """``path`` replaced by ``text`` all at once (bridge.archive.atomic_write): the old content or
    the new one, never a half-written file. Raises the OSError."""
    from bridge.archive import atomic_write

    atomic_write(path, text.encode("utf-8"))


def echo_json(value, indent: int | None = 2) -> None:
    """Print ``value`` as strict JSON (twin.jsonout: NaN and ±inf as null), which every JSON
    reader accepts, as ``--json`` promises."""
    from twin.jsonout import strict_json

    typer.echo(strict_json(value, indent=indent))


def check_endpoints(listen: list[str] | None, connect: list[str] | None) -> None:
    """``--listen``/``--connect`` (or XNECK_ZENOH_*) well formed, before a driver or model is built."""
    from bridge.runtime import endpoints
    from bridge.session import zenoh_config

    try:
        zenoh_config(endpoints(listen), endpoints(connect))
    except ValueError as exc:
        raise fail(str(exc)) from None


def check_credentials(acts: bool = True) -> None:
    """``XNECK_ZENOH_CREDENTIALS`` and ``XNECK_ZENOH_TLS`` usable (bridge.bus_credentials,
    bridge.bus_tls) when set: one ``error:`` line, before any process starts, rather than a
    traceback from each process of a stack. ``acts``: the command
    publishes (a stack, a bridge, a controller, a campaign), which a viewer's user may not: what it
    published would reach no one, so it is refused here rather than left to fail silently."""
    from bridge import bus_tls
    from bridge.bus_credentials import ENV_USER, CredentialsError, from_env

    try:
        creds = from_env()
        bus_tls.from_env()
    except (CredentialsError, bus_tls.TlsError) as exc:
        raise fail(str(exc)) from None
    if acts and creds is not None and creds.role == "viewer":
        raise fail(f"bus user {creds.user!r} ({creds.path}) is a viewer: it may watch (xneck server --connect ...), "
                   f"not act; set {ENV_USER} to an operator's entry or use the lab's credentials file")


def open_bus(listen: list[str] | None, connect: list[str] | None, autoconnect: bool = True):
    """The Zenoh session of a bus process (bridge.session.open_session): an endpoint Zenoh refuses
    (a port above 65535, an unknown host or protocol, a port in use) is one ``error:`` line.
    ``autoconnect``: see :data:`AUTOCONNECT_OPTION`."""
    import zenoh

    from bridge.runtime import endpoints
    from bridge.session import open_session

    check_endpoints(listen, connect)
    try:
        return open_session(endpoints(listen), endpoints(connect), autoconnect=autoconnect)
    except zenoh.ZError as exc:
        # Zenoh appends the Rust source location (" at /root/.cargo/…/lib.rs:62."): no use to a user.
        raise fail(f"cannot open the bus session: {str(exc).split(' at /')[0]}") from None


# The twin's options, shared by `xneck twin` and `xneck bridge --driver twin`.
LOCKSTEP_OPTION = typer.Option(False, "--lockstep", help="Twin only: one tick per command (deterministic; CI mode).")
SEED_OPTION = typer.Option(0, "--seed", min=0, help="Twin: seed of the sensor noise (≥ 0).")
CABLE_MODEL_OPTION = typer.Option(None, "--cable-model", help="Twin: rigid, linear or variable (default: the parameter file's).")
NO_FRICTION_OPTION = typer.Option(False, "--no-friction", help="Twin: simulate without motor friction.")


def check_truth(value: str) -> str:
    """Typer callback: ``--truth`` is one of twin.sim.truth.TRUTHS or a truth file that loads."""
    from twin.sim.truth import TRUTHS, TruthError
    from twin.sim.truth import check_truth as load_check

    try:
        load_check(value)
    except TruthError as exc:
        raise typer.BadParameter(f"{value!r}: {exc} (choose {' or '.join(TRUTHS)} or a truth file)") from None
    return str(Path(value).resolve()) if value not in TRUTHS else value


TRUTH_OPTION = typer.Option("model", "--truth", callback=check_truth, help="Twin: what it simulates, the parameter file as it is (model), the robot's unmodelled physics (robot: twin/sim/robot_truth.toml), or a truth FILE; see twin/sim/truth.py.")
def check_alpha_ip(value: str) -> str:
    """Typer callback: ``--alpha-ip`` is one of twin.sim.sensors.ALPHA_IP_KINDS."""
    from twin.sim.sensors import ALPHA_IP_KINDS

    if value not in ALPHA_IP_KINDS:
        raise typer.BadParameter(f"{value!r}: choose {' or '.join(ALPHA_IP_KINDS)}")
    return value


ALPHA_IP_OPTION = typer.Option("noise", "--alpha-ip", callback=check_alpha_ip, help="Twin: its α_IP, the true α plus "
                               "the camera's white noise (noise) or measured on frames rendered from its truth by the "
                               "robot's detector (camera; docs/camera.md), 30 fps of simulated time, after the exposure latency.")
MAX_TICKS_OPTION = typer.Option(None, "--max-ticks", min=1, help="Stop after this many ticks.")
IDLE_TIMEOUT_OPTION = typer.Option(None, "--idle-timeout", callback=POSITIVE,
                                   help="Lockstep: stop after this long without a command (s).")
STARTUP_TIMEOUT_OPTION = typer.Option(
    None, "--startup-timeout", callback=POSITIVE,
    help="Lockstep: the same limit before the first command (s; default: --idle-timeout).")


def check_new_archive(value: Path | None) -> Path | None:
    """Typer callback: ``--out`` of a campaign must not exist and must be writable. The runner
    refuses an existing one too (server.campaign_runner.run_campaign); checking here refuses it
    before anything is loaded or started, as a usage error rather than a traceback."""
    if value is not None and value.suffix.lower() != ".mcap":
        # an MCAP named x.json was written (input audit): the console, identify and camera align
        # know archives by their suffix
        raise fail(f"--out must be an .mcap file (the campaign is recorded as MCAP), got {value}")
    if value is not None and value.exists():
        raise fail(f"--out: {value} exists: choose another --out (archives are never overwritten)")
    if value is not None:
        check_output(value)
    return value


def check_estimator(value: str) -> str:
    """Typer callback: ``--estimator`` is one of the variable-stiffness estimators
    (twin.identification.options.VARIABLE_ESTIMATORS) or an alias of one, as ``xneck identify``
    takes them; refused before a campaign runs. Returns the estimator's own name."""
    from twin.identification.options import VARIABLE_ESTIMATORS
    from twin.identification.options import check_estimator as canonical

    try:
        return canonical(value, VARIABLE_ESTIMATORS)
    except ValueError:
        raise typer.BadParameter(f"{value!r}: choose {', '.join(VARIABLE_ESTIMATORS)}") from None


ARCHIVE_OUT_OPTION = typer.Option(
    None, "--out", callback=check_new_archive, help="MCAP file to write (.mcap), which must not exist (default: "
    "<data dir>/cli-campaigns/campaign-<id>.mcap; the data dir is XNECK_DATA_DIR, else ./data).")
PARAMS_OPTION = typer.Option(None, "--params", help="Parameter file (TOML); default: the 3-X prototype.")
SET_OPTION = typer.Option(None, "--set", help="Override one value, e.g. --set springs.l0=[0.05,0.05,0.05].")


def load_cli_params(params_file: Path | None, overrides: list[str] | None) -> Params:
    """Parameters for a command, or a clean exit with the reason (no traceback)."""
    if params_file is not None:
        check_input(params_file, "parameter file", "--params")
    try:
        return load_params(params_file, dict(parse_override(o) for o in overrides or []))
    except ParameterError as exc:
        typer.secho(f"error: {exc}", err=True, fg="red")
        raise typer.Exit(2) from None


LAW_OPTION = typer.Option(2, "--law", help="Control law: 1 (no friction), 2 (friction), 3 (friction + elastic cables).")
NO_PULLEYS_OPTION = typer.Option(False, "--no-pulleys", help="Neglect the pulleys in the controller's model (Table 3).")
TRAJECTORY_OPTION = typer.Option(
    None, "--trajectory", help="identification, control_test, or a JSON/TOML file of waypoints (degrees).")


def law_config(law: int, no_pulleys: bool):
    from controller.laws import LawConfig

    try:
        return LawConfig(law=law, no_pulleys=no_pulleys)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--law") from None


def load_checked_trajectory(name_or_path: str, params, law_config):
    """A trajectory by name or file, validated against the joint limits and the forces on its
    nominal path; a clean CLI error naming the waypoint or segment otherwise."""
    from controller.laws import nominal_force_check
    from controller.trajectory import (
        NAMED_TRAJECTORIES,
        TrajectoryError,
        TrajectoryLimits,
        load_trajectory,
        trajectory_by_name,
        validate,
    )

    try:
        traj = (trajectory_by_name(name_or_path) if name_or_path.replace("-", "_") in NAMED_TRAJECTORIES
                else load_trajectory(Path(name_or_path)))
        limits = TrajectoryLimits(alpha_max_rad=math.radians(params.limits.alpha_max_deg))
        validate(traj, limits, params.n_joints, nominal_force_check(params, law_config))
    except TrajectoryError as exc:
        typer.secho(f"error: trajectory rejected: {exc}", err=True, fg="red")
        raise typer.Exit(2) from None
    return traj
