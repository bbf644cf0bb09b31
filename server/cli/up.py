"""`xneck up`: the whole stack as separate processes on one Zenoh bus, and the dashboard URL.

    server (FastAPI + viser, the hub) --> bridge (twin or BeagleBone)
    server --> controller (campaign service) --> bridge          (A --> B: A connects to B)

The server listens on the hub endpoint (for other tools: a camera, CLI campaigns, a remote
bridge); the bridge and the controller listen on Unix sockets of their own (in a 0700 folder of
this user's) and the control path runs the other way: the controller connects to the bridge, the
server to both (peer mode, multicast scouting off). Neither the bridge nor the controller ever
reconnects to the console, so a console that stops answering cannot stall them: every retry to a
stopped hub ends in a socket close that blocks the retrying process's Zenoh poller ~40 ms (Zenoh's
hard-coded SO_LINGER), one bridge hold per retry (docs/safety.md, "Peers that stop reading";
tests/test_up_stalled_console.py). And on Unix sockets a link's close does not wait for the
peer: on loopback TCP, a peer that left (a console or tool closing) cost ~40 ms likewise
(benchmarks/peer_churn.py). Nor do they open links to the tools on the hub (``--no-autoconnect``):
gossip had them link to every tool's loopback TCP listener, and a link a process opened that
lingers on close stalls every link it opened, the controller's to the bridge among them; the tools
link to them instead, over their Unix sockets (tests/test_up_links.py). So a tool that cannot open
those sockets (another machine on an exposed hub, another user, a container without the folder)
links to the console alone and hears neither the bridge nor the controller (Zenoh peers do not
relay): it connects to a bridge of its own endpoint (``--no-bridge --bridge-at``, the board's).
With ``--no-bridge`` the controller connects to the remote bridge where it listens
(``--bridge-at``), else to the hub, to which the bridge then connects. Start order: server (until
its health endpoint answers), bridge, controller. Before anything starts, :func:`preflight` checks that the hub endpoint, the HTTP port
and the viser port are free and that no other stack answers on the hub; if not, ``xneck up`` says
so in one line and exits with code 3, having started no process (issue 13, finding 5: a second
stack on the same hub would otherwise join the first one's bus and command its bridge). Nothing
is restarted silently: if a process exits, the launcher says which, with its exit code or signal
and last log lines, stops the others and exits non-zero. With ``--restarts N`` a controller or a
camera that exits is restarted instead, saying so the same way, at most N times in
:data:`RESTART_WINDOW_S` (:data:`RESTARTABLE`: the bridge holds the neck meanwhile and the new
controller joins its run under way, taking up any slack first), each after a back-off
(:func:`restart_delay_s`: 1 s, doubled for each earlier restart in the window, at most 30 s)
during which the other children are judged as ever; past them the stack stops as without. The running campaign ends ``aborted`` naming the death either way. Before it stops them it tells the console
the cause (``POST /api/system/abort``, :func:`abort_campaign`), so that a running campaign ends
``aborted`` naming the process and how it ended, e.g. "bridge process exited (signal SIGKILL)",
in its record and archive, not the side effect the campaign would see next (the controller
service vanished, the drives disabled, the bridge silent: audit of 2026-11-26). That stop is the
console's ordinary one (the controller holds, as after the stop button); it waits at most
:data:`ABORT_TIMEOUT_S` and nothing else changes meanwhile. Ctrl-C or SIGTERM stops them all in the
safe order: controller, then bridge (which disables its drives), then server.

With ``--robot`` (the BeagleBone's bridge a child of this process) the launcher also watches the
bridge's real-time loop, as systemd's watchdog would (:class:`_LoopPings`): the loop says it ticks
(sd_notify ``WATCHDOG=1``, five times a second) to a socket of this process, and a bridge whose
process lives but whose loop was silent for :data:`BRIDGE_HUNG_S` is hung (its loop no longer runs
its watchdog or its e-stop, and the ESCONs go on driving the last currents): it is killed and
handled as a death. Likewise the controller, twin and robot alike: its loop pings (:data:`CONTROLLER_HUNG_S`),
and one silent that long is killed and handled as a death (restarted under ``--restarts``). A bridge that did not end
cleanly (killed, crashed, or not stopping within :data:`STOP_GRACE_S`) could not disable its
drives: ``xneck bridge --driver beaglebone --drives-off`` then does (enable lines off,
zero-current set values; audit of 2026-11-26: a hung bridge's SIGKILL left them as they were).
"""

from __future__ import annotations

import contextlib
import errno
import faulthandler
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import typer

from server.child_processes import (
    ENV_PARENT,
    exit_how,
    isolate,
    isolate_self,
    kill_child,
    log_tail,
    loop_environ,
    process_state,
    start_xneck,
    stop_child,
    xneck_argv,
)
from server.cli.options import (
    NON_NEGATIVE,
    PORT_MAX,
    check_credentials,
    check_endpoints,
    check_truth,
    fail,
    law_config,
    load_cli_params,
)

