"""Headless campaigns: the real processes on a private loopback bus, recorded as one MCAP file.

:func:`run_campaign` opens a Zenoh session that listens on a free loopback port (the hub),
starts the MCAP recorder on it, then starts ``xneck twin --lockstep`` (unless the robot's bridge
is already on the bus) and ``xneck controller`` as separate processes connected to the hub. It
follows the controller's campaign events (progress, finished, aborted), stops everything within
bounded time, and computes the paper's metrics from the archive it wrote — so what it prints is
exactly what the file holds.

It also follows the bridge's ``MotorState`` (:class:`server.quality.CampaignMonitor`): drives
disabled during the campaign (the bridge's e-stop) abort it with the bridge's reason, and a
finished campaign whose real-time quality breaks :data:`server.quality.THRESHOLDS` ends
``degraded`` with its reasons, in the result and in the MCAP metadata (``quality``, JSON, and
``degraded_reasons``); a degraded identification is analysed as a finished one, and one whose
cables sat at f_max says so in its message (:func:`server.quality.saturation_note`).

An identification campaign is analysed here, once its archive is finished (:func:`analyse_identification`,
the console's and the CLI's one analysis): one whose analysis fails ends ``analysis_failed`` with the
pipeline's reason and the record's gaps explained (:mod:`server.record_gaps`), in the result and in
the archive's ``xneck.campaign`` record (``outcome``, ``message``, ``analysis``), never ``finished``
(issue 17).

A storage fault while recording (the recorder's write failed: ENOSPC, EROFS, EIO) ends the run
with :class:`RecordingFailed`, which carries the run's quality counters (the archive is left as the
recorder left it: :mod:`server.campaigns` finishes it with the outcome ``failed``).

α_IP of a twin started for a campaign (``alpha_ip``; default: ``camera`` for identification,
``noise`` for control): ``camera`` measures it on frames the twin renders from its truth with
the robot's detector (``twin.camera``, issue 15) — inside a lockstep twin, every exposure of
simulated time, deterministic for the seed; beside a real-time twin, a separate ``xneck camera
--source twin`` process —; ``noise`` is the true α plus the camera's white noise. The finished
archive's ``alpha_ip`` says the α_IP recorded, whoever started the camera (:func:`alpha_ip_recorded`).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import math
import os
import queue
import shutil
import stat
import subprocess
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from bridge import bus
from bridge.archive import CAMPAIGN, ArchiveError, CampaignRecorder
from bridge.archive_read import is_complete
from bridge.session import BusPublisher, free_tcp_port, open_session, payload_of, publisher
from controller.laws import LawConfig
from controller.trajectory import Trajectory
from server.archive_metrics import metrics_from_archive
from server.archive_rewrite import rewrite_archive
from server.child_processes import isolate, log_tail, loop_environ, start_xneck, stop_child
from server.quality import (
    THRESHOLDS,
    TWIN_CAMERA,
    CampaignMonitor,
    assess,
    camera_note,
    saturation_note,
    thresholds_dict,
)
from server.service_choice import alive_services, choose_service
from server.truthstore import truth_label
from twin.model.params import Params
from twin.sim.sensors import ALPHA_IP_KINDS, ALPHA_IP_SOURCES
from twin.sim.truth import load_truth

STOP_GRACE_S = 5.0  # s a child gets after SIGTERM before SIGKILL
EXIT_GRACE_S = 1.0  # s to wait for a child's last event after it exited
FINAL_TIMING_WAIT_S = 2.0  # s the quality waits for the controller's final timing after its end event
MESSAGE_MAX = 2000  # characters of a campaign's message kept in its record and its archive
# s a vanished controller service's campaign waits for its cause before it ends on the vanishing:
# ``xneck up`` polls its children every 0.2 s, then tells the console (CI of 2026-11-29: the runner
# ended first and REST showed the side effect). Nothing physical waits on it: the bridge's watchdog
# holds the robot 10 ms after the last command, whatever the campaign's record says.
SERVICE_GONE_GRACE_S = 1.5
# s without a motor state from the bridge that end a started campaign (the bridge is gone or hung;
# the controller holds meanwhile, the bridge's watchdog too): longer than any stall of a loaded
# machine seen in the suite, far shorter than the campaign's timeout.
STOPPED_BY_USER = "stopped by the user"  # the outcome of a stop request (server.campaigns matches it)
BRIDGE_SILENT_S = 3.0
# s between two passes of the runner's loop (0.2 s apart) beyond which this process itself was held
# (SIGSTOP, a suspended machine, swap): the bridge's silence is then counted from that late pass on,
# since no state could be received meanwhile (review of session 44: a console stopped 9 s ended its
# campaign "no motor state from the bridge for 9.0 s: it is gone or hung").
RUNNER_HELD_S = 1.0
CAMERA_STARTUP_S = 120.0  # s a camera process may take to come up (OpenCV and the renderer load; a loaded machine)
# s a robot campaign waits for a bridge on the bus before it gives up with the reason: a bridge that
# runs is seen at once (its liveliness token), and the controller otherwise waited 120 s for a
# first state, silently, on a command not connected to any bridge.
BRIDGE_WAIT_S = 10.0
OWNER_WAIT_S = 0.5  # s: with several controller services, for a state saying which one the bridge obeys
# A campaign this runner ends on a controller service (a stop, a timeout, a silent bridge) is sent
# its stop again every STOP_RESEND_S until its end event comes, for STOP_ANSWER_S at most: one
# stop can be lost (the bus drops it; a flood of requests once had the service reject it, audit of
# 2026-11-30), and a second stop of the same campaign changes nothing. As server.campaigns does
# for a campaign stopped after the console's restart (its own constants, of the same values).
STOP_ANSWER_S = 3.0
STOP_RESEND_S = 0.5
#: Wall time a campaign that runs in real time (the robot, a real-time twin, `xneck up`'s) needs
#: within its timeout beyond its trajectory's duration: REALTIME_MARGIN_S and REALTIME_MARGIN of
#: the duration, for its start-up (2.7-3.1 s measured), the bridge's holds (each pauses the
#: campaign's clock, which then ramps back) and its end. A campaign whose trajectory leaves less
#: is refused before anything moves: a 600 s trajectory under the 600 s timeout was aborted at
#: progress 0.896 every time (audit of 2026-11-30).
REALTIME_MARGIN_S = 10.0
REALTIME_MARGIN = 0.1
#: The timeout of a campaign (wall, s) unless one is given: the longest trajectory
#: (controller.trajectory.TrajectoryLimits.duration_max_s, 600 s) with 300 s for the rest.
DEFAULT_TIMEOUT_S = 900.0


def check_timeout(duration_s: float, timeout_s: float, real_time: bool) -> None:
    """:class:`ValueError` saying why a trajectory of ``duration_s`` cannot run within
    ``timeout_s`` when the campaign runs in real time (:data:`REALTIME_MARGIN_S`)."""
    needed_s = duration_s * (1.0 + REALTIME_MARGIN) + REALTIME_MARGIN_S
    if real_time and needed_s > timeout_s:
        raise ValueError(f"the trajectory lasts {duration_s:.1f} s, and a campaign in real time needs "
                         f"{needed_s - duration_s:.0f} s more within its timeout of {timeout_s:.0f} s (start-up, "
                         f"holds, its end): it would be aborted before its end. Give a timeout of at least "
                         f"{math.ceil(needed_s):.0f} s (`xneck campaign --timeout`, the console's "
                         "XNECK_CAMPAIGN_TIMEOUT_S) or a shorter trajectory")


@dataclass(frozen=True)
class CampaignSpec:
    kind: str  # "control" or "identification"
    law: LawConfig
    trajectory: Trajectory
    twin: bool = True  # start a lockstep twin; False: the robot's bridge is already on the bus
    seed: int = 0
    timeout_s: float = DEFAULT_TIMEOUT_S
    params_file: Path | None = None
    overrides: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()  # extra endpoints (robot mode: where the bridge listens)
    realtime: bool = False  # twin paced at 500 Hz by the clock instead of lockstep (live viewing)
    service: bool = False  # ask the controller service on the bus (`xneck up`) instead of spawning processes
    truth: str = "model"  # what a spawned twin simulates (twin.sim.truth); a service's twin runs as it was started
    alpha_ip: str | None = None  # a spawned twin's α_IP (module docstring); None: camera for identification, else noise
    estimator: str = "auto"  # Table 2's estimator of an identification's analysis (twin.identification.pipeline)
    creep_time_s: float | None = None  # the line's creep time constant held in that analysis (s); None: estimated
    # The α_IP source (CameraAlpha.source) the campaign records when the console knows its camera
    # without spawning it (`xneck up`'s twin); None: a spawned twin's, else the first seen (server.quality)
    camera_source: str | None = None
    camera_instance: str = ""  # the camera process of that source it records (`xneck up`'s); '': the first seen

    def __post_init__(self) -> None:
        from twin.identification.options import check_variable_options

        if self.alpha_ip is not None and self.alpha_ip not in ALPHA_IP_KINDS:
            raise ValueError(f"alpha_ip must be one of {', '.join(ALPHA_IP_KINDS)}, got {self.alpha_ip!r}")
        # a bad analysis option fails before the campaign runs, not after the robot has moved
        object.__setattr__(self, "estimator", check_variable_options(self.estimator, self.creep_time_s))
        check_timeout(self.trajectory.duration_s, self.timeout_s, self.real_time)

    @property
    def real_time(self) -> bool:
        """Whether it runs at the clock's pace: the robot, a real-time twin, `xneck up`'s twin."""
        return self.realtime or self.service or not self.twin

    @property
    def alpha_ip_source(self) -> str:
        """The α_IP a spawned twin gives: as asked, else camera for identification, noise for control."""
        return self.alpha_ip or ("camera" if self.kind == "identification" else "noise")

    @property
    def spawns_camera(self) -> bool:
        """Whether the campaign spawns a camera process beside its twin: a real-time twin cannot
        wait for the renderer (its α_IP "camera")."""
        return self.twin and not self.service and self.realtime and self.alpha_ip_source == "camera"

    @property
    def recorded_camera(self) -> str | None:
        """The ``CameraAlpha.source`` the campaign records, when known before it runs: ``camera_source``,
        else that of the twin (and camera process) it spawns; None: the first seen (server.quality)."""
        if self.camera_source is not None:
            return self.camera_source
        return ALPHA_IP_SOURCES[self.alpha_ip_source] if self.twin and not self.service else None


class RecordingFailed(ArchiveError):
    """The recording of a campaign failed (a storage fault); ``quality`` holds the run's counters
    (server.quality) as far as it got, for the record of the failed campaign."""

    def __init__(self, cause: ArchiveError, quality: dict[str, object]) -> None:
        super().__init__(cause.path, cause.reason)
        self.quality = quality


class CausedStop(threading.Event):
    """A campaign's stop that may say why (``interrupted by SIGINT``): the campaign's message and
    its archive's then name that cause instead of :data:`STOPPED_BY_USER` (user audit: a CLI
    campaign stopped by Ctrl-C was recorded with no cause at all)."""

    def __init__(self) -> None:
        super().__init__()
        self.cause = ""

    def stop(self, cause: str) -> None:
        """Stop with ``cause``; the first cause given is kept (a second Ctrl-C names no new one)."""
        if not self.cause:
            self.cause = cause
        self.set()


def stop_message(stop: threading.Event) -> str:
    """What a stopped campaign's message says: its :class:`CausedStop` cause, else :data:`STOPPED_BY_USER`."""
    return getattr(stop, "cause", "") or STOPPED_BY_USER


