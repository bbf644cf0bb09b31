"""`xneck campaign control|identification`: a recorded campaign and its results."""

from __future__ import annotations

import contextlib
import json
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from server.cli.options import (
    ALPHA_IP_OPTION,
    ARCHIVE_OUT_OPTION,
    LAW_OPTION,
    NO_PULLEYS_OPTION,
    PARAMS_OPTION,
    POSITIVE,
    SET_OPTION,
    check_alpha_ip,
    check_credentials,
    check_endpoints,
    check_estimator,
    check_output,
    check_truth,
    echo_json,
    fail,
    law_config,
    load_checked_trajectory,
    load_cli_params,
)

if TYPE_CHECKING:
    from server.campaign_runner import CampaignResult, CausedStop

CAMPAIGN_ALPHA_IP_OPTION = typer.Option(
    "camera", "--alpha-ip", callback=check_alpha_ip,
    help="The twin's α_IP: camera (measured on frames rendered from its truth by the robot's detector, 30 fps, "
         "with the exposure latency) or noise (the true α plus the camera's white noise).")


ROBOT_CONNECT_OPTION = typer.Option(
    None, "--connect", help="With --robot: Zenoh endpoint where the robot's bridge listens (repeatable), e.g. "
    "tcp/<board>:7447. Default: $XNECK_ZENOH_CONNECT. A twin campaign runs on a bus of its own.")


def robot_endpoints(twin: bool, connect: list[str] | None) -> tuple[str, ...]:
    """Where a ``--robot`` campaign meets the bridge: ``--connect``, else XNECK_ZENOH_CONNECT;
    refused (a usage error, before anything starts) when neither says, or for a twin campaign,
    whose bus is its own. A campaign connected to no bridge waited for one in silence."""
    from bridge.session import ENV_CONNECT, endpoints_from_env

    if twin:
        if connect:
            raise fail("--connect applies to --robot: a twin campaign runs on a bus of its own")
        return ()
    given = list(connect or endpoints_from_env(ENV_CONNECT) or [])
    if not given:
        raise fail(f"--robot: say where the robot's bridge listens, --connect tcp/<board>:7447 (or {ENV_CONNECT})")
    check_endpoints(None, given)
    return tuple(given)


campaign_app = typer.Typer(help="Run a campaign (identification or control), record it as MCAP, print its results.",
                           no_args_is_help=True)

