"""Zenoh sessions for xneck processes, and typed publishers and subscribers of the bus contract.

Discovery is explicit: multicast scouting is off (labs share networks, tests share machines), one
process listens on a known endpoint and the others connect to it. Gossip scouting stays on so that
two processes connected to the same listener find each other and link directly (Zenoh >= 1.9 peers
no longer relay for each other). Every process also listens, on an ephemeral loopback port by
default, so that gossip has somewhere to connect.

Environment (comma-separated Zenoh endpoints, e.g. ``tcp/127.0.0.1:7447``):
    ``XNECK_ZENOH_LISTEN``   endpoints to listen on (default ``tcp/127.0.0.1:0``),
    ``XNECK_ZENOH_CONNECT``  endpoints to connect to (default none),
    ``XNECK_ZENOH_CREDENTIALS`` a credentials file: only processes that share it link (see
                             :mod:`bridge.bus_credentials`), ``XNECK_ZENOH_USER`` its entry to present,
    ``XNECK_ZENOH_TLS``      a TLS folder for ``tls/`` endpoints (:mod:`bridge.bus_tls`).
Across machines, the listening process uses ``tcp/0.0.0.0:7447`` and the others connect to it;
on a network others share, with credentials.

Importing this module gives the process's Zenoh runtime :data:`ZENOH_RX_WORKERS` receive workers
(``ZENOH_RUNTIME``, unless already set), see :func:`zenoh_runtime_environment`.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import random
import re
import socket
import threading
import time
from collections.abc import Callable, MutableMapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

import zenoh

from bridge import bus, bus_credentials, bus_tls
from bridge.bus_credentials import Credentials
from bridge.bus_tls import Tls

log = logging.getLogger(__name__)

ENV_LISTEN = "XNECK_ZENOH_LISTEN"
ENV_CONNECT = "XNECK_ZENOH_CONNECT"
DEFAULT_LISTEN = ("tcp/127.0.0.1:0",)
MODES = ("peer", "client", "router")

#: Keys on the control path: sent at once (no batching) at the highest priority.
REAL_TIME_KEYS = frozenset({bus.MOTOR_STATE, bus.MOTOR_COMMAND, bus.ESTOP})
#: Rare messages that must not be lost: under congestion the publisher waits instead of dropping.
#: Every other key is a stream where the newest value matters and a stale one is worse than none.
RELIABLE_KEYS = frozenset({bus.ESTOP, bus.CAMPAIGN_EVENTS, bus.CAMPAIGN_REQUEST})
#: Transmit queue of the real-time priority, in batches (one express message each); see zenoh_config.
REAL_TIME_QUEUE_BATCHES = 16

#: The Zenoh attachment of every message a replay republishes (server/replay.py): a recorded
#: state is not the bridge's word now, and a console that took it for one showed the e-stop
#: released while the bridge held it engaged (audit of 2026-11-28). :func:`replayed` tells it.
REPLAYED = b"xneck-replay"


def replayed(sample: zenoh.Sample) -> bool:
    """Whether ``sample`` was republished by a replay (:data:`REPLAYED`)."""
    attachment = sample.attachment
    return attachment is not None and attachment.to_bytes() == REPLAYED


#: The Zenoh attachment of every message a bridge publishes beside its states (its driver's: the
#: twin's ``Truth`` and α_IP), ``xneck-run:<epoch>``: the bridge run (``MotorState.epoch``) it
#: comes from. A ``Truth`` carries no identity of its own, and a stray twin's was archived and
#: shown beside the campaign twin's (audit of 2026-11-29); :func:`run_of` tells whose it is.
#:
#: An attachment, not a field or a key: a ``Truth`` field would be ``Truth`` v2, and a reader
#: accepts exactly one version (``bridge.bus``, "Version rule"), so every archive recorded before
#: would no longer read (``bridge.archive_read``); a key (``xneck/twin/truth/<epoch>``) would move
#: the truth off ``/xneck/twin/truth``, where every analysis of an archive reads it. The payload
#: and the archive's topics stay as they were; the recorder uses the run to keep only the
#: campaign's twin's truth (``server.quality.CampaignMonitor.keep``), so what an archive holds
#: needs no identity to be read. A replay's messages carry :data:`REPLAYED` instead: no run.
RUN_PREFIX = b"xneck-run:"


#: Characters of a sender's name an attachment may give (:meth:`SenderAttachment.of`): twice an
#: instance name's (bridge.safety.INSTANCE_NAME, 64).
NAME_MAX_CHARS = 128


#: Bytes of an attachment read for a sender's name at most; a longer one names no sender and is not
#: copied: a peer's 50 MB attachments on e-stop messages, copied under the bridge's e-stop lock,
#: stretched its ticks to 110 ms (audit of session 42).
MAX_ATTACHMENT_BYTES = 16384


@dataclass(frozen=True)
class SenderAttachment:
    """A Zenoh attachment that names where a message comes from: ``prefix`` + an ASCII name. The
    payload and the archive stay as they were (:data:`RUN_PREFIX`, why an attachment)."""

    prefix: bytes

    def attachment(self, name: str) -> bytes:
        """The attachment naming ``name``."""
        return self.prefix + name.encode()

    def of(self, sample: zenoh.Sample) -> str:
        """What ``sample``'s attachment names after the prefix, '' if it has no such attachment;
        as plain text of :data:`NAME_MAX_CHARS` at most (:func:`bridge.bus.plain_text`): any peer
        may name itself, and the names are kept, logged and shown (a camera's 4000 characters
        went to the camera API: review of session 41). An attachment longer than
        :data:`MAX_ATTACHMENT_BYTES` names nobody ('')."""
        attachment = sample.attachment
        if attachment is None or len(attachment) > MAX_ATTACHMENT_BYTES:
            return ""
        data = attachment.to_bytes()
        if not data.startswith(self.prefix):
            return ""
        return bus.plain_text(data[len(self.prefix):len(self.prefix) + 4 * NAME_MAX_CHARS].decode("ascii", "replace"),
                              NAME_MAX_CHARS)


RUN = SenderAttachment(RUN_PREFIX)
#: The bridge run (epoch) a sample says it comes from, '' if none; and the attachment naming one.
run_of, run_attachment = RUN.of, RUN.attachment

#: The Zenoh attachment of what a camera process publishes (its α_IP and frames),
#: ``xneck-camera:<instance>``: the camera it comes from. ``CameraAlpha.source`` names the kind of
#: source (``twin-render``, ``usb:0``), not the camera: two cameras of one kind on one bus had their
#: α_IP archived as one camera's (audit of 2026-11-29); :func:`camera_of` tells whose it is.
CAMERA = SenderAttachment(b"xneck-camera:")
camera_of, camera_attachment = CAMERA.of, CAMERA.attachment

#: The Zenoh attachment of a controller's ``ControllerStatus``, ``xneck-controller:<instance>``: the
#: controller it comes from. The status has no sender field; with a second controller on the bus
#: the console took the newest status of either for the campaign the bridge's owner runs (session 40).
CONTROLLER = SenderAttachment(b"xneck-controller:")
controller_of, controller_attachment = CONTROLLER.of, CONTROLLER.attachment

#: The Zenoh attachment of an ``EStop`` sent by an e-stop holder, ``xneck-estop-holder:<holder>``: the
#: holder whose token (:data:`bridge.bus.ESTOP_ENGAGED_ALL`) its release lets go of, since the token's
#: vanishing and the release reach a bridge in either order (:class:`bridge.safety.EStopHolders`).
ESTOP_HOLDER = SenderAttachment(b"xneck-estop-holder:")
estop_holder_of, estop_holder_attachment = ESTOP_HOLDER.of, ESTOP_HOLDER.attachment


#: Sessions a process accepts (Zenoh's default: 1000). A stack links every pair of its processes
#: (gossip), a dozen at most; each session of a subscriber costs the bridge a send per state (500 Hz).
MAX_SESSIONS = 64
#: Back-off of a lost or not-yet-listening connect endpoint, ms: first retry, cap. Zenoh's default
#: (1000 ms doubling to 4000 ms) left a process that started before its peer unlinked for up to
#: 4 s: a bridge started while an ``xneck estop engage --hold`` connected to it ran that long
#: unlatched, a controller restarted with its bridge that long deaf. A retry costs one refused SYN,
#: or a whole handshake against a peer that accepts and then refuses (wrong credentials, a full
#: session table; TLS on the board's one core): at most one a second (a 0.5 s cap made 23 in 10 s
#: against Zenoh's 4, review of session 42). ``docs/safety/relink.py`` measures both.
CONNECT_RETRY_MS = (100, 1000)
#: Gossip's autoconnect of a process that opens no link by itself (``zenoh_config(autoconnect=False)``):
#: only its ``connect`` endpoints; the peers that gossip tells of it link to it instead. For the
#: control path (``xneck up``'s bridge and controller), whose only links are then its own to its
#: peer and the ones it accepts, on Unix sockets: a TCP link it opened to a tool that stops reading
#: lingers on close (SO_LINGER, hard-coded in Zenoh) on the one thread of Zenoh's ``net`` runtime,
#: which also serves the links the process opened, the controller's to the bridge among them
#: (docs/safety.md, "Peers that stop reading"; tests/test_up_links.py).
NO_AUTOCONNECT = "{router: [], peer: []}"
#: Read the credentials from the environment (zenoh_config's default).
FROM_ENV = "env"

#: Zenoh's receive workers in every xneck process (Zenoh's default: 2).
ZENOH_RX_WORKERS = 8
ENV_ZENOH_RUNTIME = "ZENOH_RUNTIME"

M = TypeVar("M", bound=bus.BusMessage)


def zenoh_runtime_environment(environ: MutableMapping[str, str] = os.environ) -> str:
    """Set ``ZENOH_RUNTIME`` for :data:`ZENOH_RX_WORKERS` receive workers unless it is set; returns
    the value in force. Zenoh reads it once, when the process opens its first session.

    Why: Zenoh's TCP links linger 10 s on close (SO_LINGER, hard-coded in zenoh-link-tcp), so
    closing the link of a peer that stopped reading (a console machine suspended or unplugged, a
    stopped process) with its receive window full blocks the worker that closes it, after the
    lease (10 s), for up to 10 s more (eclipse-zenoh/zenoh#1101). With Zenoh's 2 receive workers,
    two such peers (the console and its campaign runner, a recorder) left a process deaf for 10 s:
    no state for the controller, no command nor e-stop for the bridge (tests/test_bus_dead_peers.py).
    Each such peer holds one worker; 8 leave room for a whole console machine's processes.
    """
    value = environ.setdefault(ENV_ZENOH_RUNTIME, f"(rx: (worker_threads: {ZENOH_RX_WORKERS}))")
    if not re.search(r"\brx\s*:", value):
        log.warning("%s=%r sets no receive workers (rx): Zenoh's 2 leave this process deaf for up to 10 s "
                    "when two peers stop reading (docs/safety.md, 'Peers that stop reading')", ENV_ZENOH_RUNTIME, value)
    return value


zenoh_runtime_environment()


def endpoints_from_env(name: str) -> list[str] | None:
    raw = os.environ.get(name, "").strip()
    if not raw:
        return None
    return [e.strip() for e in raw.split(",") if e.strip()]


def _check_endpoints(what: str, endpoints: Sequence[str]) -> list[str]:
    if isinstance(endpoints, str):
        raise TypeError(f"{what} endpoints must be a list of strings, not one string {endpoints!r}")
    checked = []
    for e in endpoints:
        proto, sep, address = str(e).partition("/")
        if not sep or not proto or not address:
            raise ValueError(f"{what} endpoint {e!r} is not of the form <protocol>/<address>, e.g. tcp/127.0.0.1:7447")
        if proto in ("tcp", "udp", "tls", "quic"):
            # Zenoh takes a port over 65535 and the link then fails as "nothing listens" or a
            # traceback, far from its cause (audit of 2026-11-27)
            port = address.partition("#")[0].rpartition(":")[2]
            if port.isdigit() and int(port) > 65535:
                raise ValueError(f"{what} endpoint {e!r}: the port must be at most 65535, got {port}")
        checked.append(str(e))
    return checked


def zenoh_config(
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    mode: str = "peer",
    credentials: Credentials | str | None = FROM_ENV,
    tls: Tls | str | None = FROM_ENV,
    autoconnect: bool = True,
) -> zenoh.Config:
    """Zenoh configuration of an xneck process.

    ``listen`` / ``connect``: endpoint lists; None takes ``XNECK_ZENOH_LISTEN`` /
    ``XNECK_ZENOH_CONNECT`` from the environment, then the defaults (listen on an ephemeral
    loopback port, connect to nothing). An empty list means none. ``mode``: peer, client or router.
    ``credentials``: :data:`FROM_ENV` (``XNECK_ZENOH_CREDENTIALS``, if set), None for none, or
    loaded credentials; with credentials the process links only with processes that present an
    entry of its file and accept its own (bridge.bus_credentials; raises CredentialsError, a
    ValueError, for a file that cannot be used), and drops what the file's viewers publish.
    ``tls``: :data:`FROM_ENV` (``XNECK_ZENOH_TLS``, if set), None or a loaded folder: ``tls/``
    endpoints encrypt and authenticate both ends (bridge.bus_tls; raises TlsError, a ValueError);
    a ``tls/`` endpoint without one is refused.
    ``autoconnect``: open links to the peers gossip names (default); False: open only the
    ``connect`` links, and let the others link to this process (:data:`NO_AUTOCONNECT`, why).
    Connections are retried in the background, so a process may start before its listener.
    """
    if mode not in MODES:
        raise ValueError(f"zenoh mode {mode!r} is not one of {MODES}")
    if listen is None:
        listen = endpoints_from_env(ENV_LISTEN) or list(DEFAULT_LISTEN)
    if connect is None:
        connect = endpoints_from_env(ENV_CONNECT) or []
    listen = _check_endpoints("listen", listen)
    connect = _check_endpoints("connect", connect)
    if isinstance(credentials, str):
        if credentials != FROM_ENV:
            raise ValueError(f"credentials {credentials!r}: pass {FROM_ENV!r}, None or bridge.bus_credentials.Credentials")
        credentials = bus_credentials.from_env()
    if isinstance(tls, str):
        if tls != FROM_ENV:
            raise ValueError(f"tls {tls!r}: pass {FROM_ENV!r}, None or bridge.bus_tls.Tls")
        tls = bus_tls.from_env()
    if tls is None and (secure := [e for e in [*listen, *connect] if e.startswith("tls/")]):
        raise ValueError(f"endpoint {secure[0]} needs {bus_tls.ENV_TLS}, a TLS folder (xneck bus tls DIR --host ...)")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "true")
    conf.insert_json5("scouting/gossip/autoconnect",
                      '{router: [], peer: ["router", "peer"]}' if autoconnect else NO_AUTOCONNECT)
    conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect))
    first_ms, cap_ms = CONNECT_RETRY_MS
    conf.insert_json5("connect/retry", json.dumps(
        {"period_init_ms": first_ms, "period_max_ms": cap_ms, "period_increase_factor": 2}))
    # A busy listen port is a configuration error that must not go unnoticed.
    conf.insert_json5("listen/exit_on_failure", "true")
    # The control path's express messages are one batch each, and Zenoh queues 2 batches per
    # priority by default: a sender whose transmit thread is starved for more than ~5 ms (a loaded
    # machine) dropped states that the archive then lacked (issue 21's CI run: 27 states lost,
    # identification refused). 16, Zenoh's maximum, rides out 30 ms at 500 Hz; the latest-value
    # consumers read the newest of a burst, and the allocation stays lazy.
    conf.insert_json5("transport/link/tx/queue/size/real_time", str(REAL_TIME_QUEUE_BATCHES))
    conf.insert_json5("transport/unicast/max_sessions", str(MAX_SESSIONS))
    if credentials is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(credentials.user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(credentials.password))
        conf.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(credentials.path)))
        acl = bus_credentials.viewer_access_control(credentials.viewers)
        if acl is not None:
            conf.insert_json5("access_control", json.dumps(acl))
    if tls is not None:
        conf.insert_json5("transport/link/tls", json.dumps(bus_tls.zenoh_tls(tls)))
    return conf


def open_session(
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    mode: str = "peer",
    credentials: Credentials | str | None = FROM_ENV,
    tls: Tls | str | None = FROM_ENV,
    autoconnect: bool = True,
) -> zenoh.Session:
    """Open a Zenoh session (see :func:`zenoh_config`). Use it as a context manager, or close it:
    an open session with callback subscribers can hang interpreter exit."""
    conf = zenoh_config(listen, connect, mode, credentials, tls, autoconnect)
    _log_access(conf)
    return zenoh.open(conf)


def exposed_endpoints(listen: Sequence[str]) -> list[str]:
    """The endpoints of ``listen`` that other machines can reach (not loopback, not a Unix socket)."""
    out = []
    for e in listen:
        proto, _, address = e.partition("/")
        if proto.startswith("unix"):
            continue
        host = address.rsplit(":", 1)[0].strip("[]").split("#")[0]
        if host not in ("localhost", "::1") and not host.startswith("127."):
            out.append(e)
    return out


def access_summary(listen: Sequence[str], connect: Sequence[str], credentials: Credentials | None,
                   tls: Tls | None = None) -> dict:
    """Who may link to a process that listens on ``listen`` and connects to ``connect`` (for the
    console's health): ``credentials`` in use and the ``user`` presented; ``exposed``, its listen
    endpoints other machines reach; ``remote``, the peers it connects to on other machines; ``open``,
    anyone on the network may link to it or to those peers (no credentials, and an exposed endpoint
    or a remote peer: a peer reached without credentials has none either, links need them on both
    sides; unless every such link is TLS, which admits only the lab's certificate); ``role``, ``viewer`` if the user presented is one (what this process publishes reaches
    no one) else ``operator``; ``viewers``, the users whose publications it drops; ``encrypted``,
    every link other machines may use is TLS (``tls/`` endpoints with a TLS folder, bridge.bus_tls)."""
    remote = exposed_endpoints(connect)
    exposed = exposed_endpoints(listen)
    # mutual TLS admits only holders of the lab's certificate: as closed as credentials are
    encrypted = tls is not None and bool(exposed or remote) and all(e.startswith("tls/") for e in [*exposed, *remote])
    return {"credentials": credentials is not None, "user": None if credentials is None else credentials.user,
            "role": "operator" if credentials is None else credentials.role,
            "viewers": [] if credentials is None else list(credentials.viewers),
            "exposed": exposed, "remote": remote,
            "open": credentials is None and bool(exposed or remote) and not encrypted, "encrypted": encrypted}


_warned_open: set[str] = set()


def _log_access(conf: zenoh.Config) -> None:
    """Say who may link: the credentials and TLS in force, or a warning (once per endpoint and
    process) when a process listens where other machines reach it and anyone may link, or
    unencrypted while it has TLS."""
    listen = json.loads(conf.get_json("listen/endpoints")) or []
    exposed = exposed_endpoints(listen if isinstance(listen, list) else [])
    tls = json.loads(conf.get_json("transport/link/tls"))
    ca = tls.get("root_ca_certificate") if isinstance(tls, dict) else None
    if ca:
        folder = bus_tls.load(Path(ca).parent)
        log.info("bus: tls/ links encrypted, both ends certified by %s (this certificate names %s; %.0f days left)",
                 ca, ", ".join(folder.hosts), folder.days_left())
        if folder.days_left() < bus_tls.WARN_DAYS:
            log.warning("bus: the TLS certificate of %s expires on %s: make a new folder (xneck bus tls) before then",
                        folder.path, folder.not_after.date())
        for e in exposed:
            if not e.startswith("tls/") and f"plain {e}" not in _warned_open:
                _warned_open.add(f"plain {e}")
                log.warning("bus: listening on %s unencrypted although %s is set: other machines should link over "
                            "tls/ (e.g. --listen tls/0.0.0.0:7447)", e, bus_tls.ENV_TLS)
    user = json.loads(conf.get_json("transport/auth/usrpwd/user"))
    if user:
        acl = json.loads(conf.get_json("access_control"))
        viewers = acl["subjects"][0]["usernames"] if acl.get("enabled") else []
        log.info("bus: links only with holders of %s (presenting user %r%s)%s",
                 json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file")), user,
                 ", a viewer: what it publishes reaches no one" if bus_credentials.is_viewer(user) else "",
                 f"; drops what its viewers publish ({', '.join(viewers)})" if viewers else "")
        return
    for e in exposed:
        if e not in _warned_open and not (ca and e.startswith("tls/")):  # mutual TLS admits the lab's certificate only
            _warned_open.add(e)
            log.warning("bus: listening on %s without credentials: anyone on that network can link, subscribe and "
                        "publish (commands, e-stops); set %s (xneck bus credentials FILE; docs/safety.md, "
                        "'Who may link to the bridge')", e, bus_credentials.ENV_CREDENTIALS)


LINKED, NO_LISTENER, REFUSED = "linked", "no listener", "refused"


def probe_link(endpoint: str, seconds: float = 3.0) -> str:
    """Whether this process could link to ``endpoint`` (``tcp/<host>:<port>``) now: :data:`LINKED`,
    :data:`NO_LISTENER` (the TCP connection is refused or times out) or :data:`REFUSED` (a TCP
    listener answers but no Zenoh session opens within ``seconds``: other bus credentials, or not
    a Zenoh peer). For commissioning messages; the credentials are this process's (environment)."""
    proto, _, address = endpoint.partition("/")
    host, _, port = address.rpartition(":")
    if proto in ("tcp", "tls") and port.isdigit():
        try:
            socket.create_connection((host.strip("[]"), int(port)), timeout=min(seconds, 2.0)).close()
        except OSError:
            return NO_LISTENER
    with zenoh.open(zenoh_config(listen=[], connect=[endpoint])) as probe:
        deadline = time.monotonic() + seconds
        while not list(probe.info.peers_zid()):
            if time.monotonic() > deadline:
                return REFUSED
            time.sleep(0.05)
    return LINKED


EPHEMERAL_PORTS_FILE = "/proc/sys/net/ipv4/ip_local_port_range"
LISTEN_PORTS_FROM = 10000  # free ports are drawn from here up to the kernel's ephemeral range
_handed_out: collections.deque[int] = collections.deque(maxlen=256)
_handed_lock = threading.Lock()


def _ephemeral_start() -> int:
    """First port of the range the kernel gives outgoing connections (Linux: 32768)."""
    try:
        with open(EPHEMERAL_PORTS_FILE) as f:
            return int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _bindable(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now, for a listener started next (a hub, viser, a test's
    console); another process may still take it before that listener binds.

    Drawn at random below the kernel's ephemeral range, never twice by one process in its last 256
    calls. Why: a port the kernel hands out for port 0 is one it also gives outgoing connections as
    their local port, and on a busy machine one did, between the pick and the bind (a fresh-clone CI
    run, 2026-11-28: the console of test_console_outcomes exited "address already in use"). Falls
    back to the kernel's choice when that range is too small to draw from."""
    top = _ephemeral_start()
    rng = random.Random()
    if top - LISTEN_PORTS_FROM >= 1000:
        for _ in range(64):
            port = rng.randrange(LISTEN_PORTS_FROM, top)
            with _handed_lock:
                if port in _handed_out:
                    continue
            if _bindable(host, port):
                with _handed_lock:
                    _handed_out.append(port)
                return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def liveliness_token(session: zenoh.Session, kind: str, instance: str) -> zenoh.LivelinessToken:
    """Declare ``xneck/alive/<kind>/<instance>``; it vanishes when undeclared or the session ends."""
    return session.liveliness().declare_token(bus.liveliness_key(kind, instance))


class BusPublisher(Generic[M]):
    """Publisher of one key of the contract; :meth:`put` takes a message of the key's type."""

    def __init__(self, session: zenoh.Session, key: str, msg_type: type[M], block: bool = False) -> None:
        self.key = key
        self.msg_type = msg_type
        real_time = key in REAL_TIME_KEYS
        self._pub = session.declare_publisher(
            key,
            encoding=zenoh.Encoding("application/json"),
            congestion_control=(
                zenoh.CongestionControl.BLOCK if block or key in RELIABLE_KEYS or msg_type is bus.CampaignRequest
                else zenoh.CongestionControl.DROP
            ),
            priority=zenoh.Priority.REAL_TIME if real_time else zenoh.Priority.DATA,
            express=real_time,
        )

    def put(self, msg: M, *, attachment: bytes | None = None) -> None:
        """Encode and publish (``attachment``: Zenoh's, e.g. :data:`REPLAYED`). Raises
        ``TypeError`` for a message of another type and :class:`bus.BusEncodeError` for a
        non-finite float."""
        if type(msg) is not self.msg_type:
            raise TypeError(f"{self.key} carries {self.msg_type.__name__}, not {type(msg).__name__}")
        if attachment is None:
            self._pub.put(bus.encode(msg))
        else:
            self._pub.put(bus.encode(msg), attachment=attachment)

    def put_bytes(self, data: bytes) -> None:
        """Publish a payload already made by :func:`bus.encode` from a message of this key's type
        (a sender that times or reuses its encoding)."""
        self._pub.put(data)

    def close(self) -> None:
        self._pub.undeclare()

    def __enter__(self) -> BusPublisher[M]:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def publisher(session: zenoh.Session, key: str, *, block: bool = False) -> BusPublisher[bus.BusMessage]:
    """Typed publisher on ``key`` (a concrete key of the contract). ``block``: under congestion
    wait rather than drop, whatever the key. For lockstep runs, whose pace the slowest process
    sets anyway: there a dropped state or command is a hole in the campaign's record (a loaded
    machine lost 16 % of a campaign's messages), while on the real-time path a late message is
    worse than none."""
    msg_type = bus.message_type(key)
    if msg_type is None:
        raise ValueError(f"{key!r} is not a key of the bus contract")
    return BusPublisher(session, key, msg_type, block)


def payload_of(sample: zenoh.Sample, msg_type: type[bus.BusMessage]) -> bytes:
    """The bytes of ``sample``, a message of ``msg_type``; :class:`bus.BusDecodeError` if the payload
    is larger than the contract allows for it, found before it is copied (a huge payload must not
    hold a callback)."""
    bus.check_payload_size(msg_type, len(sample.payload))
    return sample.payload.to_bytes()


@dataclass(frozen=True)
class ReceiveStats:
    """Counters of one subscriber. ``rejected`` payloads failed decoding or the receiver's check."""

    received: int = 0
    accepted: int = 0
    rejected: int = 0
    last_reject_reason: str = ""


class LatestSubscriber(Generic[M]):
    """Keeps the latest valid message of one key and counts the rejected ones.

    The Zenoh callback only decodes, validates and stores under a lock (no blocking call, no Zenoh
    call). ``validate`` is the receiver's own check (e.g. :func:`bus.check_force_command`); it
    must raise :class:`bus.BusDecodeError` to reject. Rejections are logged, at most once per
    second per subscriber, and counted.
    """

    LOG_PERIOD_S = 1.0

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        msg_type: type[M],
        validate: Callable[[M], None] | None = None,
        on_message: Callable[[M, int], None] | None = None,
        direct: bool = False,
    ) -> None:
        self.key = key
        self.msg_type = msg_type
        self._validate = validate
        self._on_message = on_message
        self._cond = threading.Condition()
        self._latest: M | None = None
        # (message, receive time) replaced whole, so a reader needs no lock: a real-time loop
        # reads it every tick, and a lock it shares with Zenoh's thread can make it wait.
        self._latest_pair: tuple[M | None, int] = (None, 0)
        self._received = self._accepted = self._rejected = 0
        self._last_reason = ""
        self._last_log_s = -float("inf")
        self._unlogged = 0
        # direct: the callback runs on Zenoh's network thread itself, not on a Python thread fed by
        # a FIFO: one thread hand-over less between a sample's arrival and what reacts to it.
        handler = zenoh.handlers.Callback(self._on_sample, indirect=False) if direct else self._on_sample
        self._sub = session.declare_subscriber(key, handler)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        now_ns = time.time_ns()  # wall clock: compared with the sender's stamps (``on_message``)
        # monotonic: which message is newer and how old it is must survive a step of the wall clock
        mono_ns = time.monotonic_ns()
        try:
            msg = bus.decode(self.msg_type, payload_of(sample, self.msg_type))
            if self._validate is not None:
                self._validate(msg)
        except bus.BusDecodeError as exc:
            self._reject(f"{sample.key_expr}: {exc.reason}")
            return
        except Exception as exc:  # noqa: BLE001 - a faulty validator must not kill the callback
            self._reject(f"{sample.key_expr}: validator failed ({type(exc).__name__}: {exc})")
            return
        with self._cond:
            self._received += 1
            self._accepted += 1
            self._latest = msg
            self._latest_pair = (msg, mono_ns)
            self._cond.notify_all()
        if self._on_message is not None:
            self._on_message(msg, now_ns)

    def _reject(self, reason: str) -> None:
        with self._cond:
            self._received += 1
            self._rejected += 1
            self._last_reason = reason
            now = time.monotonic()
            if now - self._last_log_s < self.LOG_PERIOD_S:
                self._unlogged += 1
                return
            skipped, self._unlogged, self._last_log_s = self._unlogged, 0, now
        suffix = f" (+{skipped} more since the last report)" if skipped else ""
        log.warning("rejected %s%s", reason, suffix)

    def latest(self) -> M | None:
        """The latest valid message, or None if none arrived yet."""
        with self._cond:
            return self._latest

    def latest_with_time(self) -> tuple[M | None, int]:
        """The latest valid message and its receive time (``time.monotonic_ns()``, so that a step
        of the wall clock neither makes a new message look old nor an old one new; 0 if none).
        Lock-free (one attribute read): safe from a real-time loop."""
        return self._latest_pair

    def wait(self, timeout_s: float, predicate: Callable[[M], bool] | None = None) -> M | None:
        """Block (never from a Zenoh callback) until a valid message arrives after this call, or one
        satisfying ``predicate`` is the latest; None on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            start = self._accepted
            while True:
                if self._latest is not None and (
                    predicate(self._latest) if predicate is not None else self._accepted > start
                ):
                    return self._latest
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)

    @property
    def stats(self) -> ReceiveStats:
        with self._cond:
            return ReceiveStats(self._received, self._accepted, self._rejected, self._last_reason)

    def close(self) -> None:
        self._sub.undeclare()

    def __enter__(self) -> LatestSubscriber[M]:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def subscribe_latest(
    session: zenoh.Session,
    key: str,
    msg_type: type[M] | None = None,
    validate: Callable[[M], None] | None = None,
    on_message: Callable[[M, int], None] | None = None,
    direct: bool = False,
) -> LatestSubscriber[M]:
    """Subscribe to ``key`` keeping the latest valid message; ``msg_type`` defaults to the
    registry's type for ``key`` (required for wildcard keys). ``on_message(msg, arrival_ns)``
    reacts to each valid message in the callback (it must be short and must not raise);
    ``direct`` runs it on Zenoh's network thread (see :class:`LatestSubscriber`)."""
    if msg_type is None:
        msg_type = bus.message_type(key)  # type: ignore[assignment]
        if msg_type is None:
            raise ValueError(f"{key!r} is not a key of the bus contract: pass msg_type")
    return LatestSubscriber(session, key, msg_type, validate, on_message, direct)  # type: ignore[arg-type]


__all__ = [
    "CAMERA", "CONTROLLER", "DEFAULT_LISTEN", "ENV_CONNECT", "ENV_LISTEN", "ENV_ZENOH_RUNTIME", "ESTOP_HOLDER",
    "REAL_TIME_KEYS", "RELIABLE_KEYS", "REPLAYED", "RUN", "RUN_PREFIX", "ZENOH_RX_WORKERS", "BusPublisher",
    "LatestSubscriber", "ReceiveStats", "SenderAttachment", "camera_attachment", "camera_of", "controller_attachment",
    "controller_of", "estop_holder_attachment", "estop_holder_of", "free_tcp_port", "liveliness_token", "open_session",
    "payload_of", "publisher", "replayed", "run_attachment", "run_of", "subscribe_latest", "zenoh_config",
    "zenoh_runtime_environment",
]