@dataclass
class CampaignResult:
    campaign_id: str
    path: Path
    outcome: str
    message: str
    metrics: dict[str, object] = field(default_factory=dict)
    law: str = ""
    quality: dict[str, object] = field(default_factory=dict)  # server.quality: counters, thresholds, reasons
    analysis: str = ""  # identification: "identified" or why it failed (then outcome is analysis_failed)
    identification: dict[str, object] | None = None  # twin.identification.report.report_dict, when identified
    identified_set: dict[str, Any] | None = None  # server.identified_sets.identified_set, when identified
    logs_dir: str = ""  # the child processes' logs, kept when the campaign did not finish (else removed)
    truth_seen: str = ""  # the truth the twin's messages named, where it is not the one the campaign was told

    def summary(self) -> dict[str, object]:
        out = {"campaign_id": self.campaign_id, "path": str(self.path), "outcome": self.outcome,
               "message": self.message, "law": self.law, "metrics": self.metrics, "quality": self.quality}
        if self.logs_dir:
            out["logs_dir"] = self.logs_dir
        return {**out, "analysis": self.analysis} if self.analysis else out

    def table(self) -> str:
        m = self.metrics
        lines = [f"campaign {self.campaign_id} ({self.law}): {self.outcome}  {self.message}", f"archive: {self.path}"]
        if self.logs_dir:
            lines.append(f"process logs: {self.logs_dir}")
        if m.get("ticks"):
            fmt = lambda v: "  ".join(f"{x:7.3f}" for x in v)  # noqa: E731
            lines += [
                f"ticks {m['ticks']}, {m['duration_s']:.2f} s, saturated ticks {m['saturated_ticks']}",
                "                      per joint (deg)            all",
                f"mean |α̂ − α^d| (e)    {fmt(m['e_mean_deg'])}   {m['e_mean_all_deg']:7.3f}",
                f"max  |α̂ − α^d|        {fmt(m['e_max_deg'])}",
            ]
            if m.get("e_alpha_mean_deg") is not None:
                lines += [f"mean |α̂ − α_IP| (e_α) {fmt(m['e_alpha_mean_deg'])}   {m['e_alpha_mean_all_deg']:7.3f}",
                          f"max  |α̂ − α_IP|       {fmt(m['e_alpha_max_deg'])}"]
            lines += [f"mean force (N)  {fmt(m['force_mean_N'])}   all {m['force_mean_all_N']:.2f}",
                      f"max force (N)   {fmt(m['force_max_N'])}"]
        return "\n".join(lines)