def campaign_control(
    law: int = LAW_OPTION,
    no_pulleys: bool = NO_PULLEYS_OPTION,
    twin: bool = typer.Option(True, "--twin/--robot", help="Against a lockstep twin started for the campaign, or "
                              "the robot's bridge already on the bus."),
    trajectory: str = typer.Option("control_test", "--trajectory", help="Trajectory name or file (degrees)."),
    out: Path | None = ARCHIVE_OUT_OPTION,
    as_json: bool = typer.Option(False, "--json", help="Print the metrics as JSON."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the twin's sensor noise (≥ 0)."),
    truth: str = typer.Option("model", "--truth", callback=check_truth, help="What the twin simulates: the "
                              "parameter file as it is (model), the robot's unmodelled physics (robot), or a truth "
                              "FILE (e.g. from `xneck twin calibrate`)."),
    alpha_ip: str = ALPHA_IP_OPTION,
    timeout: float = typer.Option(900.0, "--timeout", callback=POSITIVE, help="Abort the campaign after this many "
                                  "seconds (wall); on the robot its trajectory's duration, 10 % and 10 s more must fit in it."),
    connect: list[str] | None = ROBOT_CONNECT_OPTION,
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Run a control campaign (3-X paper §7), record it, print e, e_α, forces and saturation."""
    from server.campaign_runner import CampaignSpec

    _check_default_archive(out)
    check_credentials()  # its processes meet on the bus
    params = load_cli_params(params_file, overrides)
    config = law_config(law, no_pulleys)
    traj = load_checked_trajectory(trajectory, params, config)
    try:
        spec = CampaignSpec(kind="control", law=config, trajectory=traj, twin=twin, seed=seed, timeout_s=timeout,
                            params_file=params_file, overrides=tuple(overrides or ()), truth=truth, alpha_ip=alpha_ip,
                            connect=robot_endpoints(twin, connect))
    except ValueError as exc:  # the trajectory does not fit in --timeout on the robot
        raise fail(str(exc)) from None
    result, signum = _run_recorded(spec, params, out, as_json)
    _print_end(result, as_json, signum)
    if signum:
        raise typer.Exit(128 + signum)  # as a shell says a process a signal ended (130 for SIGINT)
    if result.outcome != "finished":
        raise typer.Exit(1)


CLI_RESERVE_BYTES = 512 * 1024  # as the console's campaigns/.reserve (server.campaigns.RESERVE_BYTES)


def _print_end(result: CampaignResult, as_json: bool, signum: int = 0) -> None:
    """A campaign's end as every ending prints it: the table (``archive:``, ``process logs:``) or,
    with ``--json``, its summary (``outcome``, ``path``, ``logs_dir``); then, unless it finished, an
    ``error:`` line on stderr (``warning:`` if degraded). ``signum``: the signal that stopped it."""
    if as_json:
        echo_json(result.summary())
    else:
        typer.echo(result.table())
    if result.outcome != "finished" or signum:
        # on stderr as `campaign identification` says it: a script looking for `error:` had missed
        # a control test's abort, printed only in the table (audit of session 42)
        kind = "warning" if result.outcome == "degraded" and not signum else "error"
        late = f" ({_signal_cause(signum)} after the campaign ended)" if signum and \
            not result.message.startswith(_signal_cause(signum)) else ""
        typer.secho(f"{kind}: campaign {result.campaign_id} {result.outcome}: {result.message}{late}", err=True,
                    fg="yellow" if kind == "warning" else "red")


def _signal_cause(signum: int) -> str:
    """The campaign's message for a stop by signal ``signum``: ``interrupted by SIGINT``."""
    return f"interrupted by {signal.Signals(signum).name}"


@contextlib.contextmanager
def _stop_on_signals(stop: CausedStop) -> Iterator[list[int]]:
    """While the campaign runs, SIGINT and SIGTERM stop it (``stop``, a
    :class:`server.campaign_runner.CausedStop`) instead of killing this process: it then ends
    ``aborted`` with the signal as its cause, finishes its archive and stops its processes, and the
    CLI prints where as any other ending (user audit: Ctrl-C exited 130 with nothing said, and
    SIGTERM left the twin and controller running). A second signal raises KeyboardInterrupt (the old
    way out, should the end itself hang). Yields the list the first signal's number goes in."""
    got: list[int] = []

    def on_signal(signum: int, _frame: object) -> None:
        if got:
            raise KeyboardInterrupt
        got.append(signum)
        stop.stop(_signal_cause(signum))

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield got
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _run_recorded(spec, params, out: Path | None, as_json: bool) -> tuple[CampaignResult, int]:
    """:func:`server.campaign_runner.run_campaign`, a storage fault being one ``error:`` line (exit
    1) and the archive finished where it lies with the outcome ``failed`` and the reason, as the
    console does (a full disk was a traceback and an unreadable file: audit of 2026-11-28).
    Returns the result and the signal (SIGINT, SIGTERM) that stopped the campaign, 0 for none."""
    from bridge.archive import ArchiveError
    from bridge.archive_read import is_complete
    from bridge.archive_recovery import finish_in_place
    from server.campaign_runner import CausedStop, RecordingFailed, default_archive, run_campaign

    # Room for the final records on a full disk, given up on a fault (as the console's campaigns/.reserve).
    reserve = (Path(out).parent if out else default_archive("reserve").parent) / f".xneck-reserve-{os.getpid()}"
    try:
        reserve.parent.mkdir(parents=True, exist_ok=True)
        with open(reserve, "wb") as f:
            f.write(b"\0" * CLI_RESERVE_BYTES)
            os.fsync(f.fileno())
    except OSError:  # no room even for it: the campaign's own start says so
        reserve.unlink(missing_ok=True)
    stop = CausedStop()
    line = _ProgressLine()
    try:
        with _stop_on_signals(stop) as got:
            try:
                result = run_campaign(spec, params, out, progress=None if as_json else line, stop=stop)
            finally:
                line.end()
        return result, (got[0] if got else 0)
    except ArchiveError as exc:
        reserve.unlink(missing_ok=True)
        fields = {"message": f"recording failed: {exc.reason}"[:2000]}
        if isinstance(exc, RecordingFailed) and exc.quality:
            fields["quality"] = json.dumps(exc.quality)
        if not exc.path.exists():
            kept = "none was written"
        elif is_complete(exc.path):
            kept = f"{exc.path} is readable"
        else:
            try:
                report = finish_in_place(exc.path, "failed", fields)
                kept = f"{exc.path} finished where it lies, readable ({report.messages} messages, outcome failed)"
            except ArchiveError as again:
                kept = (f"{exc.path} left unfinished ({again.reason}): free some space, then "
                        f"bridge.archive_recovery.recover repairs it (the console does at start-up)")
        typer.secho(f"error: the campaign failed: {exc.reason}; archive: {kept}", err=True, fg="red")
        raise typer.Exit(1) from None
    finally:
        reserve.unlink(missing_ok=True)


def _check_default_archive(out: Path | None) -> None:
    """Without --out the archive goes below the data directory (server.campaign_runner.default_archive):
    check that it can be written there before the campaign runs, as --out is checked."""
    if out is None:
        from server.campaign_runner import default_archive

        check_output(default_archive("check"), "the data directory (XNECK_DATA_DIR, else ./data)")


def _print_progress(fraction: float, message: str) -> None:
    """The progress bar on stderr, redrawn in place (``fraction`` 0-1); its line ends at 1.0 only."""
    bar = "#" * int(30 * fraction)
    typer.echo(f"\r[{bar:<30s}] {100 * fraction:5.1f}% {message[:60]:<60s}", nl=False, err=True)
    if fraction >= 1.0:
        typer.echo("", err=True)


class _ProgressLine:
    """:func:`_print_progress` that knows whether its line is still open: :meth:`end` closes it, so
    that what a campaign ending short of 100 % prints next starts on a line of its own (user audit:
    "…the bridge obeys controlcampaign control-…")."""

    def __init__(self) -> None:
        self.open = False

    def __call__(self, fraction: float, message: str) -> None:
        _print_progress(fraction, message)
        self.open = fraction < 1.0

    def end(self) -> None:
        if self.open:
            typer.echo("", err=True)
            self.open = False


def campaign_identification(
    twin: bool = typer.Option(True, "--twin/--robot", help="Against a lockstep twin started for the campaign, or "
                              "the robot's bridge already on the bus."),
    out: Path | None = ARCHIVE_OUT_OPTION,
    as_json: bool = typer.Option(False, "--json", help="Print the identification tables as JSON."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the twin's sensor noise (≥ 0)."),
    truth: str = typer.Option("robot", "--truth", callback=check_truth, help="What the twin simulates: the robot's "
                              "unmodelled physics (robot: twin/sim/robot_truth.toml, the default), the parameter file "
                              "as it is (model, an identity check), or a truth FILE; see twin/sim/truth.py."),
    alpha_ip: str = CAMPAIGN_ALPHA_IP_OPTION,
    timeout: float = typer.Option(900.0, "--timeout", callback=POSITIVE, help="Abort the campaign after this many "
                                  "seconds (wall); on the robot its trajectory's duration, 10 % and 10 s more must fit in it."),
    trajectory: str = typer.Option("identification", "--trajectory", help="identification (§5.2.2), or a "
                                   "trajectory file (e.g. from `xneck excitation design`), validated as any campaign's."),
    estimator: str = typer.Option("auto", "--estimator", callback=check_estimator, help="Table 2's estimator, "
                                  "as `xneck identify --estimator` (auto, the default: where the campaign rejects the paper's model, "
                                  "outputerror if the line's damping is light, else loadfriction; iv where it "
                                  "keeps it; or iv, ols, wls, loadfriction, outputerror)."),
    creep_time_s: float | None = typer.Option(None, "--creep-time-s", help="The line's creep time constant (s) "
                                              "measured apart, as `xneck identify --creep-time-s`."),
    connect: list[str] | None = ROBOT_CONNECT_OPTION,
    params_file: Path | None = PARAMS_OPTION,
    overrides: list[str] | None = SET_OPTION,
) -> None:
    """Run the identification trajectory (§5.2.2) in closed loop with law 1, record it, and
    identify friction and cable stiffness from the archive (Tables 1-2, Figs. 4-8). A twin's α_IP
    is measured on frames it renders (--alpha-ip camera, issue 15). A failed identification ends
    the campaign analysis_failed (in the archive too), with its reason and the record's gaps explained."""
    from server.campaign_runner import CampaignSpec
    from server.cli.identify import identify
    from twin.identification.options import check_variable_options

    try:
        check_variable_options(estimator, creep_time_s)  # a bad τ fails before the campaign runs, not after
    except ValueError as exc:
        typer.echo(f"error: --creep-time-s: {exc}", err=True)
        raise typer.Exit(2) from None
    _check_default_archive(out)
    check_credentials()  # its processes meet on the bus
    params = load_cli_params(params_file, overrides)
    config = law_config(1, False)
    traj = load_checked_trajectory(trajectory, params, config)
    try:
        spec = CampaignSpec(kind="identification", law=config, trajectory=traj, twin=twin,
                            seed=seed, timeout_s=timeout, params_file=params_file, overrides=tuple(overrides or ()),
                            truth=truth, alpha_ip=alpha_ip, estimator=estimator, creep_time_s=creep_time_s,
                            connect=robot_endpoints(twin, connect))
    except ValueError as exc:  # the trajectory does not fit in --timeout on the robot
        raise fail(str(exc)) from None
    result, signum = _run_recorded(spec, params, out, as_json)
    if result.outcome not in ("finished", "degraded") or signum:
        _print_end(result, as_json, signum)  # the archive and the logs said too, as a control campaign's
        raise typer.Exit(128 + signum if signum else 1)
    if result.outcome == "degraded":
        typer.secho(f"warning: campaign {result.campaign_id} degraded: {result.message}", err=True, fg="yellow")
    if not as_json:
        typer.echo(f"campaign {result.campaign_id} recorded in {result.path}; identifying…")
    identify(result.path, json_out=as_json, out=None, params_file=params_file, overrides=overrides, cutoff_hz=None,
             threshold=None, no_alpha_hat=False, validate=None, estimator=estimator, sigma="hac", no_bounds=False,
             creep_time_s=creep_time_s, alpha_ip_source=None,  # the campaign recorded one camera (server.quality)
             window=None)
