"""The bus contract: every key expression and message schema of the xneck Zenoh bus.

Every process (bridge, controller, twin, server, recorder) imports this one module, so a message
changes in exactly one place. The module depends on msgspec only (no zenoh), so offline tools that
read MCAP archives use the same types.

Wire format
    JSON (``msgspec.json``), one message per Zenoh sample. The same bytes are written to MCAP with
    ``message_encoding="json"`` and a JSON Schema (:func:`json_schema`) that Foxglove can read.

Units and frames
    SI units, spelled in field names (``_rad``, ``_rad_s``, ``_N``, ``_m``, ``_s``). Per-motor and
    per-cable lists are in motor index order, the order of the robot's parameter file. Joint angles
    ``alpha`` are the X-joint angles, base to head. ``stamp_s`` is the sender's clock in seconds:
    wall time (``time.time()``) for hardware processes, simulated time for the twin. A camera on
    another machine than the bridge stamps on the bridge's clock, which the bridge serves on the
    queryable :data:`BRIDGE_CLOCK` (:class:`ClockReading`).

Version rule
    Every message carries ``v``, its schema version; the current one is the default of the ``v``
    field of its type (:func:`schema_version`). Any change to a message's fields (added, removed,
    renamed, retyped, or a changed unit or meaning) bumps that message's version. Receivers accept
    exactly the version they were built with and reject every other one with a
    :class:`BusDecodeError` naming both versions; there is no negotiation, since all processes ship
    from one repository: the version catches mixed deployments and old archives. ``v`` is required
    on the wire even though it has a default in Python.

Validation
    :func:`decode` checks structure only: JSON syntax, version, field names and types, required
    fields, and that every float is finite (JSON has no NaN/inf; ``msgspec`` rejects ``NaN`` tokens,
    ``null`` for a float and overflowing literals such as ``1e999``). Range checks that need the
    robot's parameters (list lengths, force limits) belong to the receiver; :func:`check_force_command`
    is the shared one for commands. Checks between fields that an archive already recorded may
    fail (a camera's capture after its publication: :func:`check_camera_alpha_stamps`) are not in
    :func:`decode` either, so that such an archive still reads. All raise only :class:`BusDecodeError`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from typing import Annotated, Any, Literal, TypeVar

import msgspec

from bridge.imageheader import ImageFileError, image_size

PREFIX = "xneck"

# Key expressions (Zenoh: no leading slash; MCAP topics are "/" + key).
MOTOR_STATE = f"{PREFIX}/motor/state"
MOTOR_COMMAND = f"{PREFIX}/motor/command"
CAMERA_ALPHA = f"{PREFIX}/camera/alpha_ip"
CAMERA_FRAME = f"{PREFIX}/camera/frame"
TWIN_TRUTH = f"{PREFIX}/twin/truth"
CONTROLLER_STATUS = f"{PREFIX}/controller/status"
CONTROLLER_TIMING = f"{PREFIX}/controller/timing"
CAMPAIGN_EVENTS = f"{PREFIX}/campaign/events"
CAMPAIGN_REQUEST = f"{PREFIX}/campaign/request"
#: Requests addressed to one controller service: ``xneck/campaign/request/<instance>``
#: (:func:`campaign_request_key`). The console addresses every request: with two services on the
#: bus, both took a bare request, and the one the bridge does not obey aborted the console's
#: campaign (audit of 2026-11-28).
CAMPAIGN_REQUEST_TO = f"{PREFIX}/campaign/request/*"
ESTOP = f"{PREFIX}/estop"
#: Liveliness tokens of an engaged e-stop, ``xneck/estop/engaged/<holder>`` (:func:`estop_token_key`):
#: whoever engages the e-stop (the console) declares one before it publishes the ``EStop`` and
#: keeps it until it releases. An ``EStop`` reaches only the bridges linked when it is sent, and
#: the bridge's latch lived in its memory: a bridge restarted (or started) under an engaged e-stop
#: came up ``inactive`` and a running controller enabled it (audit of the e-stop, S3). A bridge
#: starts latched while any such token is alive, and releases only when none is (docs/safety.md).
ESTOP_ENGAGED_ALL = f"{PREFIX}/estop/engaged/*"
#: The bridge's stamp clock, a Zenoh *queryable* the bridge serves (``session.get`` it; nothing is
#: published there): each reply is one :class:`ClockReading`. A camera on another machine's clock
#: measures its offset from it (:mod:`bridge.clock_sync`, docs/camera.md, "One clock").
BRIDGE_CLOCK = f"{PREFIX}/bridge/clock"
HEALTH_ALL = f"{PREFIX}/health/*/*"
ALIVE_ALL = f"{PREFIX}/alive/**"
ALL = f"{PREFIX}/**"

DriveState = Literal["disabled", "inactive", "active", "hold"]
CampaignEventKind = Literal["started", "progress", "finished", "aborted", "interrupted"]


class BusDecodeError(Exception):
    """A payload was rejected; ``reason`` is a human-readable sentence fit for a log or a counter."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class BusEncodeError(ValueError):
    """A message cannot be put on the bus (non-finite float, unregistered type): a sender bug."""