CLI_ARCHIVES = "cli-campaigns"  # below the data directory; not campaigns/, which the console indexes and recovers


def default_archive(campaign_id: str) -> Path:
    """Where a campaign run without an explicit file is recorded: the console's data directory
    (server.settings: ``XNECK_DATA_DIR``, else ./data), ``cli-campaigns/campaign-<id>.mcap``;
    never the current directory (a checkout used to collect hundreds of MB of them)."""
    from server.settings import Settings

    settings = Settings()  # pyright: ignore[reportCallIssue] - pydantic-settings fills the fields from XNECK_*
    return Path(settings.data_dir).resolve() / CLI_ARCHIVES / f"campaign-{campaign_id}.mcap"


WORKDIR_PREFIX = "xneck-"  # $TMPDIR/xneck-<campaign id>-*: a CLI campaign's folder (kept when it does not finish)
CONSOLE_WORKDIR_PREFIX = "xneck-console-"  # a console campaign's (removed when it ends, swept at the console's start)
STALE_WORKDIR_S = 86400.0  # s after which a console campaign's folder no console knows is a leftover


def sweep_console_workdirs(ended: Callable[[str], bool], tmp: Path | None = None, now: float | None = None,
                           max_age_s: float = STALE_WORKDIR_S) -> list[Path]:
    """Remove the working folders console campaigns left in ``tmp`` (default: the temporary
    directory) before :func:`run_campaign` removed them itself, or after a crash; returns those
    removed. Only folders (no link, no file) of this software's naming: ``xneck-console-<id>-*``
    whose campaign ``ended(id)`` says ended, or whose last change is older than ``max_age_s`` s
    (another console's, on the same machine, that is running stays: ``now`` and the age in s of
    the epoch); ``xneck-<id>-*`` (the naming before) only when ``ended(id)``: a CLI campaign's is
    its user's, kept with its logs (README), and this console knows none of their ids."""
    base = Path(tmp) if tmp is not None else Path(tempfile.gettempdir())
    now = time.time() if now is None else now
    removed = []
    try:
        entries = list(base.iterdir())
    except OSError:
        return []
    for entry in entries:
        name = entry.name
        console = name.startswith(CONSOLE_WORKDIR_PREFIX)
        if not console and not name.startswith(WORKDIR_PREFIX):
            continue
        cid = name[len(CONSOLE_WORKDIR_PREFIX if console else WORKDIR_PREFIX):].rpartition("-")[0]
        try:
            st = entry.lstat()
        except OSError:
            continue
        if not cid or not stat.S_ISDIR(st.st_mode):
            continue
        if ended(cid) or (console and now - st.st_mtime > max_age_s):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
    return removed