STOP_GRACE_S = 8.0
HUNG_KILL_WAIT_S = 1.0  # s a hung child, killed, is waited for in one pass of the supervisor
LOG_LINES = 12  # of a child's log in an error message
PREFLIGHT_EXIT = 3  # exit code of a refused start (nothing was started)
PROBE_S = 1.0  # how long the preflight waits for a Zenoh peer on a busy hub port
# s the supervisor waits for the console to end a running campaign with a child's death as its
# cause (the console waits 10 s for the record, server.campaigns.ABORT_WAIT_S; the rest is HTTP).
ABORT_TIMEOUT_S = 15.0
# s added to the time since a child was last seen alive, for the console's window of campaigns that
# ended of its death before they were told (the request's own transit, a loaded machine).
ABORT_WINDOW_MARGIN_S = 1.0
READY_HINT_S = 60.0  # s after the children's start without "xneck is up": said once
# s without a ping from a live local robot bridge's loop after which it counts as hung (a stall the
# bridge's own watchdog cannot see: a SIGSTOP, a C call holding the GIL): five missed pings.
BRIDGE_HUNG_S = 1.0
# s without a ping from the controller's loop (controller.process.ControllerNode.run) after which it
# counts as hung and is killed, then handled as a death (restarted under --restarts): a SIGSTOPped
# controller had left the bridge holding and `xneck up` silent; its console ended the campaign
# "the controller service vanished" 11 s later (audit of session 44). Ten missed pings.
CONTROLLER_HUNG_S = 2.0
PING_WATCHDOG_S = 0.4  # WATCHDOG_USEC given to the bridge: it pings every half of it (bridge.runtime.SystemdNotify)
DRIVES_OFF_TIMEOUT_S = 30.0  # s `xneck bridge --drives-off` may take (rcpy's import initialises the board)
# s over which ``--restarts`` counts a child's restarts (systemd's StartLimitIntervalSec): a child
# that keeps dying stops the stack once it has used them up within this window.
RESTART_WINDOW_S = 600.0
# The children a restart cannot harm: while the controller is away the bridge's watchdog holds the
# neck, and the new one joins the bridge's run under way, taking up any slack before its law runs
# (controller.service.CampaignService.initialise); the camera only gives α_IP. A bridge that died
# could not disable its drives, and the console is what a restart would be told through.
RESTARTABLE = ("controller", "camera")
# s before the first restart of a child within RESTART_WINDOW_S, doubled for each further one up to
# RESTART_DELAY_MAX_S (systemd's RestartSec, with RestartSteps' growth): a child that crashed at
# start-up was restarted at once, its N restarts used up in a burst of a few seconds (review of
# session 46), before a transient cause (a busy bus, a slow disk) could pass.
RESTART_DELAY_S = 1.0
RESTART_DELAY_MAX_S = 30.0


def restart_delay_s(earlier: int) -> float:
    """Seconds to wait before restarting a child that has been restarted ``earlier`` times within
    :data:`RESTART_WINDOW_S`: 1, 2, 4, 8, 16, then 30 s (:data:`RESTART_DELAY_S` doubled per
    earlier restart, at most :data:`RESTART_DELAY_MAX_S`)."""
    if earlier >= 16:  # 2**16 s is far past the cap: no float overflow for a large count
        return RESTART_DELAY_MAX_S
    return min(RESTART_DELAY_S * 2.0 ** max(0, earlier), RESTART_DELAY_MAX_S)


class RestartPlan:
    """Each restartable child's restarts within :data:`RESTART_WINDOW_S` (counted per child, as
    systemd counts per unit: a flaky camera must not use up the controller's) and the one it waits
    for, if any. The supervisor's loop asks it on every pass, so that it goes on judging the other
    children (a bridge that dies meanwhile stops the stack) while a dead one waits its back-off.
    Times are seconds on the caller's monotonic clock."""

    def __init__(self, restarts: int, window_s: float = RESTART_WINDOW_S) -> None:
        self.restarts = restarts
        self.window_s = window_s
        self.times: dict[str, list[float]] = {name: [] for name in RESTARTABLE}  # when each restart was planned
        self._due: dict[str, float] = {}  # child -> when it is to be started again

    def forget_old(self, now: float) -> None:
        """Drop the restarts older than the window: they no longer count, nor lengthen the delay."""
        for times in self.times.values():
            times[:] = [t for t in times if now - t < self.window_s]

    def used(self, name: str) -> int:
        """Restarts of ``name`` within the window (a planned one included)."""
        return len(self.times.get(name, ()))

    def may_restart(self, name: str) -> bool:
        """Whether ``name`` is restartable and has a restart left within the window."""
        return name in self.times and self.used(name) < self.restarts

    def plan(self, name: str, now: float) -> float:
        """Counts a restart of ``name``, which died at ``now``, and returns its delay (s): due at
        ``now`` plus :func:`restart_delay_s` of its restarts before it within the window."""
        delay_s = restart_delay_s(self.used(name))
        self.times[name].append(now)
        self._due[name] = now + delay_s
        return delay_s

    def waiting(self, name: str) -> bool:
        """Whether ``name`` is dead and waiting for its restart (not a new death to judge)."""
        return name in self._due

    def due(self, now: float) -> list[str]:
        """The children whose delay has passed at ``now``, in the order of :data:`RESTARTABLE`; no
        longer waiting once returned."""
        ready = [name for name in RESTARTABLE if self._due.get(name, float("inf")) <= now]
        for name in ready:
            del self._due[name]
        return ready


SOCKETS_PREFIX = "xneck-up-"  # + the pid of the xneck up that made the folder, "-", random
BRIDGE_ENDPOINT_FILE = "bridge.endpoint"  # in that folder: where its bridge listens (stack_bridge_endpoints)


def _remove_stale_socket_folders(root: Path | None = None) -> list[Path]:
    """Remove the control path's socket folders (``SOCKETS_PREFIX<pid>-…`` in the temporary
    directory) left by an ``xneck up`` that was killed (SIGKILL skips its clean-up): this user's
    folders whose pid no longer runs. A pid taken by another process since keeps its folder (it
    goes at a later start); a folder of another user, or without a pid, is never touched."""
    root = Path(tempfile.gettempdir()) if root is None else root
    removed = []
    for folder in root.glob(f"{SOCKETS_PREFIX}*-*"):
        pid_text = folder.name[len(SOCKETS_PREFIX):].partition("-")[0]
        try:
            if not pid_text.isdigit() or folder.is_symlink() or folder.stat().st_uid != os.getuid():
                continue
            os.kill(int(pid_text), 0)
        except ProcessLookupError:
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
        except (OSError, ValueError, OverflowError):  # gone meanwhile, or another user's pid: alive
            continue
    return removed