class BusMessage(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Fields every message carries.

    ``seq`` counts messages of one publisher (starts anywhere, +1 per message; gaps mean loss).
    ``stamp_s`` is the sender's time of the data in seconds (simulated time for the twin).
    Lists are not copied: treat a received message as read-only.
    """

    v: int = 1
    seq: int
    stamp_s: float


class MotorState(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Motor shaft angles and applied cable forces, published by the bridge (or the twin) at 500 Hz.

    ``force_applied_N`` is what the drives actually apply, after the bridge's clamping to
    [f_min, f_max], bumpless ramp and hold logic. ``hold_reason`` is empty unless ``drive == "hold"``,
    or, in a stopping bridge's last state (``drive == "disabled"``), says why it stopped, or, with
    ``drive`` ``"inactive"`` or ``"hold"``, says that it refused commands as answering no recent
    state within the last second (a link whose round trip is too long: nothing else said why).

    Identity (v2): ``epoch`` is a random id of this bridge run, new at every start (a command
    answers a state by echoing it; a restarted bridge is recognised at once); ``bridge`` is the
    bridge's instance name; ``owner`` the controller instance whose commands it accepts ("" if
    none). The e-stop (v2): ``estop_engaged`` is the bridge's latched e-stop, the one truth every
    other process shows, and ``estop_reason`` why (e.g. "malformed e-stop message: ...").
    """

    v: int = 2
    theta_rad: list[float]
    force_applied_N: list[float]
    drive: DriveState
    hold_reason: str = ""
    epoch: str
    bridge: str
    owner: str = ""
    estop_engaged: bool = False
    estop_reason: str = ""


class ForceCommand(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Cable force set-points [N], controller to bridge, one per motor. ``source`` names the law
    (for logs) so a rejected or clamped command can be traced.

    Identity (v2): ``sender`` is the sending controller's instance, whose liveliness token
    ``liveliness_key("controller", sender)`` must be alive; the bridge obeys one owner at a time.
    ``epoch`` is the bridge epoch of the ``MotorState`` the command answers and ``stamp_s`` that
    state's ``stamp_s`` (one clock on the command key): a command for another bridge run is refused.
    """

    v: int = 2
    force_N: list[float]
    source: str
    sender: str
    epoch: str


class CameraAlpha(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """X-joint angles measured by the camera (image processing, about 30 Hz).

    ``capture_stamp_s`` is the middle of the exposure, ``stamp_s`` the publication time, both on the
    bus clock: the twin's simulated time, the bridge's stamp clock for a USB camera (measured over
    :data:`BRIDGE_CLOCK`; ``xneck camera --clock local``: the PC's wall clock), video time for a file.
    v2: ``alpha_ip_rad[i]`` is null for a joint the camera did not measure (a hidden marker, an
    outlier): missing, never guessed. ``confidence[i]`` in [0, 1] grades each joint (0 when
    missing); empty when the publisher does not grade (the twin's white-noise camera).
    ``source`` names the frames (``twin-noise``, ``twin-render``, ``usb:0``, ``file:run.mp4``) and
    ``dropped`` counts the frames the source lost since it started. See
    :func:`check_camera_alpha` for the receiver's range check, and :func:`check_camera_alpha_stamps`
    for its time check (the capture not after the publication), which the archive's recorder applies.
    """

    v: int = 2
    alpha_ip_rad: list[float | None]
    capture_stamp_s: float
    confidence: list[float] = []
    source: str = ""
    dropped: int = 0


#: Bounds of a camera frame, checked when it is decoded: a frame is large, and untrusted input.
FRAME_DATA_MAX_BYTES = 1024 * 1024  # a 1280×720 JPEG at quality 75 is 100-300 kB, noise included
FRAME_MAX_SIDE_PX = 8192
FRAME_MAX_MARKERS = 64


class CameraFrame(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """A camera frame (JPEG) and the markers the detector found on it, decimated to a few Hz
    (``xneck camera --frame-rate-hz``), for the console's camera panel and the campaign archive
    (which stores it as ``foxglove.CompressedImage`` on ``/xneck/camera/image``).

    ``stamp_s`` is the publication time and ``capture_stamp_s`` the middle of the exposure, on
    the bus clock as in :class:`CameraAlpha` (whose message of the same exposure has the same
    ``capture_stamp_s``). ``frame_id`` names the camera's frame of reference, ``format`` the
    encoding of ``data`` (base64 in JSON), ``width``/``height`` its size in pixels.
    ``marker_bar[k]`` is the bar of the k-th marker centroid (0 the base bar … n the head bar,
    −1 a base-plate reference marker), at pixel (``markers_px[2k]``, ``markers_px[2k+1]``).
    Sizes are bounded when decoded; :func:`check_camera_frame` is the receiver's content check.
    """

    v: int = 1
    capture_stamp_s: float
    frame_id: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")] = "camera"
    format: Literal["jpeg"] = "jpeg"
    width: Annotated[int, msgspec.Meta(ge=1, le=FRAME_MAX_SIDE_PX)]
    height: Annotated[int, msgspec.Meta(ge=1, le=FRAME_MAX_SIDE_PX)]
    data: Annotated[bytes, msgspec.Meta(min_length=4, max_length=FRAME_DATA_MAX_BYTES)]
    marker_bar: Annotated[list[Annotated[int, msgspec.Meta(ge=-1, le=FRAME_MAX_MARKERS)]],
                          msgspec.Meta(max_length=FRAME_MAX_MARKERS)] = []
    markers_px: Annotated[list[float], msgspec.Meta(max_length=2 * FRAME_MAX_MARKERS)] = []
    source: Annotated[str, msgspec.Meta(max_length=256)] = ""


class Truth(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Ground truth of the twin (never published by hardware); ``stamp_s`` is simulated time.

    Per joint: ``alpha_rad``, ``alpha_dot_rad_s``. Per motor: ``theta_rad``, ``theta_dot_rad_s``.
    Per cable: ``tension_N``, ``elongation_m``, ``slack`` (cable tension at zero).
    ``near_singular`` flags a configuration close to a singular one of the mechanism.

    Whose truth: not a field. The bridge that runs the twin names its run (``MotorState.epoch``)
    in the Zenoh attachment (``bridge.session.RUN_PREFIX``, why there), and a campaign archive
    holds only the truth of the run whose states it follows. ``truth``: which truth the twin
    simulates (twin.sim.truth: ``model``, ``robot`` or a truth file's ``name``; empty in archives
    before 2026-12-01), so that a campaign's record says what was observed, not only what its
    console was told (truth audit of 2026-12-01).
    """

    v: int = 1
    alpha_rad: list[float]
    alpha_dot_rad_s: list[float]
    theta_rad: list[float]
    theta_dot_rad_s: list[float]
    tension_N: list[float]
    elongation_m: list[float]
    slack: list[bool]
    near_singular: bool
    truth: str = ""


class ControllerStatus(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """What the controller did for one motor state (every state it took, holds included).

    ``tick_s`` is the loop period actually measured, ``compute_s`` the time spent in the law.
    ``overruns`` counts ticks whose compute exceeded the period, ``deadline_misses`` ticks whose
    command left late, ``ticks`` the states answered: all three since ``campaign_id`` started
    (since the previous campaign ended when ``campaign_id`` is empty), never since the process
    started (v2). ``saturated`` flags each motor whose force was clipped. ``alpha_hat_rad``
    (estimate), ``alpha_d_rad`` (desired) and ``e_rad`` (error) are per joint. ``holding``: the
    command is the hold forces, ``hold_reason`` says why (drives disabled, stale states...).
    """

    v: int = 2
    law: str
    tick_s: float
    compute_s: float
    overruns: int
    deadline_misses: int
    saturated: list[bool]
    alpha_hat_rad: list[float]
    alpha_d_rad: list[float]
    e_rad: list[float]
    holding: bool
    hold_reason: str = ""
    campaign_id: str = ""
    ticks: int = 0


class ControllerTiming(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Where the controller's ticks spent their time, about once a second (issue 21).

    The window since the last message: ``window_ticks`` ticks, the state-to-command latency (from
    the state's arrival at the controller's subscriber to its command handed to Zenoh) and the
    tick period (between two states' arrivals) as p50/p99/max in ms, the same per stage
    (``decode``, ``law``, ``encode``, ``put``), and histograms over the bins ``bin_edges_ms``
    (``len(bin_edges_ms) − 1`` counts; the last bin takes everything above). ``campaign_*``: the
    campaign ``campaign_id`` so far ("" between campaigns: since the service started or the last
    campaign ended), its counts as in :class:`ControllerStatus` and its histograms; the campaign
    quantiles are upper bin edges. ``window_skipped``: stale states of a burst (after the
    controller was held up) it did not answer, in the window.
    """

    v: int = 1
    campaign_id: str = ""
    window_ticks: int
    window_skipped: int = 0
    latency_p50_ms: float
    latency_p99_ms: float
    latency_max_ms: float
    period_p50_ms: float
    period_p99_ms: float
    stage_p50_ms: dict[str, float]
    stage_p99_ms: dict[str, float]
    bin_edges_ms: list[float]
    latency_counts: list[int]
    period_counts: list[int]
    campaign_ticks: int
    campaign_deadline_misses: int
    campaign_overruns: int
    campaign_latency_counts: list[int]
    campaign_period_counts: list[int]
    campaign_latency_p50_ms: float
    campaign_latency_p99_ms: float


class CampaignEvent(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Life cycle of a campaign (identification run, tracking experiment...).

    ``kind`` is the campaign kind, ``event`` the transition, ``progress`` in [0, 1]. ``ticks``,
    ``overruns`` and ``deadline_misses`` are the controller's counts for this campaign so far (v2;
    see :class:`ControllerStatus`), so that a console can judge the real-time quality of a run.
    """

    v: int = 2
    campaign_id: str
    kind: str
    event: CampaignEventKind
    progress: float = 0.0
    message: str = ""
    ticks: int = 0
    overruns: int = 0
    deadline_misses: int = 0


#: Bounds of a campaign request, checked when it is decoded (v2): a request is untrusted input.
CAMPAIGN_ID_PATTERN = r"^[A-Za-z0-9_.\-]{1,128}$"
TRAJECTORY_JSON_MAX_BYTES = 256 * 1024
PARAMETERS_TOML_MAX_BYTES = 64 * 1024
CampaignKind = Literal["control", "identification", "jog"]


class CampaignRequest(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Console to a controller service (``xneck controller`` without ``--trajectory``): start a
    campaign with ``law`` (1-3), ``no_pulleys``, a trajectory (``trajectory_json``, the
    ``Trajectory.to_json()`` form, degrees) and the campaign's parameter set, or stop the one running. The controller answers with
    ``CampaignEvent``s of the same ``campaign_id`` (``aborted`` with the reason if it refuses).

    v2: the id, kind and law are checked when decoded, and the two texts are bounded in size.
    ``trajectory_json`` is JSON text, never a path: the controller opens no file named on the bus.

    v3: kind ``jog`` (the console's ``POST /api/jog``): a move to one pose, not archived; a jog
    asked for while a jog runs waits for it to end (the newest one only), so the console's sliders
    chain gentle moves without a force step, and ``settle_s`` is short.
    """

    v: int = 3
    campaign_id: Annotated[str, msgspec.Meta(pattern=CAMPAIGN_ID_PATTERN)]
    action: Literal["start", "stop"]
    kind: CampaignKind = "control"
    law: Literal[1, 2, 3] = 2
    no_pulleys: bool = False
    trajectory_json: Annotated[str, msgspec.Meta(max_length=TRAJECTORY_JSON_MAX_BYTES)] = ""
    # the campaign's parameter set (Params.to_toml()); empty: the controller's own
    parameters_toml: Annotated[str, msgspec.Meta(max_length=PARAMETERS_TOML_MAX_BYTES)] = ""


class EStop(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Emergency stop: while ``engaged``, the bridge holds and ignores force commands."""

    v: int = 1
    engaged: bool
    reason: str


class Health(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Counters of a process, at about 1 Hz on ``xneck/health/<kind>/<instance>``.

    ``rejected`` maps a key expression to the number of payloads refused on it since start,
    ``last_reject_reason`` is the most recent reason (empty if none).
    """

    v: int = 1
    process: str
    instance: str
    uptime_s: float
    received: dict[str, int]
    rejected: dict[str, int]
    last_reject_reason: str = ""


#: A bridge's instance name or epoch in a :class:`ClockReading`: what ``--instance`` accepts, bounded
#: (a reply is untrusted: the querier names the run it synchronised with in its log and health).
CLOCK_NAME_PATTERN = r"^[A-Za-z0-9_.\-]{1,64}$"


class ClockReading(BusMessage, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """One reply of the bridge's clock queryable (:data:`BRIDGE_CLOCK`).

    ``stamp_s`` is the bridge's stamp clock when it replied: the clock of its ``MotorState.stamp_s``
    (the driver's ``stamp_s()``: the board's wall clock in s for hardware, the simulated time of
    the last tick for the twin). ``seq`` counts this bridge run's replies. ``epoch`` and
    ``bridge`` are those of its ``MotorState`` (the run and the instance name), so the querier
    knows which run it synchronised with and sees a restart. Not archived (a query's reply reaches
    only the querier).
    """

    v: int = 1
    epoch: Annotated[str, msgspec.Meta(pattern=CLOCK_NAME_PATTERN)]
    bridge: Annotated[str, msgspec.Meta(pattern=CLOCK_NAME_PATTERN)]


M = TypeVar("M", bound=BusMessage)

#: Key expression -> message type, for every fixed key.
REGISTRY: dict[str, type[BusMessage]] = {
    MOTOR_STATE: MotorState,
    MOTOR_COMMAND: ForceCommand,
    CAMERA_ALPHA: CameraAlpha,
    CAMERA_FRAME: CameraFrame,
    TWIN_TRUTH: Truth,
    CONTROLLER_STATUS: ControllerStatus,
    CONTROLLER_TIMING: ControllerTiming,
    CAMPAIGN_EVENTS: CampaignEvent,
    CAMPAIGN_REQUEST: CampaignRequest,
    ESTOP: EStop,
    BRIDGE_CLOCK: ClockReading,
}

#: Key patterns (``*`` = one chunk) -> message type, for keys that carry a process name.
PATTERNS: dict[str, type[BusMessage]] = {HEALTH_ALL: Health, CAMPAIGN_REQUEST_TO: CampaignRequest}

MESSAGE_TYPES: tuple[type[BusMessage], ...] = tuple(dict.fromkeys((*REGISTRY.values(), *PATTERNS.values())))

#: The largest payload (bytes) a receiver decodes, by message type (others: ``PAYLOAD_MAX_BYTES``).
#: Checked before a payload is copied out of Zenoh or parsed: a 20 MB ``ForceCommand`` held the
#: bridge's callback (and the GIL) for 134 ms and delayed an e-stop by 175 ms (audit of
#: 2026-11-26). The real-time messages are a few hundred bytes; a frame is base64 in JSON; a
#: request carries a trajectory and a parameter set.
PAYLOAD_MAX_BYTES = 64 * 1024
REAL_TIME_PAYLOAD_MAX_BYTES = 8 * 1024
PAYLOAD_MAX_BYTES_BY_TYPE: dict[type[BusMessage], int] = {
    MotorState: REAL_TIME_PAYLOAD_MAX_BYTES,
    ForceCommand: REAL_TIME_PAYLOAD_MAX_BYTES,
    EStop: REAL_TIME_PAYLOAD_MAX_BYTES,
    ClockReading: 1024,  # at most 218 bytes (every field at its bound): a larger reply is not a bridge's
    CameraFrame: 4 * (FRAME_DATA_MAX_BYTES // 3 + 1) + PAYLOAD_MAX_BYTES,
    CampaignRequest: TRAJECTORY_JSON_MAX_BYTES + PARAMETERS_TOML_MAX_BYTES + 4096,
}


def max_payload_bytes(msg_type: type[BusMessage]) -> int:
    """The largest payload (bytes) of ``msg_type`` a receiver decodes."""
    return PAYLOAD_MAX_BYTES_BY_TYPE.get(msg_type, PAYLOAD_MAX_BYTES)


def check_payload_size(msg_type: type[BusMessage], n_bytes: int) -> None:
    """Raise :class:`BusDecodeError` if a payload of ``n_bytes`` is too large for ``msg_type``
    (call it before copying the payload out of Zenoh)."""
    limit = max_payload_bytes(msg_type)
    if n_bytes > limit:
        raise BusDecodeError(f"{msg_type.__name__}: payload of {n_bytes} bytes, more than {limit}")

# A chunk of a process kind or instance name: safe in a key expression and in a file name.
_NAME = re.compile(r"^[A-Za-z0-9_.\-]+$")


#: Characters shown as a space besides the controls (Unicode Cc): the bidi controls (U+202E
#: reversed the rest of a log line: review of session 42), the invisible ones that make two names
#: look alike (zero-width space, word joiner, BOM) and the line and paragraph separators (a log
#: viewer's new line). The zero-width joiners, soft hyphen and tags of emoji and scripts stay.
_NOT_PLAIN = re.compile("[\x00-\x1f\x7f-\x9f\u061c\u200b\u200e\u200f\u2028-\u202e\u2060-\u2064"
                        "\u2066-\u2069\ufeff]")


def plain_text(text: str, n: int = 200) -> str:
    """A reason or name as it may be logged, shown and encoded: what does not encode as UTF-8 (a
    Latin-1 terminal's bytes, which Python keeps as lone surrogates) becomes "?", each control,
    bidi, invisible or line-separator character a space (:data:`_NOT_PLAIN`: a newline forged a
    log line, an escape sequence drove the terminal, review of session 41; a bidi override
    reversed the log line, session 42), cut to ``n`` characters ("..." at the end when cut)."""
    text = _NOT_PLAIN.sub(" ", text[: n + 1].encode("utf-8", "replace").decode("utf-8"))  # one for one
    return text if len(text) <= n else text[: n - 3] + "..."


def _check_name(what: str, name: str) -> str:
    if not isinstance(name, str) or not _NAME.fullmatch(name):
        raise ValueError(f"{what} {name!r} must be non-empty and use only letters, digits, '_', '.', '-'")
    return name


def liveliness_key(kind: str, instance: str) -> str:
    """Key of the liveliness token of one process: ``xneck/alive/<kind>/<instance>``."""
    return f"{PREFIX}/alive/{_check_name('process kind', kind)}/{_check_name('instance', instance)}"


def parse_liveliness_key(key: str) -> tuple[str, str]:
    """``(kind, instance)`` of a liveliness key; ``ValueError`` if ``key`` is not one."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != PREFIX or parts[1] != "alive":
        raise ValueError(f"{key!r} is not a liveliness key ({PREFIX}/alive/<kind>/<instance>)")
    return parts[2], parts[3]


def estop_token_key(holder: str) -> str:
    """Key of the liveliness token ``holder`` keeps while it holds the e-stop engaged:
    ``xneck/estop/engaged/<holder>`` (:data:`ESTOP_ENGAGED_ALL`)."""
    return f"{ESTOP_ENGAGED_ALL[:-2]}/{_check_name('e-stop holder', holder)}"


def parse_estop_token_key(key: str) -> str:
    """The holder named by an e-stop token's key; ``ValueError`` if ``key`` is not one."""
    parts = str(key).split("/")
    if len(parts) != 4 or "/".join(parts[:3]) != ESTOP_ENGAGED_ALL[:-2] or not _NAME.fullmatch(parts[3]):
        raise ValueError(f"{key!r} is not an e-stop token key ({ESTOP_ENGAGED_ALL})")
    return parts[3]


def campaign_request_key(instance: str) -> str:
    """Key of the campaign requests addressed to the controller service ``instance``:
    ``xneck/campaign/request/<instance>`` (a service takes these and the bare
    :data:`CAMPAIGN_REQUEST`; its peers never see them)."""
    return f"{CAMPAIGN_REQUEST}/{_check_name('instance', instance)}"


def health_key(kind: str, instance: str) -> str:
    """Key of the health counters of one process: ``xneck/health/<kind>/<instance>``."""
    return f"{PREFIX}/health/{_check_name('process kind', kind)}/{_check_name('instance', instance)}"


def _matches(pattern: str, key: str) -> bool:
    p, k = pattern.split("/"), key.split("/")
    return len(p) == len(k) and all(a == "*" or a == b for a, b in zip(p, k))


def message_type(key: str) -> type[BusMessage] | None:
    """The message type published on ``key`` (a concrete key, not a wildcard), or None."""
    key = str(key)
    found = REGISTRY.get(key)
    if found is not None:
        return found
    for pattern, msg_type in PATTERNS.items():
        if _matches(pattern, key):
            return msg_type
    return None


def schema_version(msg_type: type[BusMessage]) -> int:
    """Current schema version of ``msg_type``: the default of its ``v`` field."""
    for field in msgspec.structs.fields(msg_type):
        if field.name == "v":
            return int(field.default)
    raise TypeError(f"{msg_type.__name__} has no schema version field 'v'")


_VERSIONS: dict[type, int] = {t: schema_version(t) for t in MESSAGE_TYPES}


def schema_name(msg_type: type[BusMessage]) -> str:
    """Name of the MCAP schema of ``msg_type``, e.g. ``xneck.MotorState``."""
    return f"{PREFIX}.{msg_type.__name__}"


def mcap_topic(key: str) -> str:
    """MCAP/Foxglove topic of a key expression: ``"/" + key``."""
    key = str(key)
    return key if key.startswith("/") else "/" + key


def key_of_topic(topic: str) -> str:
    """Inverse of :func:`mcap_topic`."""
    return topic[1:] if topic.startswith("/") else topic


# --- encoding ---------------------------------------------------------------------------------



def _enc_hook(obj: Any) -> Any:
    # numpy scalars (np.float64 subclasses float but msgspec wants exact builtins)
    item = getattr(obj, "item", None)
    if callable(item) and type(obj).__module__ == "numpy":
        return item()
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


_encoder = msgspec.json.Encoder(enc_hook=_enc_hook)


def _non_finite_field(msg: BusMessage) -> str | None:
    for name in msg.__struct_fields__:
        value = getattr(msg, name)
        if isinstance(value, float):
            if not math.isfinite(value):
                return f"{name} = {value}"
        elif isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                if isinstance(item, float) and not math.isfinite(item):
                    return f"{name}[{i}] = {item}"
    return None


def encode(msg: BusMessage) -> bytes:
    """JSON bytes of ``msg``. Raises :class:`BusEncodeError` on a NaN or infinite float (msgspec
    would silently write ``null``, which every receiver rejects) or on an unregistered type."""
    if type(msg) not in _VERSIONS:
        raise BusEncodeError(f"{type(msg).__name__} is not a registered bus message type")
    data = _encoder.encode(msg)
    # msgspec writes every NaN or infinity as null: without a null the fields need no look (their
    # walk costs more than the encoding, and the bridge encodes 500 states a second: issue 20).
    bad = _non_finite_field(msg) if b"null" in data else None
    if bad is not None:
        raise BusEncodeError(f"{type(msg).__name__}: non-finite float {bad}")
    return data


# --- decoding ---------------------------------------------------------------------------------


class _Envelope(msgspec.Struct):
    """Just the version, read first so that a message of another version is reported as such
    rather than as an unknown or missing field."""

    v: int


_envelope_decoder = msgspec.json.Decoder(_Envelope)
_decoders: dict[type, msgspec.json.Decoder] = {t: msgspec.json.Decoder(t) for t in MESSAGE_TYPES}


def decode(type_or_key: type[M] | str, payload: bytes | bytearray | memoryview) -> M:
    """Decode and validate one payload.

    ``type_or_key`` is a message type or a key expression of the registry. Raises only
    :class:`BusDecodeError`, whose reason names the type and the problem (bad JSON, missing ``v``,
    wrong version, wrong type, missing or unknown field, non-finite float, unknown key).
    """
    if isinstance(type_or_key, str):
        msg_type = message_type(type_or_key)
        if msg_type is None:
            raise BusDecodeError(f"no message type is registered for key {type_or_key!r}")
    else:
        msg_type = type_or_key
    decoder = _decoders.get(msg_type)  # type: ignore[arg-type]
    if decoder is None:
        raise BusDecodeError(f"{getattr(msg_type, '__name__', msg_type)!r} is not a bus message type")
    name = msg_type.__name__
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise BusDecodeError(f"{name}: payload must be bytes, got {type(payload).__name__}")
    check_payload_size(msg_type, len(payload))
    try:
        version = _envelope_decoder.decode(payload).v
    except msgspec.ValidationError as exc:
        raise BusDecodeError(f"{name}: no valid schema version 'v' ({exc})") from None
    except msgspec.DecodeError as exc:
        raise BusDecodeError(f"{name}: malformed JSON ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - the contract: nothing but BusDecodeError escapes
        raise BusDecodeError(f"{name}: undecodable payload ({type(exc).__name__}: {exc})") from None
    expected = _VERSIONS[msg_type]
    if version != expected:
        raise BusDecodeError(f"{name}: schema version {version} is not supported (expected {expected})")
    try:
        return decoder.decode(payload)  # type: ignore[return-value]
    except msgspec.DecodeError as exc:
        raise BusDecodeError(f"{name}: {exc}") from None
    except Exception as exc:  # noqa: BLE001 - the contract: nothing but BusDecodeError escapes
        raise BusDecodeError(f"{name}: undecodable payload ({type(exc).__name__}: {exc})") from None


def check_force_command(cmd: ForceCommand, n_motors: int, f_min_N: float, f_max_N: float) -> None:
    """Range check of a decoded command against the robot's parameters (receiver side).

    Raises :class:`BusDecodeError` if ``force_N`` does not have ``n_motors`` entries or one lies
    outside ``[f_min_N, f_max_N]``; ``f_min_N`` is normally 0 (cables only pull).
    """
    if len(cmd.force_N) != n_motors:
        raise BusDecodeError(f"ForceCommand: {len(cmd.force_N)} forces for {n_motors} motors")
    for i, f in enumerate(cmd.force_N):
        if not (f_min_N <= f <= f_max_N):  # also false for NaN
            raise BusDecodeError(f"ForceCommand: force_N[{i}] = {f} N outside [{f_min_N}, {f_max_N}] N")


def check_motor_state(msg: MotorState, n_motors: int, f_max_N: float) -> None:
    """Range check of a decoded motor state (receiver side): one angle and one applied force per
    motor, the forces within [0, ``f_max_N``] (the bridge clamps what it applies; a wrong-length
    or 1e308 N state made the controller raise or command 1e308 N: audit of 2026-11-26).
    Raises :class:`BusDecodeError`."""
    if len(msg.theta_rad) != n_motors:
        raise BusDecodeError(f"MotorState: {len(msg.theta_rad)} angles for {n_motors} motors")
    if len(msg.force_applied_N) != n_motors:
        raise BusDecodeError(f"MotorState: {len(msg.force_applied_N)} applied forces for {n_motors} motors")
    for i, f in enumerate(msg.force_applied_N):
        if not (0.0 <= f <= f_max_N):
            raise BusDecodeError(f"MotorState: force_applied_N[{i}] = {f} N outside [0, {f_max_N}] N")


#: s an exposure's ``capture_stamp_s`` may lie after the ``stamp_s`` of the message that reports it:
#: the two come from one clock and every publisher stamps the capture at or before the
#: publication (a video file: equal; the twin and a USB camera: a latency ≥ 0 before), so this
#: only absorbs rounding. A capture any later is a stray's, or a broken publisher's.
CAPTURE_AFTER_PUBLICATION_MAX_S = 1e-3


def check_camera_alpha_stamps(msg: CameraAlpha) -> None:
    """Time check of a camera message, which needs no robot parameter (the recorder runs it): both
    stamps finite (a message decoded from the bus always has them so; one built in a process may
    not) and the capture not after the publication beyond :data:`CAPTURE_AFTER_PUBLICATION_MAX_S`.
    One stray α_IP stamped capture 1e9 s passed every check, was archived, and the identification
    refused the whole record for a clock step (audit of 2026-11-29). Not part of :func:`decode`:
    archives recorded before this check still read; their readers drop such a message.
    Raises :class:`BusDecodeError`."""
    capture, stamp = msg.capture_stamp_s, msg.stamp_s
    if not (math.isfinite(capture) and math.isfinite(stamp)):
        raise BusDecodeError(f"CameraAlpha: capture_stamp_s = {capture}, stamp_s = {stamp}: not finite")
    if capture > stamp + CAPTURE_AFTER_PUBLICATION_MAX_S:
        raise BusDecodeError(f"CameraAlpha: capture_stamp_s = {capture:.6g} s after its publication "
                             f"stamp_s = {stamp:.6g} s (an exposure ends before the message that reports it)")


def check_camera_alpha(msg: CameraAlpha, n_joints: int) -> None:
    """Range check of a decoded camera message (receiver side): ``n_joints`` angles within ±π, a
    confidence per joint in [0, 1] (or none), 0 for every missing joint, ``dropped`` ≥ 0, and its
    stamps (:func:`check_camera_alpha_stamps`). Raises :class:`BusDecodeError`."""
    check_camera_alpha_stamps(msg)
    if len(msg.alpha_ip_rad) != n_joints:
        raise BusDecodeError(f"CameraAlpha: {len(msg.alpha_ip_rad)} angles for {n_joints} joints")
    for i, a in enumerate(msg.alpha_ip_rad):
        if a is not None and not (-math.pi <= a <= math.pi):
            raise BusDecodeError(f"CameraAlpha: alpha_ip_rad[{i}] = {a} rad outside [-pi, pi]")
    if msg.confidence:
        if len(msg.confidence) != n_joints:
            raise BusDecodeError(f"CameraAlpha: {len(msg.confidence)} confidences for {n_joints} joints")
        for i, (a, c) in enumerate(zip(msg.alpha_ip_rad, msg.confidence)):
            if not (0.0 <= c <= 1.0) or (a is None and c != 0.0):
                raise BusDecodeError(f"CameraAlpha: confidence[{i}] = {c} (must be in [0, 1], 0 when missing)")
    if msg.dropped < 0:
        raise BusDecodeError(f"CameraAlpha: dropped = {msg.dropped} < 0")


def check_camera_frame(msg: CameraFrame) -> None:
    """Content check of a decoded frame (receiver side): ``data`` starts as a JPEG does (SOI
    marker), two coordinates per marker, every centroid inside the image. It does not decode the
    image (a receiver that shows it lets the browser or OpenCV refuse a damaged one).
    Raises :class:`BusDecodeError`."""
    if msg.data[:3] != b"\xff\xd8\xff":
        raise BusDecodeError("CameraFrame: data is not a JPEG image (no SOI marker)")
    # The size the JPEG itself declares is what a browser or decoder allocates: a 1 kB frame may
    # declare 60000×60000 px (audit of 2026-11-26). It must be the frame's own width × height.
    try:
        _kind, w, h = image_size(msg.data)
    except ImageFileError as exc:
        raise BusDecodeError(f"CameraFrame: {exc}") from None
    if (w, h) != (msg.width, msg.height):
        raise BusDecodeError(f"CameraFrame: the JPEG is {w}×{h} px (its header says), the frame {msg.width}×{msg.height}")
    if len(msg.markers_px) != 2 * len(msg.marker_bar):
        raise BusDecodeError(f"CameraFrame: {len(msg.markers_px)} coordinates for {len(msg.marker_bar)} markers")
    for k in range(len(msg.marker_bar)):
        x, y = msg.markers_px[2 * k], msg.markers_px[2 * k + 1]
        if not (0.0 <= x <= msg.width and 0.0 <= y <= msg.height):
            raise BusDecodeError(f"CameraFrame: marker {k} at ({x}, {y}) px outside the {msg.width}×{msg.height} image")


# --- schemas ----------------------------------------------------------------------------------


def json_schema(msg_type: type[BusMessage]) -> dict[str, Any]:
    """Self-contained JSON Schema (no ``$ref``) of ``msg_type``, with a ``title``, for MCAP/Foxglove.

    ``v`` is required and constant: the schema describes exactly one version.
    """
    if msg_type not in _VERSIONS:
        raise TypeError(f"{msg_type!r} is not a registered bus message type")
    raw = msgspec.json.schema(msg_type)
    schema = dict(raw["$defs"][msg_type.__name__]) if "$ref" in raw else dict(raw)
    # Flat messages only: a nested struct would need its $defs carried along.
    assert "$ref" not in msgspec.json.encode(schema).decode(), "nested structs are not supported"
    version = _VERSIONS[msg_type]
    properties = dict(schema["properties"])
    properties["v"] = {"type": "integer", "const": version, "description": "schema version"}
    schema["properties"] = properties
    schema["required"] = ["v", *[r for r in schema.get("required", []) if r != "v"]]
    schema["title"] = msg_type.__name__
    schema["$comment"] = f"{schema_name(msg_type)} version {version}"
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}


def json_schema_bytes(msg_type: type[BusMessage]) -> bytes:
    """:func:`json_schema` as the bytes stored in an MCAP schema record."""
    return msgspec.json.encode(json_schema(msg_type))


def as_plain(msg: BusMessage) -> Mapping[str, Any]:
    """A message as a dict of builtins (for JSON APIs and plotting)."""
    return msgspec.structs.asdict(msg)


__all__ = [
    "ALIVE_ALL",
    "ALL",
    "BRIDGE_CLOCK",
    "CAMERA_ALPHA",
    "CAMERA_FRAME",
    "CAMPAIGN_EVENTS",
    "CAMPAIGN_REQUEST",
    "CAMPAIGN_REQUEST_TO",
    "CAPTURE_AFTER_PUBLICATION_MAX_S",
    "CONTROLLER_STATUS",
    "CONTROLLER_TIMING",
    "ESTOP",
    "ESTOP_ENGAGED_ALL",
    "HEALTH_ALL",
    "MESSAGE_TYPES",
    "MOTOR_COMMAND",
    "MOTOR_STATE",
    "PATTERNS",
    "PAYLOAD_MAX_BYTES",
    "PAYLOAD_MAX_BYTES_BY_TYPE",
    "PREFIX",
    "REGISTRY",
    "TWIN_TRUTH",
    "BusDecodeError",
    "BusEncodeError",
    "BusMessage",
    "CameraAlpha",
    "CameraFrame",
    "CampaignEvent",
    "CampaignRequest",
    "ClockReading",
    "ControllerStatus",
    "ControllerTiming",
    "EStop",
    "ForceCommand",
    "Health",
    "MotorState",
    "Truth",
    "as_plain",
    "campaign_request_key",
    "check_camera_alpha",
    "check_camera_alpha_stamps",
    "check_camera_frame",
    "check_force_command",
    "check_motor_state",
    "check_payload_size",
    "decode",
    "encode",
    "estop_token_key",
    "health_key",
    "json_schema",
    "json_schema_bytes",
    "key_of_topic",
    "liveliness_key",
    "max_payload_bytes",
    "mcap_topic",
    "message_type",
    "parse_estop_token_key",
    "parse_liveliness_key",
    "plain_text",
    "schema_name",
    "schema_version",
]