def new_campaign_id(kind: str) -> str:
    return f"{kind}-{dt.datetime.now().strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:4]}"


def _param_args(spec: CampaignSpec) -> list[str]:
    out = ["--params", str(spec.params_file)] if spec.params_file else []
    for o in spec.overrides:
        out += ["--set", o]
    return out


def run_campaign(
    spec: CampaignSpec, params: Params, out: Path | None = None,
    progress: Callable[[float, str], None] | None = None, campaign_id: str | None = None,
    session: zenoh.Session | None = None, hub: str | None = None, stop: threading.Event | None = None,
    on_monitor: Callable[[CampaignMonitor | None], None] | None = None, console: bool = False,
) -> CampaignResult:
    """Run one campaign end to end (module docstring). Never leaves a child process behind.

    ``console``: a console's campaign, whose working folder (its trajectory file and processes'
    logs, ``$TMPDIR/xneck-console-<id>-*``) is removed whatever the outcome: nothing shows a
    console's user that folder, and those of its unfinished campaigns accumulated by the hundred
    (user audit). Else (the CLI) it is kept, and named, when the campaign does not finish (README).

    ``session``/``hub``: run on an existing session that listens on ``hub`` (the server does, so
    it sees the live traffic); by default a private hub is opened. ``stop``: set it to abort.
    ``on_monitor``: called with the campaign's :class:`~server.quality.CampaignMonitor` once it
    knows the camera expected, and with None once it is closed (the console's live view shows the
    camera the campaign records: :attr:`server.live.LatestValues.prefer_camera`).
    """
    campaign_id = campaign_id or new_campaign_id(spec.kind)
    path = Path(out) if out else default_archive(campaign_id)
    if path.exists():
        raise FileExistsError(f"{path} exists: choose another --out (archives are never overwritten)")
    if (session is None) != (hub is None):
        raise ValueError("pass both session and hub, or neither")
    path.parent.mkdir(parents=True, exist_ok=True)
    workdir = Path(tempfile.mkdtemp(prefix=f"{CONSOLE_WORKDIR_PREFIX if console else WORKDIR_PREFIX}{campaign_id}-"))
    try:
        if session is None:
            hub = f"tcp/127.0.0.1:{free_tcp_port()}"
            with open_session(listen=[hub], connect=list(spec.connect)) as own:
                result = _run(spec, params, path, progress, campaign_id, own, hub, stop or threading.Event(),
                              workdir, on_monitor)
        else:
            result = _run(spec, params, path, progress, campaign_id, session, hub, stop or threading.Event(), workdir,
                          on_monitor)
    except BaseException:
        if console:  # a storage fault, a bug: nobody is told of the folder either
            shutil.rmtree(workdir, ignore_errors=True)
        raise
    if console and result.logs_dir:
        shutil.rmtree(workdir, ignore_errors=True)
        result.logs_dir = ""
    return result