def stack_bridge_endpoints(root: Path | None = None) -> dict[int, str]:
    """The bridge endpoint of each ``xneck up`` of this user that runs now (its pid -> what it
    wrote in its socket folder's :data:`BRIDGE_ENDPOINT_FILE`): where ``xneck estop`` reaches the
    bridge without the console, which may be the one that hangs (review of session 41)."""
    root = Path(tempfile.gettempdir()) if root is None else root
    found: dict[int, str] = {}
    for folder in sorted(root.glob(f"{SOCKETS_PREFIX}*-*")):
        pid_text = folder.name[len(SOCKETS_PREFIX):].partition("-")[0]
        try:
            if not pid_text.isdigit() or folder.is_symlink() or folder.stat().st_uid != os.getuid():
                continue
            os.kill(int(pid_text), 0)
            endpoint = (folder / BRIDGE_ENDPOINT_FILE).read_text(encoding="utf-8").strip()
        except (OSError, ValueError, OverflowError, UnicodeDecodeError):  # gone, another user's, no file
            continue
        if endpoint and len(endpoint) < 1000 and _runs_xneck_up(int(pid_text)):
            found[int(pid_text)] = endpoint
    return found


def _runs_xneck_up(pid: int) -> bool:
    """Whether process ``pid`` is an ``xneck up`` (its command line, where /proc has it): a folder
    a killed stack left keeps its pid, which another process may have taken since (review of
    session 41: a ``sleep`` there made ``xneck estop`` see two stacks and send nothing)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return not Path("/proc/self").exists()  # no /proc: alive is all that can be told
    words = [a.decode("utf-8", "replace") for a in argv if a]
    return "up" in words and any(w.endswith("xneck") or w == "server.cli" for w in words)


def _port_taken(host: str, port: int) -> str:
    """Why ``host:port`` cannot be bound now ('' if it can). SO_REUSEADDR as the servers use it,
    so a port in TIME_WAIT counts as free but one with a listener does not."""
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as exc:
            return "in use" if exc.errno == errno.EADDRINUSE else (exc.strerror or str(exc))
    return ""


def _tcp_address(endpoint: str) -> tuple[str, int] | None:
    """(host, port) of a ``tcp/<host>:<port>`` endpoint; None for other protocols or no port."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto != "tcp" or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def _bus_access(hub: str, no_bridge: bool) -> str:
    """One line on who may link to the stack's processes (bridge.bus_credentials, bridge.bus_tls)."""
    from bridge import bus_tls
    from bridge.bus_credentials import ENV_CREDENTIALS, from_env
    from bridge.session import exposed_endpoints

    creds, folder = from_env(), bus_tls.from_env()
    tls = f"; TLS {folder.path} for tls/ endpoints ({folder.days_left():.0f} days left)" if folder is not None else ""
    if creds is not None:
        viewers = f"; viewers {', '.join(creds.viewers)} may watch, not act" if creds.viewers else ""
        return f"bus: credentials {creds.path} (user {creds.user!r}): processes without them get no link{viewers}{tls}"
    if exposed_endpoints([hub]) or no_bridge:
        return (f"bus: no credentials: anyone on the network can link to the hub{' and the bridge' if no_bridge else ''}; "
                f"set {ENV_CREDENTIALS} (xneck bus credentials FILE; docs/safety.md, 'Who may link to the bridge'){tls}")
    return f"bus: loopback only, no credentials{tls}"


def _bridge_link(endpoint: str) -> str:
    """A note on a remote bridge at ``endpoint`` that this machine cannot link to now ('' if it can):
    the commissioning mistakes that otherwise look alike, a bridge that never appears."""
    from bridge.session import LINKED, NO_LISTENER
    from server.cli.bus import link_report

    state, sentence = link_report(endpoint)
    if state == LINKED:
        return ""
    if state == NO_LISTENER:
        return f"note: {sentence} yet: start the bridge there, or check the address (the controller waits for it)"
    return f"warning: {sentence} (docs/bridge.md, deployment step 3)"


def _stack_on(hub: str) -> list[str]:
    """Processes of an xneck stack answering on ``hub`` (their liveliness keys), ['a Zenoh peer'] for
    a Zenoh peer without any, [] when nothing Zenoh answers within :data:`PROBE_S`."""
    import zenoh

    from bridge import bus
    from bridge.session import zenoh_config

    with zenoh.open(zenoh_config(listen=[], connect=[hub.replace("0.0.0.0", "127.0.0.1")])) as probe:
        deadline = time.monotonic() + PROBE_S
        while not list(probe.info.peers_zid()) and time.monotonic() < deadline:
            time.sleep(0.05)
        if not list(probe.info.peers_zid()):
            return []
        # The hub's peers link to the probe by gossip, not at once: ask again for a short while.
        found: set[str] = set()
        while not found and time.monotonic() < deadline + PROBE_S:
            found = {"/".join(str(r.ok.key_expr).split("/")[2:])
                     for r in probe.liveliness().get(bus.ALIVE_ALL, timeout=0.25) if r.ok is not None}
            time.sleep(0.05)
    return sorted(found) or ["a Zenoh peer"]


def preflight(host: str, port: int, viser_port: int, hub: str) -> str:
    """The reason ``xneck up`` must not start (one line), or '' when it may."""
    hub_address = _tcp_address(hub)
    if hub_address is not None and hub_address[1] != 0:
        why = _port_taken(*hub_address)
        if why:
            stack = _stack_on(hub)
            if stack:
                return (f"another xneck stack answers on the hub {hub} ({', '.join(stack)}): stop it, or give this "
                        f"one its own --hub, --port, --viser-port and --data-dir")
            return (f"the hub endpoint {hub} is {why} (another program listens there, or a stack whose bus "
                    f"credentials differ): choose another --hub")
    why = _port_taken(host, port) if port else ""
    if why:
        return f"the dashboard port {host}:{port} is {why}: choose another --port"
    why = _port_taken(host, viser_port) if viser_port else ""
    if why:
        return f"the 3D view port {host}:{viser_port} is {why}: choose another --viser-port (0 = a free one)"
    return ""


def _healthy(url: str) -> bool:
    try:
        with urllib.request.urlopen(url + "api/system/health", timeout=1.0) as r:  # a loopback URL we built
            return r.status == 200
    except OSError:
        return False