def _run(spec, params, path, progress, campaign_id, session, hub, stop, workdir: Path,
         on_monitor=None) -> CampaignResult:
    traj_file = workdir / "trajectory.json"
    traj_file.write_text(spec.trajectory.to_json())
    common = ["--listen", "tcp/127.0.0.1:0", "--connect", hub, *[a for c in spec.connect for a in ("--connect", c)],
              *_param_args(spec)]
    metadata = {
        "campaign_id": campaign_id, "kind": spec.kind, "law": spec.law.name,
        "trajectory": spec.trajectory.to_json(), "parameter_set": params.name,
        "target": "twin" if spec.twin else "robot", "seed": str(spec.seed),
        "pace": "realtime" if spec.realtime or not spec.twin else "lockstep",
        "twin_truth": spec.truth if spec.twin else "",  # a service's twin: the truth the console was told
        # the α_IP asked of a spawned twin; the finished record says the one recorded (alpha_ip_recorded)
        "alpha_ip": spec.alpha_ip_source if spec.twin and not spec.service else "",
        "parameters_toml": params.to_toml(),
    }
    if spec.kind == "identification":  # how its analysis is asked to run (the archive's reader may refit it otherwise)
        metadata["estimator"] = spec.estimator
        metadata["creep_time_s"] = "" if spec.creep_time_s is None else repr(float(spec.creep_time_s))
    events: queue.Queue[bus.CampaignEvent] = queue.Queue()
    procs: dict[str, subprocess.Popen] = {}
    logs: dict[str, Path] = {}
    outcome, message = "aborted", ""

    def on_event(sample) -> None:
        try:
            ev = bus.decode(bus.CampaignEvent, payload_of(sample, bus.CampaignEvent))
        except bus.BusDecodeError:
            return
        if ev.campaign_id == campaign_id:
            events.put(ev)

    sub = session.declare_subscriber(bus.CAMPAIGN_EVENTS, on_event)
    services = _Services(session) if spec.service else None
    # Follows the bridge's drives from now on (the e-stop's one truth) and counts the quality.
    monitor = CampaignMonitor(session, n_cables=params.n_cables)
    if spec.recorded_camera is not None:  # its camera, whichever α_IP comes first (a stray camera's)
        # the camera process it spawns, not another of its source on the hub (server.quality, "One camera")
        # or, when its own twin publishes the α_IP (rendered in lockstep, or noise), the twin's
        spawned = f"camera-{campaign_id}" if spec.spawns_camera else TWIN_CAMERA if spec.twin and not spec.service \
            and spec.camera_source is None else ""
        monitor.expect_alpha_ip_source(spec.recorded_camera, spec.camera_instance or spawned)
    if on_monitor is not None:
        on_monitor(monitor)
    realtime = spec.realtime or not spec.twin
    quality: dict[str, object] = {}
    recorder = CampaignRecorder(session, path, metadata, on_error=lambda _exc: stop.set(),  # a storage fault ends it
                                keep=monitor.keep)
    requests: BusPublisher[bus.BusMessage] | None = None  # service mode: to the controller service
    requested = False  # a start request went out (a stop follows an abort)
    ended = False  # the controller's end event of the campaign came: no stop is owed
    try:
        def spawn(name: str, args: list[str]) -> None:
            logs[name] = workdir / f"{name}.log"
            # a loop process takes its real-time priority itself once set up (server.child_processes.loop_environ)
            env = {**os.environ, "PYTHONUNBUFFERED": "1", **(loop_environ(args[0]) if realtime else {})}
            procs[name] = start_xneck(args, logs[name], env)
            if realtime:  # a lockstep twin runs flat out: no real-time priority for it (issue 21)
                isolate(procs[name].pid, args[0], realtime=False)

        not_up = ""  # a camera process (or a robot's bridge) that is not up: the campaign does not start
        if not spec.twin and not spec.service:  # the robot's bridge, already on the bus: is it?
            not_up = _wait_alive(session, f"{bus.PREFIX}/alive/bridge/*", stop, BRIDGE_WAIT_S, "bridge",
                                 where=", ".join(spec.connect) or hub)
        if spec.service:
            # To one service: the one the bridge obeys, else the only one (server/service_choice.py).
            alive = alive_services(session)
            owners = monitor.owners()
            give_up = time.monotonic() + OWNER_WAIT_S
            while len(alive) > 1 and not owners & set(alive) and time.monotonic() < give_up:
                time.sleep(0.02)  # the monitor was just made: the bridge's states say whom it obeys
                owners = monitor.owners()
            target, not_up = choose_service(alive, owners)
            requests = publisher(session, bus.campaign_request_key(target) if target else bus.CAMPAIGN_REQUEST)
            if target:
                monitor.follow(target)
            if not not_up:
                requests.put(bus.CampaignRequest(
                    seq=1, stamp_s=time.time(), campaign_id=campaign_id, action="start", kind=spec.kind,
                    law=spec.law.law, no_pulleys=spec.law.no_pulleys, trajectory_json=spec.trajectory.to_json(),
                    parameters_toml=params.to_toml()))
                requested = True
        else:
            lockstep = spec.twin and not spec.realtime
            # A real-time twin cannot wait for the renderer: a camera process beside it measures its truth.
            camera_process = spec.spawns_camera
            if camera_process:  # first, and waited for: the campaign's first seconds need α_IP too
                spawn("camera", ["camera", "--source", "twin", "--seed", str(spec.seed), "--idle-timeout",
                                 str(CAMERA_STARTUP_S), "--instance", f"camera-{campaign_id}", *common])
                not_up = _wait_alive(session, bus.liveliness_key("camera", f"camera-{campaign_id}"), stop,
                                     CAMERA_STARTUP_S, "camera", child=(procs["camera"], logs["camera"]))
            if spec.twin and not not_up:
                alpha_ip = ["--no-camera"] if camera_process else ["--alpha-ip", spec.alpha_ip_source]
                spawn("twin", ["twin", *(["--lockstep"] if lockstep else []), "--seed", str(spec.seed),
                               "--truth", spec.truth, *alpha_ip, "--idle-timeout", "30", "--startup-timeout", "120",
                               "--instance", f"twin-{campaign_id}", *common])
            law_args = ["--law", str(spec.law.law)] + (["--no-pulleys"] if spec.law.no_pulleys else [])
            if not not_up:
                monitor.follow(f"controller-{campaign_id}")
                spawn("controller", ["controller", *law_args, "--instance", f"controller-{campaign_id}",
                                     "--trajectory", str(traj_file),
                                     *(["--lockstep"] if lockstep else []), "--campaign-id", campaign_id,
                                     "--campaign-kind", spec.kind, "--idle-timeout", "20", *common])
        if not_up:
            outcome, message = "aborted", not_up
        deadline = time.monotonic() + spec.timeout_s
        answer_deadline = time.monotonic() + 10.0
        started = False
        dead_since = 0.0  # when a child was first seen exited (its last event may be on the way)
        gone_since = 0.0  # when the controller service was first seen gone (its cause may be on the way)
        last_pass = held_until = time.monotonic()  # RUNNER_HELD_S
        while not not_up:
            try:
                ev = events.get(timeout=0.2)
            except queue.Empty:
                ev = None
            if ev is not None and ev.event in ("finished", "aborted"):
                # The controller's end, taken off the queue here even when the drives' word below
                # ends the loop first: else the stop that follows waited STOP_ANSWER_S for an end
                # already consumed, the campaign shown running 3.5 s into an e-stop (user audit of
                # session 42: a start meanwhile got 409 "running", not the e-stop's refusal).
                ended = True
            disabled = monitor.drives_disabled()
            if disabled:
                outcome, message = "aborted", f"the drives were disabled during the campaign: {disabled}"
                break
            now = time.monotonic()
            if now - last_pass > RUNNER_HELD_S:
                held_until = now
            last_pass = now
            silent_s = min(monitor.state_silence_s(), now - held_until) if started else 0.0
            if silent_s > BRIDGE_SILENT_S:
                outcome, message = "aborted", f"no motor state from the bridge for {silent_s:.1f} s: it is gone or hung"
                break
            if ev is not None:
                if not started:
                    monitor.begin()
                started = True
                monitor.note_event(ev)
                if progress:
                    progress(ev.progress, ev.event if not ev.message else f"{ev.event}: {ev.message}")
                if ev.event in ("finished", "aborted"):
                    outcome, message, ended = ev.event, ev.message, True
                    break
            # Every turn, not only when no event came for 0.2 s: a lockstep twin's events (one per
            # 0.5 s of campaign time) come faster than that on a quick machine, and a stop, the
            # deadline or a dead child were then never seen (audit of 2026-11-27).
            dead = [n for n, p in procs.items() if p.poll() is not None]
            if dead:
                # A controller that finished puts its last event just before it exits: under load
                # the event may come after the exit is seen. Wait for it a moment (issue 21).
                dead_since = dead_since or time.monotonic()
                if time.monotonic() - dead_since < EXIT_GRACE_S:
                    continue
                name = dead[0]
                outcome = "aborted"
                message = f"{name} exited with code {procs[name].returncode}: {log_tail(logs[name], 3)}"
                break
            if time.monotonic() > deadline:
                outcome, message = "aborted", f"timed out after {spec.timeout_s:.0f} s"
                break
            if stop.is_set():
                # The console's e-stop sets stop too: the bridge's word on it, if it comes, names the reason.
                disabled = monitor.wait_drives_disabled(0.3)
                outcome, message = ("aborted", f"the drives were disabled during the campaign: {disabled}") \
                    if disabled else ("aborted", stop_message(stop))
                break
            # Once its events have stopped (0.2 s), and SERVICE_GONE_GRACE_S after: a service killed
            # under `xneck up` is named by the supervisor, which needs that time to tell the console
            # the cause before the campaign ends on its side effect (CI of 2026-11-27, 2026-11-29).
            if ev is None and services is not None and not services.alive():
                gone_since = gone_since or time.monotonic()
                if time.monotonic() - gone_since >= SERVICE_GONE_GRACE_S:
                    outcome, message = "aborted", f"the controller service vanished from the bus ({services.gone})"
                    break
            else:
                gone_since = 0.0
            if spec.service and not started and time.monotonic() > answer_deadline:
                outcome, message = "aborted", "no controller service answered the campaign request"
                break
    finally:
        if ended:  # its final latency figures, put before the end event, may be a moment behind it
            monitor.wait_final_timing(campaign_id, FINAL_TIMING_WAIT_S)
        monitor.end()
        # Not when the service vanished: nothing would answer (it ended the campaign with it).
        if requests is not None and requested and outcome == "aborted" and not ended \
                and (services is None or services.alive()):
            with contextlib.suppress(Exception):
                ended = _stop_until_ended(requests, events, campaign_id) is not None
        if requests is not None:
            requests.close()
        if services is not None:
            services.close()
        for p in procs.values():
            stop_child(p, STOP_GRACE_S)
        sub.undeclare()
        monitor.close()
        if on_monitor is not None:
            on_monitor(None)
        counters = monitor.counters(recorder.stats.dropped)
        reasons = assess(counters, realtime) if outcome == "finished" else []
        if reasons:
            outcome, message = "degraded", "; ".join(reasons) + (f" ({message})" if message else "")
        note = camera_note(counters)  # another camera's α_IP set aside: said, though the record is clean
        if spec.kind == "identification" and (clipped := saturation_note(counters)):  # said, not judged
            note = f"{note}; {clipped}" if note else clipped
        if note:
            message = f"{message}; {note}" if message else note
        truth_seen = monitor.truth_seen or ""
        if spec.twin and (differs := truth_note(spec.truth, truth_seen)):  # said, and the record names what ran
            message = f"{message}; {differs}" if message else differs
        else:
            truth_seen = ""
        quality = {**counters, "realtime": realtime, "reasons": reasons, "thresholds": thresholds_dict(THRESHOLDS)}
        try:
            recorder.stop(outcome, {"message": message[:MESSAGE_MAX], "quality": json.dumps(quality),
                                    "degraded_reasons": "; ".join(reasons)},
                          final_metadata=lambda: {"alpha_ip": alpha_ip_recorded(monitor.recorded_alpha_ip())},
                          end_of=campaign_id if ended else "")  # all the controller put before its end
        except ArchiveError as exc:  # a storage fault: the run's counters go with it to the record
            raise RecordingFailed(exc, quality) from exc
    result = CampaignResult(campaign_id, path, outcome, message, law=spec.law.name, quality=quality,
                            truth_seen=truth_seen)
    # The children's logs matter only when something went wrong: kept then (and named), else removed,
    # so that a lab's thousands of campaigns do not leave as many folders in the temporary directory.
    if outcome == "finished":
        shutil.rmtree(workdir, ignore_errors=True)
    else:
        result.logs_dir = str(workdir)
    try:
        result.metrics = metrics_from_archive(path)
    except (ValueError, ArchiveError) as exc:  # a damaged archive's reason, not the campaign's failure
        result.metrics = {"error": str(exc)}
    if spec.kind == "identification" and outcome in ("finished", "degraded"):
        if progress:
            progress(1.0, "identifying (twin.identification.pipeline)…")
        analyse_identification(result, spec.params_file, spec.estimator, spec.creep_time_s, spec.overrides,
                               base_name=params.name, stop=stop)
    return result