def _bridge_seen(url: str) -> bool:
    """Whether the console at ``url`` has a motor state of a bridge (``/api/system/health``); any
    failure is a no (a console dying mid-answer raised http.client's errors, which are no OSError)."""
    try:
        with urllib.request.urlopen(url + "api/system/health", timeout=1.0) as r:  # a loopback URL we built
            return (json.loads(r.read(65536)).get("bridge") or {}).get("state_age_s") is not None
    except Exception:  # noqa: BLE001 - not yet, whatever the reason
        return False


def _watch_bridge_seen(url: str, seen: threading.Event, give_up: threading.Event) -> threading.Thread:
    """A daemon thread that sets ``seen`` once the console at ``url`` has the bridge's states
    (polled every 0.3 s until then or ``give_up``): off the supervisor's loop, which a hung or
    trickling console had held a second or more a pass, its hang detection as late (review of
    this session's diff)."""
    def poll() -> None:
        while not give_up.is_set() and not _bridge_seen(url):
            give_up.wait(0.3)
        if not give_up.is_set():
            seen.set()

    thread = threading.Thread(target=poll, name="xneck-up-bridge-seen", daemon=True)
    thread.start()
    return thread


def _token(data_dir: Path) -> str:
    """The console's API token, as it resolves it: ``XNECK_TOKEN``, else ``<data-dir>/token`` ('' if none)."""
    from server.settings import TOKEN_FILE

    token = os.environ.get("XNECK_TOKEN", "")
    if token:
        return token
    try:
        return (Path(data_dir) / TOKEN_FILE).read_text().strip()
    except OSError:
        return ""