def truth_note(told: str, seen: str) -> str:
    """'' if the twin's ``Truth`` messages name the truth ``told`` (a name or a truth file's path;
    nothing named: a twin from before the field), else what the campaign's message says. A
    console in a stack is told its twin's truth (``xneck up --truth``, ``xneck server
    --twin-truth``) and cannot set it: with ``--no-bridge`` the twin is another's, and the record
    had named what the console was told (truth audit of 2026-12-01)."""
    if not seen:
        return ""
    try:
        expected = load_truth(told).name
    except (OSError, ValueError):  # gone or changed since: nothing to compare against
        return ""
    if seen == expected:
        return ""
    return (f"the twin simulated the {seen!r} truth (its Truth messages), not {truth_label(told)!r} as this "
            f"console was told: the record names {seen!r}")


#: The twin's α_IP kind (:data:`ALPHA_IP_KINDS`) of each twin camera's ``CameraAlpha.source``.
_KIND_OF_SOURCE = {source: kind for kind, source in ALPHA_IP_SOURCES.items()}


def alpha_ip_recorded(source: str) -> str:
    """The archive's ``alpha_ip`` of a campaign that recorded the α_IP of ``source`` ('' for none):
    a twin camera's kind (``camera``, ``noise``: what a spawned twin is asked), another camera's
    source (``usb:0``), ``none`` when it recorded none. Written when the recording ends, whoever
    started the camera: a campaign through `xneck up`'s controller service had said "" (user audit
    of session 42)."""
    if not source:
        return "none"
    return _KIND_OF_SOURCE.get(source, source[: CampaignMonitor.SOURCE_NAME_MAX])


def _stop_until_ended(requests: BusPublisher[bus.BusMessage], events: queue.Queue[bus.CampaignEvent],
                      campaign_id: str) -> bus.CampaignEvent | None:
    """Send the stop of ``campaign_id`` on ``requests`` until its end event (finished, aborted)
    comes on ``events``, every :data:`STOP_RESEND_S`, for :data:`STOP_ANSWER_S` at most; the end
    event, or None if none came (the bridge's watchdog holds the robot once the controller's
    commands stop, whatever the record says)."""
    give_up = time.monotonic() + STOP_ANSWER_S
    seq = 1  # the start request was 1
    while True:
        seq += 1
        requests.put(bus.CampaignRequest(seq=seq, stamp_s=time.time(), campaign_id=campaign_id, action="stop"))
        resend_at = min(time.monotonic() + STOP_RESEND_S, give_up)
        while (left := resend_at - time.monotonic()) > 0:
            try:
                ev = events.get(timeout=left)
            except queue.Empty:
                break
            if ev.event in ("finished", "aborted"):
                return ev
        if time.monotonic() >= give_up:
            return None


def analyse_identification(result: CampaignResult, params_file: Path | None, estimator: str = "auto",
                           creep_time_s: float | None = None, overrides: tuple[str, ...] = (),
                           base_name: str = "", stop: threading.Event | None = None) -> None:
    """Identify a recorded identification campaign (:func:`server.results.analyse_archive`, Table 2
    by ``estimator``, the creep time held at ``creep_time_s`` s if given, the parameter file with the
    campaign's ``overrides``, as its controller ran) into ``result``, with the set it identified; a failed
    analysis makes the outcome ``analysis_failed`` with its reason, in the result and in the archive
    (module docstring). In a child process (server.analysis_process): the console stays responsive
    and gets its memory back. ``stop`` set meanwhile (an abort, the console closing) kills it: the
    recording's outcome stays, the archive is not amended, the message says the analysis was not
    done (``xneck identify`` does it on the archive)."""
    from server.analysis_process import AnalysisStopped, run_in_child
    from server.results import analyse_archive

    try:
        result.identification, result.analysis, result.identified_set = run_in_child(
            analyse_archive, result.path, params_file, estimator=estimator, creep_time_s=creep_time_s,
            overrides=overrides, base_name=base_name, what="identification", stop=stop)
    except AnalysisStopped as exc:
        why = stop_message(stop) if stop is not None else "stopped"
        result.identification, result.identified_set = None, None
        result.analysis = f"identification not done: {exc} ({why}); `xneck identify {result.path}` does it"
        result.message = f"{result.message}; {result.analysis}" if result.message else result.analysis
        return
    except Exception as exc:  # noqa: BLE001 - the process died, could not start (EMFILE), sent what cannot be read
        result.identification, result.analysis, result.identified_set = (
            None, f"identification failed: {type(exc).__name__}: {exc}", None)
    if result.identification is not None:
        return
    result.outcome = "analysis_failed"
    result.message = failed_analysis_message(result.analysis, result.message)
    if is_complete(result.path):
        rewrite_archive(result.path, amend={CAMPAIGN: {"outcome": result.outcome, "message": result.message[:MESSAGE_MAX],
                                                       "analysis": result.analysis[:MESSAGE_MAX]}})