def abort_campaign(url: str, token: str, cause: str, ended_within_s: float, stack_stopping: bool = False) -> str:
    """Tell the console at ``url`` that ``cause`` ends its running campaign (``POST
    /api/system/abort``; also one whose run ended within ``ended_within_s`` seconds, having seen
    the cause's side effect first). ``stack_stopping``: the stack stops next, the campaign gets no
    3D scene (its record is final at once, so the line printed is its final state). Returns one
    line for the operator: what became of which campaign, or why the console could not be told.
    Waits at most :data:`ABORT_TIMEOUT_S`."""
    if not token:
        return "the console could not be told why (no API token)"
    request = urllib.request.Request(  # a loopback URL we built
        url + "api/system/abort", method="POST",
        data=json.dumps({"reason": cause, "ended_within_s": round(min(ended_within_s, 60.0), 3),
                         "stack_stopping": stack_stopping}).encode(),
        headers={"Content-Type": "application/json", "Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(request, timeout=ABORT_TIMEOUT_S) as r:
            answer = json.loads(r.read())
    except (OSError, ValueError) as exc:
        return f"the console could not be told why ({exc})"
    if answer.get("campaign_id") is None:
        return "no campaign was running"
    return f"campaign {answer['campaign_id']} {answer['status']}: {answer['message']}"


def _say(text: str, err: bool = False, fg: str | None = None) -> None:
    """``typer.secho`` that never raises: once the terminal is gone (a closed SSH session: EIO) or
    the pipe it wrote to (``xneck up 2>&1 | tee up.log``, Ctrl-C killing ``tee`` too: EPIPE), a
    message on the supervisor's or the shutdown's path had raised out of it, skipping the stop of
    the children after it and a robot's `--drives-off` (review of session 53)."""
    with contextlib.suppress(OSError, ValueError):  # ValueError: a stream already closed
        typer.secho(text, err=err, fg=fg)


def drives_off(driver_args: list[str], param_args: list[str], log_file: Path) -> str:
    """Run ``xneck bridge <driver_args> --drives-off`` (output appended to ``log_file``), once
    more if it fails; one line for the operator saying whether the drives are off. In a session
    of its own: a second Ctrl-C to the terminal's process group had killed it half-way, the
    enable lines left high (audit of 2026-11-26)."""
    why = ""
    for _attempt in range(2):
        try:
            with open(log_file, "ab") as log:
                proc = subprocess.run(xneck_argv("bridge", *driver_args, *param_args, "--drives-off"), stdout=log,
                                      stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, timeout=DRIVES_OFF_TIMEOUT_S,
                                      env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True)
        except subprocess.TimeoutExpired:
            why = f"did not end within {DRIVES_OFF_TIMEOUT_S:.0f} s"
            continue
        except OSError as exc:  # no fork on a machine out of memory or processes, a log that cannot be opened
            why = f"could not be started ({exc.strerror or exc})"
            continue
        if proc.returncode == 0:
            return "the bridge did not end cleanly: its drives were disabled by `xneck bridge --drives-off`"
        why = f"failed ({exit_how(proc.returncode)}), see {log_file}"
    return f"DRIVES MAY BE ON: `xneck bridge --drives-off` {why}"


class _LoopPings:
    """Seconds since the robot bridge's real-time loop last said it ticks: the ``WATCHDOG=1``
    datagrams of :class:`bridge.runtime.SystemdNotify`, sent from the loop's own
    thread to a socket of this process (Linux abstract namespace) named in the child's
    ``NOTIFY_SOCKET``. This process stands in for systemd's watchdog. Judged by the bridge's motor
    states on the bus before, a healthy bridge was killed when the console, which hosts the hub,
    was stopped for 2.5 s and the states stalled with it (CI of 2026-11-27); the pings take no bus
    and no other process. Pings that queued while this process was stopped are read on its next
    pass, as fresh ones: a paused supervisor judges nothing stale."""

    def __init__(self) -> None:
        self.address = f"@xneck-up-{os.getpid()}-{os.urandom(4).hex()}"
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self._sock.bind("\0" + self.address[1:])
        self._sock.setblocking(False)
        self._last_ns: int | None = None

    def environ(self) -> dict[str, str]:
        """What the bridge's environment needs for the loop to ping here (``WATCHDOG_PID`` unset:
        the child's own)."""
        return {"NOTIFY_SOCKET": self.address, "WATCHDOG_USEC": str(int(PING_WATCHDOG_S * 1e6))}

    def age_s(self) -> float | None:
        """Reads every datagram that came; seconds since the latest ping (``None`` before the first:
        a bridge still starting is not judged)."""
        while True:
            try:
                data = self._sock.recv(4096)
            except OSError:  # BlockingIOError: nothing more
                break
            # READY=1 comes before the first tick, which may be slow on a loaded machine: only a
            # tick's ping starts the clock (CI of 541ce3d: judged from READY, a bridge whose first
            # ticks took over 1 s was killed; the bus's states had started it at the first state).
            if "WATCHDOG=1" in data.decode(errors="replace").splitlines():
                self._last_ns = time.monotonic_ns()
        last_ns = self._last_ns
        return None if last_ns is None else (time.monotonic_ns() - last_ns) / 1e9

    def restarted(self) -> None:
        """A new process pings here now: the old one's pings say nothing of it."""
        self.age_s()
        self._last_ns = None

    def close(self) -> None:
        self._sock.close()


def up(
    robot: bool = typer.Option(False, "--robot", help="Drive the BeagleBone's motors instead of the twin."),
    no_bridge: bool = typer.Option(False, "--no-bridge", help="The bridge runs elsewhere (e.g. on the BeagleBone) "
                                   "and connects to --hub, or listens at --bridge-at."),
    bridge_at_option: str | None = typer.Option(
        None, "--bridge-at", help="With --no-bridge: the endpoint the remote bridge listens on (e.g. "
        "tcp/<board>:7447, the bridge started with --listen tcp/0.0.0.0:7447). The controller and the console "
        "connect to it, so the control path never retries a hung console (docs/safety.md)."),
    # The console's own variables (server.settings: XNECK_HOST, XNECK_PORT, XNECK_DATA_DIR), since up
    # hands these to `xneck server` as options, which override them: a lab's XNECK_DATA_DIR was ignored
    # by up while `xneck campaign` recorded into it as "the console's data directory".
    host: str = typer.Option("127.0.0.1", "--host", envvar="XNECK_HOST", help="Dashboard bind address "
                             "(default 127.0.0.1, $XNECK_HOST)."),
    port: int = typer.Option(8000, "--port", min=1, max=PORT_MAX, envvar="XNECK_PORT",
                             help="Dashboard HTTP port (1-65535; default 8000, $XNECK_PORT)."),
    viser_port: int = typer.Option(0, "--viser-port", min=0, max=PORT_MAX,
                                   help="Port of the 3D view (0: a free one; at most 65535)."),
    hub: str = typer.Option("tcp/127.0.0.1:7447", "--hub", help="Zenoh endpoint the server listens on and the "
                            "others connect to. Use tcp/0.0.0.0:7447 for a bridge on another machine."),
    data_dir: Path = typer.Option(Path("data"), "--data-dir", envvar="XNECK_DATA_DIR",
                                  help="Archives, parameter sets, token, logs (default ./data, $XNECK_DATA_DIR)."),
    law: int = typer.Option(2, "--law", help="Law the controller holds with between campaigns."),
    driver_config: Path | None = typer.Option(None, "--driver-config", help="BeagleBone wiring and ESCON points (TOML)."),
    seed: int = typer.Option(0, "--seed", min=0, max=2**31 - 1, help="Seed of the twin's sensor noise "
                             "(0 to 2³¹ − 1, what the console accepts as --twin-seed)."),
    truth: str = typer.Option("robot", "--truth", callback=check_truth, help="What the stack's twin simulates: the "
                              "robot's unmodelled physics (robot, the default: twin/sim/robot_truth.toml, so that the "
                              "campaigns run here are not the controller's own model), the parameter file as it is "
                              "(model), or a truth FILE; see twin/sim/truth.py."),
    params_file: Path | None = typer.Option(None, "--params", help="Parameter file (default: the 3-X prototype)."),
    alpha_ip: str = typer.Option("noise", "--alpha-ip", help="Twin's α_IP: noise (the true α plus the camera's white "
                                 "noise) or camera (an `xneck camera --source twin` process renders the truth at 30 fps "
                                 "and detects the markers, as the robot's camera would; costs about a fifth of a core)."),
    exit_after: float | None = typer.Option(None, "--exit-after", callback=NON_NEGATIVE, help="Stop everything "
                                            "after this many seconds (tests, demos)."),
    loop_stall: float | None = typer.Option(
        None, "--loop-stall", callback=NON_NEGATIVE,
        help="The bridge's loop watchdog (s, at least 0.05; 0: off): when its loop makes no tick for this long, the "
        "bridge disables the drives and exits with code 70, as `xneck bridge --loop-stall`. Default: the bridge's "
        "(0.5 with --robot, off on the twin)."),
    restarts: int = typer.Option(0, "--restarts", min=0, max=100, help="Restart a controller or camera that dies, "
                                 "at most this many times in 10 minutes (default 0: any death stops the stack), after "
                                 "1 s, 2 s, 4 s, ... (at most 30 s) for its 1st, 2nd, 3rd, ... restart in them. The "
                                 "bridge holds the neck meanwhile; a running campaign ends aborted naming the death."),
) -> None:
    """Start the bridge, the controller and the server as separate processes and print the URL."""
    if bridge_at_option is not None and not no_bridge:
        raise fail("--bridge-at names a bridge that runs elsewhere: it needs --no-bridge")
    if bridge_at_option is not None:
        check_endpoints(["tcp/127.0.0.1:0"], [bridge_at_option])  # one error line for a malformed endpoint
    if alpha_ip not in ("noise", "camera"):
        raise fail(f"--alpha-ip must be noise or camera, not {alpha_ip!r}")
    if loop_stall is not None:  # now, not as a bridge that exits once the stack is up
        from bridge.loop_watchdog import MIN_STALL_S

        if no_bridge:
            raise fail("--loop-stall sets the watchdog of the bridge `xneck up` starts: not with --no-bridge "
                       "(give it to that bridge's `xneck bridge`)")
        if 0 < loop_stall < MIN_STALL_S:
            raise fail(f"--loop-stall must be 0 (off) or at least {MIN_STALL_S} s, not {loop_stall:g}")
    law_config(law, False)  # a bad --law now, not as a controller that exits once the stack is up
    # Likewise a --params or --driver-config that does not load: it was the bridge's exit once the
    # stack was up ("xneck is up" printed first), and with --robot a failed --drives-off besides.
    load_cli_params(params_file, None)
    if robot and not no_bridge:
        from server.cli.processes import _driver_table

        _driver_table(driver_config)
    check_credentials()  # every child reads them: one line now, not a failure per process
    hub_address = _tcp_address(hub)
    if hub_address is not None and hub_address[1] > PORT_MAX:  # the socket module would raise OverflowError
        raise fail(f"--hub {hub}: the port must be at most {PORT_MAX}")
    refused = preflight(host, port, viser_port, hub)
    if not refused:
        # Before anything starts: a second stack on a data directory in use started a console that
        # refused, and printed the tail of the shared logs/server.log, the first console's API
        # token included (audit of 2026-11-28).
        from server.datadir import DataDirError, DataDirInUse, DataDirLock

        with contextlib.suppress(DataDirError):  # any other fault: the one line below, as before
            try:
                DataDirLock(Path(data_dir)).release()
            except DataDirInUse as exc:
                refused = str(exc)
    if refused:
        typer.secho(f"error: xneck up refused to start: {refused}", err=True, fg="red")
        raise typer.Exit(PREFLIGHT_EXIT)
    logs = Path(data_dir) / "logs"
    try:
        logs.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # e.g. a read-only data directory: one line, nothing started
        from bridge.archive import storage_reason

        typer.secho(f"error: cannot use the data directory {data_dir}: {storage_reason(exc)}", err=True, fg="red")
        raise typer.Exit(2) from None
    # This process too runs off the loop's CPUs, as the console does: its bus session's threads,
    # which judge whether the bridge is hung, must not queue there below the real-time threads (CI:
    # a controller importing for 2.7 s at FIFO 49 starved them and a healthy bridge was killed).
    isolate_self("up")
    from bridge.session import ENV_CONNECT, ENV_LISTEN

    bridge_link = _bridge_link(bridge_at_option) if bridge_at_option else ""

    connect_to = hub.replace("0.0.0.0", "127.0.0.1")
    common = ["--listen", "tcp/127.0.0.1:0", "--connect", connect_to]
    # The control path's own endpoints (module docstring): the console connects to them, they never
    # to the console. Unix sockets, not loopback TCP: closing a TCP link (a peer leaving, a console's link after its
    # lease) blocks Zenoh's poller until the peer acknowledges (SO_LINGER, hard-coded in Zenoh), ~40
    # ms when its ACK is delayed, a bridge hold (benchmarks/peer_churn.py); a Unix socket's close does
    # not wait. The folder is this user's alone (0700), which loopback TCP ports are not.
    _remove_stale_socket_folders()
    sockets = Path(tempfile.mkdtemp(prefix=f"{SOCKETS_PREFIX}{os.getpid()}-"))
    bridge_at = bridge_at_option if no_bridge else f"unixsock-stream/{sockets / 'bridge.sock'}"
    controller_at = f"unixsock-stream/{sockets / 'controller.sock'}"
    control_path = [arg for at in (bridge_at, controller_at) if at for arg in ("--connect", at)]
    estop_at = bridge_at or connect_to  # a bridge without --bridge-at connects to the hub
    (sockets / BRIDGE_ENDPOINT_FILE).write_text(estop_at + "\n", encoding="utf-8")
    param_args = ["--params", str(params_file)] if params_file else []
    url = f"http://{host}:{port}/"
    procs: dict[str, subprocess.Popen] = {}
    log_files: dict[str, Path] = {}
    stop = {"signal": ""}

    def on_signal(signum: int, _frame: object) -> None:
        stop["signal"] = signal.Signals(signum).name

    # A closed terminal or a dropped SSH session (SIGHUP) and SIGQUIT stop the stack as Ctrl-C does:
    # the default action killed this process at once and left its children unsupervised.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT):
        signal.signal(sig, on_signal)
    # `kill -USR1 <pid>` writes every thread's stack to stderr (the log): where a stack that seems
    # stuck waits (a hung bridge twice left unjudged on CI, the log silent after start-up).
    faulthandler.register(signal.SIGUSR1, all_threads=True)

    started_with: dict[str, tuple[list[str], dict[str, str] | None]] = {}
    plan = RestartPlan(restarts)  # on time.monotonic()
    telling: list[threading.Thread] = []  # the console told of restarts, off the loop

    def tell_console(cause: str, ended_within_s: float, colour: str) -> None:
        _say(abort_campaign(url, _token(data_dir), cause, ended_within_s), err=True, fg=colour)

    def told_before() -> None:
        """Wait (bounded) for the restarts' messages to the console, so that it hears the causes in order."""
        for thread in telling:
            thread.join(ABORT_TIMEOUT_S)

    def start(name: str, args: list[str], env: dict[str, str] | None = None) -> None:
        started_with[name] = (args, env)
        log_files[name] = logs / f"{name}.log"
        if plan.used(name):
            # where the new process's lines begin: a child that died before writing any had its
            # predecessor's last lines shown as its own (audit of session 44)
            with open(log_files[name], "a", encoding="utf-8") as log:
                log.write(f"---- xneck up: {name} restarted ({plan.used(name)} of {restarts}) at "
                          f"{time.strftime('%Y-%m-%d %H:%M:%S')} ----\n")
        # The endpoints are given on each command line: a user's XNECK_ZENOH_* must not add others.
        child_env = {**{k: v for k, v in os.environ.items() if k not in (ENV_LISTEN, ENV_CONNECT)},
                     "PYTHONUNBUFFERED": "1", ENV_PARENT: str(os.getpid()), **loop_environ(args[0]), **(env or {})}
        if env and "NOTIFY_SOCKET" in env:
            child_env.pop("WATCHDOG_PID", None)  # inherited from a systemd unit of ours it would name us, not the child
        procs[name] = start_xneck(args, log_files[name], child_env, append=True, start_new_session=True)
        # The loop's processes on their CPU, the console off it (issue 21); a loop process takes
        # its real-time priority itself once set up (loop_environ: at its exec, its imports had
        # starved another stack's controller until it was killed as hung; fresh-user audit of 2026-12-01).
        isolate(procs[name].pid, args[0], realtime=False)

    code = 0
    bridge_seen, stop_polling = threading.Event(), threading.Event()  # "xneck is up" waits for the bridge's states
    watch = _LoopPings() if robot and not no_bridge else None
    controller_watch = _LoopPings()
    driver: list[str] = []
    bridge_instance = f"bridge-up-{os.getpid()}"
    camera = alpha_ip == "camera" and not robot and not no_bridge
    camera_instance = f"camera-up-{os.getpid()}"  # named to the console: another twin-render camera is not it
    drives_set_off = False
    try:
        start("server", ["server", "--host", host, "--port", str(port), "--data-dir", str(data_dir), "--hub", hub,
                         *control_path, "--stack",
                         "--mode", "robot" if robot else "twin", "--viser-port", str(viser_port),
                         # what this stack's twin bridge is, so that campaign requests are checked against it
                         "--twin-truth", truth, "--twin-seed", str(seed),
                         # the one camera its campaigns record, whatever other α_IP is on the hub (server.quality)
                         *(["--twin-alpha-ip", alpha_ip] if not robot and not no_bridge else []),
                         *(["--twin-camera", camera_instance] if camera else [])])
        deadline = time.monotonic() + 60
        while not _healthy(url):
            if procs["server"].poll() is not None or time.monotonic() > deadline or stop["signal"]:
                raise RuntimeError(f"the server did not come up:\n{log_tail(log_files['server'], LOG_LINES)}")
            time.sleep(0.2)
        if camera:  # before the twin, so its first truth is seen; off the loop's CPU like the console
            start("camera", ["camera", "--source", "twin", "--seed", str(seed), "--instance", camera_instance,
                             *common, *param_args])
        if not no_bridge:
            driver = ["--driver", "beaglebone"] + (["--driver-config", str(driver_config)] if driver_config else []) \
                if robot else ["--driver", "twin", "--seed", str(seed), "--truth", truth] + (["--no-camera"] if camera else [])
            start("bridge", ["bridge", *driver, "--instance", bridge_instance, "--listen", str(bridge_at),
                             "--no-autoconnect", *param_args,
                             *([] if loop_stall is None else ["--loop-stall", repr(loop_stall)])],
                  watch.environ() if watch is not None else None)
        # Without --bridge-at the bridge and the controller meet on the hub: gossip must link them.
        start("controller", ["controller", "--law", str(law), "--listen", controller_at,
                             "--connect", connect_to if bridge_at is None else bridge_at,
                             *([] if bridge_at is None else ["--no-autoconnect"]), *param_args],
              controller_watch.environ())
        token_file = Path(data_dir) / "token"

        def describe() -> None:
            _say(f"  bus hub {hub}; {'robot (BeagleBone)' if robot else f'twin ({truth} truth)'} bridge"
                 f"{(' expected at ' + bridge_at if bridge_at else ' expected on the hub') if no_bridge else ''}"
                 f", controller service (law {law})")
            if bridge_link:
                _say(f"  {bridge_link}")
            if no_bridge and not bridge_at:
                _say("  note: a bridge that connects to the hub retries it while this console hangs, one bumpless "
                     "hold per retry; a listening bridge and --bridge-at avoid that (docs/bridge.md, deployment)")
            _say(f"  {_bus_access(hub, no_bridge)}")
            _say(f"  e-stop from a terminal, the console down too: xneck estop engage (its bridge: {estop_at})")
            _say(f"  API token in {token_file}; logs in {logs}; Ctrl-C stops everything")

        # "up" once a campaign can start: the controller's loop runs (its service is on the bus, its
        # warm-up done) and, with a bridge of this stack, the console has its motor states. Said
        # as soon as the children were started, a campaign asked for at once got 503 "the
        # controller service is not on the bus (being restarted ..., or stopped)" for 20-28 s on a
        # loaded machine, which reads as a crash (fresh-user audit of 2026-12-01).
        _say(f"xneck is starting: console {url} up; waiting for the {'controller' if no_bridge else 'bridge and the controller'}…")
        describe()
        announced, hinted = False, False
        if not no_bridge:
            _watch_bridge_seen(url, bridge_seen, stop_polling)
        started = seen_alive = last_pass = time.monotonic()  # when every child was last seen running
        # Why a child was killed, kept until its death is handled: one slow to exit after SIGKILL
        # dies a pass or more later, and had been said to have "exited (signal SIGKILL)" (review).
        hung: dict[str, str] = {}
        while not stop["signal"]:
            if not announced and controller_watch.age_s() is not None and (no_bridge or bridge_seen.is_set()):
                _say(f"xneck is up: dashboard {url}  (API docs {url}docs)")
                announced = True
                stop_polling.set()
            elif not announced and not hinted and time.monotonic() - started > READY_HINT_S:
                hinted = True
                _say(f"  still starting after {READY_HINT_S:.0f} s (a loaded machine, or see the logs in {logs})",
                     err=True, fg="yellow")
            polled = time.monotonic()
            # A pass that comes late (this process stopped, e.g. Ctrl-Z then fg, the children with it)
            # does not count its own lateness: the pings' age grew with the pause (audit of
            # 2026-11-26: a healthy bridge killed). Subtracted, not skipped: a supervisor late on
            # every pass (a starved CPU) had never judged a hung bridge (final CI of session 45).
            lateness_s, last_pass = max(0.0, polled - last_pass - 0.2), polled
            for name, pings, limit_s in (("bridge", watch, BRIDGE_HUNG_S), ("controller", controller_watch,
                                                                            CONTROLLER_HUNG_S)):
                raw = pings.age_s() if pings is not None else None
                age = None if raw is None else raw - lateness_s
                if age is not None and age > limit_s and procs[name].poll() is None:
                    # Hung: SIGTERM would wait on a loop that does not run. Not waited for long: one
                    # whose exit is slow (starved) is judged dead on a later pass, while this loop
                    # goes on watching the others (its wait's timeout had ended xneck up).
                    if not kill_child(procs[name], HUNG_KILL_WAIT_S) and name not in hung:
                        # Killed but its threads cannot run their exit (a CPU held by real-time work:
                        # a killed FIFO process on the loop's CPU waits for every higher task there).
                        # Said at once (the log had stayed silent after start-up, CI of session 52),
                        # and a robot's drives set off now, beside it (`--drives-off` may run beside a
                        # bridge): set off after its exit only, they had stayed enabled for as long as
                        # the exit was late.
                        _say(f"warning: the {name} hung (its loop silent for {age:.1f} s): killed, not exited "
                             f"after {HUNG_KILL_WAIT_S:g} s ({process_state(procs[name].pid)}); waiting for it",
                             err=True, fg="yellow")
                        if name == "bridge" and robot:  # and again after its exit (drives_set_off stays False):
                            # a thread preempted in a system call (a GPIO write) ends that call first
                            _say(drives_off(driver, param_args, log_files["bridge"]), err=True, fg="red")
                    hung.setdefault(name, f"hung (its loop silent for {age:.1f} s), killed")
            for name in plan.due(polled):  # its back-off over
                if name == "controller":  # its endpoint, left by the dead process, for the new one to listen on
                    with contextlib.suppress(OSError):
                        (sockets / "controller.sock").unlink()
                    controller_watch.restarted()
                start(name, *started_with[name])
                _say(f"  {name} restarted (pid {procs[name].pid})")
            # a child waiting for its restart is not a new death
            dead = [(n, p.returncode) for n, p in procs.items() if p.poll() is not None and not plan.waiting(n)]
            plan.forget_old(polled)
            # What stops the stack first (a bridge or console before a child that may be restarted:
            # the bridge's death had been named "camera exited" when both died in one pass).
            dead.sort(key=lambda d: plan.may_restart(d[0]))
            if dead and plan.may_restart(dead[0][0]):
                causes = []
                for name, rc in dead:  # every one restartable, with a restart left
                    how = hung.pop(name, None) or f"exited ({exit_how(rc)})"
                    # Started again by a later pass once its delay is over: this loop goes on judging
                    # the others meanwhile (the bridge's watchdog holds the neck while the controller is away).
                    delay_s = plan.plan(name, polled)
                    restarting = (f"restarting {name} in {delay_s:.0f} s ({plan.used(name)} of {restarts} "
                                  f"within {RESTART_WINDOW_S / 60:.0f} min)")
                    causes.append(f"{name} process {how}, {restarting}")  # the console's header shows it
                    _say(f"warning: the {name} {how}; {restarting}.\n"
                         f"last lines of {log_files[name]}:\n{log_tail(log_files[name], LOG_LINES)}", err=True,
                         fg="yellow")
                # Off the loop: a console that hangs had held the restart 15 s (and this loop with it).
                telling.append(threading.Thread(
                    target=tell_console, name="xneck-up-abort", daemon=True,
                    args=("; ".join(causes), time.monotonic() - seen_alive + ABORT_WINDOW_MARGIN_S, "yellow")))
                telling[-1].start()
                seen_alive = last_pass = time.monotonic()
                continue
            if dead:
                name, rc = dead[0]
                bridge_rc = next((c for n, c in dead if n == "bridge"), 0)
                if robot and bridge_rc != 0:
                    # The drives first, whichever death is named: with the console dead in the same
                    # pass (listed first) they had waited for the controller's stop, up to 16 s
                    # (review of session 53).
                    _say(drives_off(driver, param_args, log_files["bridge"]), err=True, fg="red")
                    drives_set_off = True
                how = hung.get(name) or f"exited ({exit_how(rc)})"
                more = f" ({plan.used(name)} restart(s) within {RESTART_WINDOW_S / 60:.0f} min used up)" \
                    if restarts and name in RESTARTABLE else ""
                also = "".join(f"; the {n} {hung.get(n) or f'exited ({exit_how(c)})'} too" for n, c in dead[1:])
                _say(f"error: the {name} {how}{more}{also}; stopping the stack, nothing "
                     f"{'more ' if more else ''}is restarted.\n"
                     f"last lines of {log_files[name]}:\n{log_tail(log_files[name], LOG_LINES)}", err=True, fg="red")
                if name != "server":  # the console ends its campaign with the cause before the rest stops
                    told_before()
                    _say(abort_campaign(url, _token(data_dir), f"{name} process {how}",
                                        time.monotonic() - seen_alive + ABORT_WINDOW_MARGIN_S, stack_stopping=True),
                         err=True, fg="red")
                code = 1
                break
            seen_alive = polled
            if exit_after is not None and time.monotonic() - started > exit_after:
                break
            time.sleep(0.2)
        if code == 0 and procs.get("server") is not None and procs["server"].poll() is None:
            # The operator's stop (Ctrl-C, SIGTERM, --exit-after) ends a running campaign with that
            # cause before the controller and the bridge stop: it had recorded their stop's side
            # effect, "the drives were disabled during the campaign" (audit of 2026-11-28).
            why = f"xneck up was stopped ({stop['signal']})" if stop["signal"] else "xneck up reached --exit-after"
            told_before()
            told = abort_campaign(url, _token(data_dir), why, 0.0, stack_stopping=True)
            if told != "no campaign was running":
                _say(told, err=True, fg="yellow")
    except RuntimeError as exc:
        _say(f"error: {exc}", err=True, fg="red")
        code = 1
    finally:
        stop_polling.set()
        for name in ("controller", "bridge", "camera", "server"):
            p = procs.get(name)
            if p is not None and (how := stop_child(p, STOP_GRACE_S)):
                _say(f"{name} did not stop within {STOP_GRACE_S:.0f} s: {how}", err=True, fg="yellow")
            if name == "bridge" and robot and p is not None and p.returncode != 0 and not drives_set_off:
                _say(drives_off(driver, param_args, log_files["bridge"]), err=True, fg="red")
        if watch is not None:
            watch.close()
        controller_watch.close()
        shutil.rmtree(sockets, ignore_errors=True)
        _say(f"xneck stopped{' (' + stop['signal'] + ')' if stop['signal'] else ''}")
    if code:
        raise typer.Exit(code)