def failed_analysis_message(analysis: str, run: str) -> str:
    """The message of a campaign whose analysis failed: the analysis's reason, then the run's own
    message in parentheses, kept whole within :data:`MESSAGE_MAX` (its notes: cables at f_max,
    holds, a stop's cause), the reason clipped to the room left (whole in the archive's
    ``analysis`` field). Cut at the end instead, a reason that lists many gaps had taken the
    saturation note out of the archive (fresh-clone CI of session 55)."""
    if not run:
        return analysis
    room = max(MESSAGE_MAX - len(run) - 3, 300)
    head = analysis if len(analysis) <= room else analysis[:room - 1] + "…"
    return f"{head} ({run})"


def _wait_alive(session: zenoh.Session, key: str, stop: threading.Event, timeout_s: float, what: str, *,
                child: tuple[subprocess.Popen, Path] | None = None, where: str = "") -> str:
    """Wait for a liveliness token ``key``: a ``child``'s (its process and log), or, without one,
    any process's the key matches on the bus reached at ``where``. '' once it is up, else why not
    (the child exited, it took longer than ``timeout_s``, or the campaign was stopped)."""
    up = threading.Event()
    sub = session.liveliness().declare_subscriber(
        key, lambda sample: up.set() if sample.kind == zenoh.SampleKind.PUT else None, history=True)
    deadline = time.monotonic() + timeout_s
    try:
        while not up.wait(0.1):
            if child is not None and child[0].poll() is not None:
                return f"the {what} exited with code {child[0].returncode} before it was up: {log_tail(child[1], 3)}"
            if stop.is_set():
                return stop_message(stop)
            if time.monotonic() > deadline:
                if child is None:
                    return (f"no {what} on the bus at {where or 'the campaign hub'} within {timeout_s:.0f} s: "
                            f"is it running, and listening there (e.g. xneck bridge --listen tcp/0.0.0.0:7447)?")
                return f"the {what} was not up within {timeout_s:.0f} s: {log_tail(child[1], 3)}"
        return ""
    finally:
        sub.undeclare()


class _Services:
    """Controller services seen on the bus (liveliness), to notice one vanishing mid-campaign."""

    def __init__(self, session: zenoh.Session) -> None:
        self._lock = threading.Lock()
        self._alive: set[str] = set()
        self.gone = ""
        self._sub = session.liveliness().declare_subscriber(
            f"{bus.PREFIX}/alive/campaign-service/*", self._on_sample, history=True)

    def _on_sample(self, sample) -> None:
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(str(sample.key_expr))
            else:
                self._alive.discard(str(sample.key_expr))
                self.gone = str(sample.key_expr)

    def alive(self) -> bool:
        with self._lock:
            return bool(self._alive) or not self.gone

    def close(self) -> None:
        self._sub.undeclare()
