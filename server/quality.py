"""What a campaign's run was really like: the drives' state and the real-time quality, measured on
the bus while it runs, and the thresholds that make its outcome ``degraded`` (issue 13, findings 4
and 7).

:class:`CampaignMonitor` subscribes to the bridge's ``MotorState`` and the controller's
``ForceCommand`` and ``ControllerStatus`` on the campaign's session; its callbacks only decode and update counters under a
lock. The campaign runner marks the window (:meth:`~CampaignMonitor.begin` at the controller's
first event, :meth:`~CampaignMonitor.end` at its last), hands it the controller's own counts of
the campaign (:meth:`~CampaignMonitor.note_event`: ``CampaignEvent`` v2 carries ``ticks``,
``overruns``, ``deadline_misses`` since the campaign started) and asks two questions:

Drives
    :meth:`~CampaignMonitor.drives_disabled` — did the bridge report its drives disabled (its
    e-stop, latched and published in every ``MotorState``) during the window? Then the campaign
    ends ``aborted`` with the bridge's reason, whatever the controller says: the bridge is the one
    truth of the e-stop, not what the console last sent.
Quality
    :func:`assess` compares the window's counters with :data:`THRESHOLDS`; every breach is a reason,
    and a campaign that finished with reasons ends ``degraded``. The thresholds (defined here only):

    - **deadline misses**: ticks whose command left late over the ticks of the campaign, both as
      the controller counts them for this campaign (its last event), at most
      :attr:`QualityThresholds.deadline_miss_rate_max` (1 %). Real-time campaigns only: a lockstep
      run has no deadline.
    - **record gaps**: ``MotorState`` and ``ForceCommand`` messages missing from their publishers'
      ``seq`` sequences as seen by the console, plus those the recorder dropped, over the messages
      expected, at most :attr:`QualityThresholds.lost_fraction_max` (0.1 %). A gap is one run of
      missing messages; both the gaps and the messages lost are reported.
    - **rate**: the commands' rate in wall-clock time over the window, at least
      :attr:`QualityThresholds.rate_min_fraction` (95 %) of :attr:`QualityThresholds.nominal_rate_hz`
      (500 Hz, the prototype's control rate). Real-time campaigns only: lockstep runs as fast as
      it can and its simulated time is exact by construction.

Cables at f_max (said, not judged)
    The law's ticks (the campaign's controller's ``ControllerStatus``, holds excluded:
    ``law_ticks``) with a cable saturated (``saturated_ticks``; per cable ``saturated_by_cable``)
    are counted for every campaign. An identification's message says so when they are more than
    :data:`SATURATION_NOTE_FRACTION` (1 %) of them (:func:`saturation_note`; user audit of session
    42: 11 % of a campaign's ticks at f_max, ``finished`` without a word). It is a note, not a
    reason to degrade: the force recorded is the force applied (f_max asks 2.2 A of the ESCON's 5 A
    on the prototype, ρ·f_max/k_t: its current loop does not saturate there), so the fit's data
    stand; what saturation changes is the excitation, which the law tracked less closely than
    designed, and the fit's σ says what that cost. A control campaign's saturation is its law's
    performance (its metrics' ``saturated_ticks``, Fig. 14). A status counts only when it has one
    ``saturated`` flag per cable of the robot (the runner tells the monitor how many; else the
    first status counted sets it): any peer may name the followed controller, and a forged status
    of 13 000 flags had cost a millisecond under the monitor's lock and grown
    ``saturated_by_cable`` to 13 000 counts in the record (review of session 43). Others are
    counted in ``rejected_payloads``.

The same counters go to the campaign's record (``quality``) and its MCAP metadata.

One bridge, one controller
    Once told the campaign's controller (:meth:`~CampaignMonitor.follow`), the monitor takes only
    its commands and statuses (a status names its controller in its attachment), and only the
    states of the bridge run they answer (their ``epoch``); the recorder keeps the same
    (:meth:`~CampaignMonitor.keep`; another controller's statuses had been archived too, session 43). A second bridge on the bus (a lab's
    robot bridge joining the twin's hub) had ended the campaign on its own disabled drives and
    mixed its states and sequence numbers into the record (audit of 2026-11-28).

    The twin's ``Truth`` has no identity field: the bridge that runs the twin names its run in
    the sample's attachment (:func:`bridge.session.run_of`), and only the truth of the run
    followed is kept, so an archive holds one ground truth (a second twin's had been archived
    beside it, interleaved: audit of 2026-11-29). Once that run is known, a truth that names
    another run or none is set aside; so is what another run's driver publishes (a twin's α_IP),
    while α_IP naming no run (a camera process) is kept. Set aside, counted:
    ``foreign_messages`` (everything), ``foreign_truths`` (its truths).

One camera
    Any peer may publish α_IP, and two cameras did on one bus (`xneck up`'s twin's white noise and
    an `xneck camera --source twin` beside it): both were archived, interleaved, the campaign's
    e_α compared α̂ with both, and the identification fitted them as one camera (k(4) 4464 → 7530
    N/m: audit of 2026-11-29). A campaign records the α_IP of one ``CameraAlpha.source``: the one
    the runner knows it started (:meth:`~CampaignMonitor.expect_alpha_ip_source`: a spawned twin's
    or camera process's, `xneck up`'s twin's), else the first the recorder sees. The others are
    set aside and counted, in ``foreign_messages`` and per source in ``foreign_alpha_ip``
    (``alpha_ip_source`` names the one recorded), and :func:`camera_note` says so in the
    campaign's message.

    A source is a kind of camera, which two share (two `xneck camera --source twin`, two ``usb:0``
    on two PCs: both archived as one, audit of 2026-11-29). A camera process names itself in its
    α_IP's attachment (:func:`bridge.session.camera_of`): of the source recorded, the camera
    expected, else the first named, is recorded (``alpha_ip_camera``); another camera's α_IP is
    set aside as above, counted as ``<source>@<camera>``, and so are its frames
    (``foreign_messages``). α_IP naming no camera (a twin's white noise, an older camera process,
    a replay) is told by its source alone, as before.
"""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any

import zenoh

from bridge import bus
from bridge.session import controller_of, payload_of, run_of


@dataclass(frozen=True)
class QualityThresholds:
    """Limits below which a finished campaign is ``degraded`` (module docstring)."""

    deadline_miss_rate_max: float = 0.01  # deadline misses per tick
    lost_fraction_max: float = 0.001  # messages missing from the record per message expected
    rate_min_fraction: float = 0.95  # of the nominal rate, wall clock
    nominal_rate_hz: float = 500.0  # the prototype's control rate


THRESHOLDS = QualityThresholds()
#: An identification's message notes its cables at f_max beyond this fraction of the law's ticks
#: (module docstring, "Cables at f_max").
SATURATION_NOTE_FRACTION = 0.01


class _SeqCounter:
    """Counts messages and the runs of missing ``seq`` numbers of one publisher. A jump back
    (a restarted publisher) starts a new sequence, neither a gap nor a loss."""

    def __init__(self) -> None:
        self.count = self.gaps = self.lost = 0
        self._last: int | None = None

    def add(self, seq: int) -> None:
        self.count += 1
        if self._last is not None and seq > self._last + 1:
            self.gaps += 1
            self.lost += seq - self._last - 1
        self._last = seq


class CampaignMonitor:
    """Follows the drives and counts the real-time quality of one campaign (module docstring).
    Close it (or use it as a context manager)."""

    def __init__(self, session: zenoh.Session, n_cables: int | None = None) -> None:
        """``n_cables``: the robot's cables (a controller status with another number of ``saturated``
        flags is rejected; None: the first status counted says it)."""
        self._lock = threading.Lock()
        self._n_cables = n_cables
        self._active = self._ended = False
        self._states, self._commands = _SeqCounter(), _SeqCounter()
        self._first_cmd_s = self._last_cmd_s = 0.0
        self._last_state_s: float | None = None  # time.monotonic() of the newest MotorState, any time
        self._began_s: float | None = None
        self._controller = {"controller_ticks": 0, "overruns": 0, "deadline_misses": 0}  # its counts, this campaign
        self._law_ticks = self._saturated_ticks = 0  # the law's ticks in the window, those with a cable at f_max
        self._saturated_by_cable: list[int] = []
        self.disabled_reason = ""
        self.rejected = 0
        self._timing: dict[str, Any] = {}  # the controller's own timing of this campaign (issue 21)
        self._follow = ""  # the campaign's controller instance ('' until told: every sender)
        self.epoch = ""  # the bridge run its commands answer ('' until one came: every bridge)
        self.foreign = 0  # states, commands, truths and α_IP of other bridges and controllers, not taken
        self.foreign_truths = 0  # of which truths of another twin (or of none said)
        self.truth_seen: str | None = None  # the truth its twin says it simulates (Truth.truth; first one decoded)
        self._owners: dict[str, tuple[str, float]] = {}  # bridge epoch -> (the controller it obeys, monotonic s)
        self._alpha_ip_source: str | None = None  # the camera recorded (None until known: module docstring)
        self._alpha_ip_camera = ""  # the camera process recorded ('' until one named itself: module docstring)
        self.foreign_alpha_ip: dict[str, int] = {}  # α_IP of other cameras set aside, per source[@camera]
        self._alpha_ip_kept = 0  # α_IP of the camera recorded that the recorder kept
        self._camera_expected = False  # the camera recorded was named by the runner, not adopted
        self._cameras_alive: set[str] = set()  # camera processes whose liveliness token is up
        self._cameras_gone: set[str] = set()  # ... whose token went (seen up, then down)
        self._subs = [session.declare_subscriber(bus.MOTOR_STATE, self._on_state),
                      session.declare_subscriber(bus.MOTOR_COMMAND, self._on_command),
                      session.declare_subscriber(bus.CONTROLLER_STATUS, self._on_status),
                      session.declare_subscriber(bus.CONTROLLER_TIMING, self._on_timing),
                      session.declare_subscriber(bus.TWIN_TRUTH, self._on_run_message),
                      session.declare_subscriber(bus.CAMERA_ALPHA, self._on_run_message),
                      session.liveliness().declare_subscriber(f"{bus.PREFIX}/alive/camera/*", self._on_camera_token,
                                                              history=True)]

    # -- whose messages ------------------------------------------------------------------------
    def follow(self, controller: str) -> None:
        """Take only ``controller``'s commands from now on, and the states of the bridge run they answer."""
        with self._lock:
            self._follow = controller

    def expect_alpha_ip_source(self, source: str, camera: str = "") -> None:
        """Record only the α_IP of ``source`` (``CameraAlpha.source``) and, if given, of the camera
        process ``camera`` (its instance), the camera the campaign started, whatever comes first
        (module docstring, "One camera")."""
        with self._lock:
            self._alpha_ip_source, self._alpha_ip_camera = source, camera
            self._camera_expected = bool(camera)

    def recorded_camera(self) -> str:
        """The camera process whose α_IP is recorded (module docstring, "One camera"): its instance,
        :data:`TWIN_CAMERA` for the campaign's twin's own, '' until one named itself (or when only
        the source tells). Takes no lock (one attribute read): the console's live view asks it at
        every read, under a lock of its own (:attr:`server.live.LatestValues.prefer_camera`)."""
        return self._alpha_ip_camera

    def recorded_alpha_ip(self) -> str:
        """The ``CameraAlpha.source`` of the α_IP the recorder kept (:meth:`keep`), '' if it kept
        none: a camera expected that sent nothing recorded nothing. Ask it once the recorder has
        written its last message (:meth:`bridge.archive.CampaignRecorder.stop`'s ``final_metadata``)."""
        with self._lock:
            return (self._alpha_ip_source or "") if self._alpha_ip_kept else ""

    def _on_camera_token(self, sample: zenoh.Sample) -> None:
        # Zenoh callback thread: a camera process appeared or went (its instance is the key's last chunk).
        try:
            _kind, name = bus.parse_liveliness_key(str(sample.key_expr))
        except ValueError:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                if len(self._cameras_alive) < 64:  # a flood of forged tokens stays bounded
                    self._cameras_alive.add(name)
                self._cameras_gone.discard(name)
            elif name in self._cameras_alive:
                self._cameras_alive.discard(name)
                self._cameras_gone.add(name)

    def owners(self, within_s: float = 0.5) -> set[str]:
        """The controllers the bridges on the bus obeyed within the last ``within_s`` s."""
        now = time.monotonic()
        with self._lock:
            return {owner for owner, t in self._owners.values() if owner and now - t <= within_s}

    def keep(self, key: str, msg: bus.BusMessage, run: str = "", camera: str = "", controller: str = "") -> bool:
        """Whether the recorder keeps ``msg``, whose sample named the bridge run ``run``, the
        camera process ``camera`` and the controller ``controller`` ('' for none): not a state of
        another bridge run than the campaign's, nor a command or status of another controller, nor
        a truth not of the campaign's run, nor anything else another run's driver published, nor
        another camera's α_IP or frame (module docstring)."""
        if isinstance(msg, bus.MotorState):
            return not self.epoch or msg.epoch == self.epoch
        if isinstance(msg, bus.ForceCommand):
            return not self._follow or msg.sender == self._follow
        if isinstance(msg, bus.ControllerStatus):
            # another controller's statuses had been archived, and its saturation counted in the
            # campaign's metrics (helper's finding, session 43)
            return not self._follow or controller == self._follow
        if not self._of_run(isinstance(msg, bus.Truth), run):
            return False  # counted by the subscriber (_on_run_message)
        if isinstance(msg, bus.CameraAlpha):
            # the campaign's own twin's α_IP (rendered or noise, in its driver) carries its run
            return self._one_camera(msg.source, camera or (TWIN_CAMERA if run else ""))
        return self._camera_frame(msg.source, camera) if isinstance(msg, bus.CameraFrame) else True

    #: distinct foreign α_IP sources counted by name (a flood of forged names stays bounded), and
    #: the length a name is cut to; the rest are counted under ``(others)``
    FOREIGN_SOURCES_MAX, SOURCE_NAME_MAX = 8, 64

    def _one_camera(self, source: str, camera: str) -> bool:
        """Whether α_IP of ``source`` from the camera process ``camera`` ('' if it names none) is the
        campaign's camera: the expected one, else the first seen (module docstring, "One camera")."""
        with self._lock:
            if self._alpha_ip_source is None:
                self._alpha_ip_source = source
            if source == self._alpha_ip_source:
                if not camera:
                    self._alpha_ip_kept += 1
                    return True  # no name to tell it by: its source is the campaign's
                if not self._alpha_ip_camera or self._handed_over(camera):
                    self._alpha_ip_camera = camera
                if camera == self._alpha_ip_camera:
                    self._alpha_ip_kept += 1
                    return True
            self.foreign += 1
            name = camera_name(source, camera)[: self.SOURCE_NAME_MAX]
            if name not in self.foreign_alpha_ip and len(self.foreign_alpha_ip) >= self.FOREIGN_SOURCES_MAX:
                name = "(others)"
            self.foreign_alpha_ip[name] = self.foreign_alpha_ip.get(name, 0) + 1
            return False

    def _handed_over(self, camera: str) -> bool:
        """(Under the lock.) Whether the camera adopted (the first seen, not one the runner named)
        is gone and ``camera``, alive, takes its place: a camera process restarted mid-campaign
        under a new name (its default name is random) had all its later α_IP set aside (audit of
        2026-11-29)."""
        # gone, not merely unseen: a token the subscriber has not yet heard of is no camera gone
        return (not self._camera_expected and self._alpha_ip_camera in self._cameras_gone
                and camera in self._cameras_alive)

    def _camera_frame(self, source: str, camera: str) -> bool:
        """Whether a frame of ``source`` from the camera process ``camera`` may be the recorded
        camera's: not if the α_IP recorded is of another source or names another camera."""
        with self._lock:
            other = (self._alpha_ip_source not in (None, source)
                     or bool(camera and self._alpha_ip_camera and camera != self._alpha_ip_camera))
            self.foreign += other
            return not other

    def _of_run(self, truth: bool, run: str) -> bool:
        """Whether a sample naming the bridge run ``run`` is the campaign's: any until its run is
        known; then a truth only of that run, anything else unless it names another."""
        epoch = self.epoch  # one read: the command callback may move it to a restarted bridge's run
        return not epoch or run == epoch or (not truth and not run)

    # -- window -----------------------------------------------------------------------------
    def begin(self) -> None:
        """Start counting (the controller's first event of the campaign)."""
        with self._lock:
            self._active = True
            self._began_s = time.monotonic()

    def note_event(self, event: bus.CampaignEvent) -> None:
        """The controller's counts of this campaign so far, from one of its events."""
        with self._lock:
            self._controller = {"controller_ticks": event.ticks, "overruns": event.overruns,
                                "deadline_misses": event.deadline_misses}

    def wait_final_timing(self, campaign_id: str, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the controller's final timing of ``campaign_id``: the one
        with its end event's ticks (:meth:`note_event`). Call before :meth:`end`. Why: the timing's
        subscriber runs in its own thread (zenoh-python's default), which may be behind the events'
        though the controller put the timing first (bridge.archive.CampaignRecorder.stop)."""
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                if not self._controller["controller_ticks"]:
                    return False  # no tick ran: no timing to wait for
                if self._timing.get("id") == campaign_id \
                        and self._timing.get("ticks") == self._controller["controller_ticks"]:
                    return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.005)

    def state_silence_s(self) -> float:
        """Seconds since the bridge's newest motor state (since :meth:`begin` if none came); 0
        before it began. A campaign whose bridge went silent is not waited for until its timeout
        (audit of 2026-11-26: a killed or hung remote bridge left a campaign running 600 s)."""
        with self._lock:
            if self._began_s is None:
                return 0.0
            return time.monotonic() - max(self._began_s, self._last_state_s or self._began_s)

    def end(self) -> None:
        """Stop counting and following (the campaign's last event; the bridge may disable after)."""
        with self._lock:
            self._active, self._ended = False, True

    # -- callbacks (Zenoh threads: decode, count, nothing else) -----------------------------
    def _decode(self, msg_type: type[bus.BusMessage], sample: zenoh.Sample) -> Any:
        try:
            return bus.decode(msg_type, payload_of(sample, msg_type))
        except bus.BusDecodeError:
            with self._lock:
                self.rejected += 1
            return None

    def _on_state(self, sample: zenoh.Sample) -> None:
        msg = self._decode(bus.MotorState, sample)
        if msg is None:
            return
        engaged, reason = drive_estop(msg)
        with self._lock:
            now = time.monotonic()
            if len(self._owners) < 64 or msg.epoch in self._owners:  # a flood of forged epochs stays bounded
                self._owners[msg.epoch] = (msg.owner, now)
            if self.epoch and msg.epoch != self.epoch:
                self.foreign += 1
                return
            self._last_state_s = now
            # Drives are followed from the monitor's creation, the quality only within the window.
            if (engaged or msg.drive == "disabled") and not self.disabled_reason and not self._ended:
                self.disabled_reason = reason
            if self._active:
                self._states.add(msg.seq)

    def _on_command(self, sample: zenoh.Sample) -> None:
        msg = self._decode(bus.ForceCommand, sample)
        now = time.monotonic()
        with self._lock:
            if msg is None:
                return
            if self._follow and msg.sender != self._follow:
                self.foreign += 1
                return
            if self._follow:
                self.epoch = msg.epoch  # a restarted bridge's new run: its commands answer it
            if not self._active:
                return
            if self._commands.count == 0:
                self._first_cmd_s = now
            self._last_cmd_s = now
            self._commands.add(msg.seq)

    def _on_status(self, sample: zenoh.Sample) -> None:
        """Counts the law's ticks with a cable at f_max (module docstring): of the followed controller
        (its status names it in the attachment), within the window, holds excluded."""
        with self._lock:
            if not self._active or (self._follow and controller_of(sample) != self._follow):
                return  # not decoded: neither the campaign's nor counted as foreign (its commands are)
        msg = self._decode(bus.ControllerStatus, sample)
        if msg is None or msg.holding:
            return
        with self._lock:
            if not self._active:
                return
            if self._n_cables is None and msg.saturated:
                self._n_cables = len(msg.saturated)
            if len(msg.saturated) != self._n_cables:  # not the robot's cables: forged, or another robot's
                self.rejected += 1
                return
            self._law_ticks += 1
            if any(msg.saturated):
                self._saturated_ticks += 1
                if len(self._saturated_by_cable) < len(msg.saturated):
                    self._saturated_by_cable += [0] * (len(msg.saturated) - len(self._saturated_by_cable))
                for j, clipped in enumerate(msg.saturated):
                    self._saturated_by_cable[j] += clipped

    def _on_run_message(self, sample: zenoh.Sample) -> None:
        """Counts the truths and α_IP of another twin (not decoded: the attachment says whose)."""
        truth = str(sample.key_expr) == bus.TWIN_TRUTH
        if self._of_run(truth, run_of(sample)):
            if truth and self.truth_seen is None and self.epoch:  # once, of the campaign's own run
                msg = self._decode(bus.Truth, sample)
                if msg is not None:
                    self.truth_seen = msg.truth
            return
        with self._lock:
            self.foreign += 1
            self.foreign_truths += truth

    def _on_timing(self, sample: zenoh.Sample) -> None:
        msg = self._decode(bus.ControllerTiming, sample)
        with self._lock:
            if msg is None or not msg.campaign_id or (self._ended and msg.campaign_id != self._timing.get("id")):
                return
            # Its state-to-command latency over the whole campaign (upper bin edges, ms), and the
            # stale states of bursts it skipped; the last message of the campaign is its final one.
            skipped = self._timing.get("skipped_states", 0) + msg.window_skipped
            self._timing = {"id": msg.campaign_id, "ticks": msg.campaign_ticks,
                            "latency_p50_ms": msg.campaign_latency_p50_ms,
                            "latency_p99_ms": msg.campaign_latency_p99_ms, "skipped_states": skipped}

    # -- questions --------------------------------------------------------------------------
    def drives_disabled(self) -> str:
        """The bridge's reason if it reported its drives disabled during the window, else ''."""
        with self._lock:
            return self.disabled_reason

    def wait_drives_disabled(self, timeout_s: float) -> str:
        """:meth:`drives_disabled`, waiting up to ``timeout_s`` for the bridge to say so."""
        deadline = time.monotonic() + timeout_s
        while not self.drives_disabled() and time.monotonic() < deadline:
            time.sleep(0.01)
        return self.drives_disabled()

    def counters(self, recorder_dropped: int = 0) -> dict[str, Any]:
        """The window's counters (plain numbers, for the record and the MCAP metadata)."""
        with self._lock:
            duration_s = self._last_cmd_s - self._first_cmd_s
            return {
                "ticks": self._commands.count, "states": self._states.count,
                "duration_wall_s": round(duration_s, 4),
                "rate_hz": round((self._commands.count - 1) / duration_s, 2) if duration_s > 0 else 0.0,
                **self._controller,
                **{k: v for k, v in self._timing.items() if k not in ("id", "ticks")},
                "record_gaps": self._states.gaps + self._commands.gaps + (1 if recorder_dropped else 0),
                "messages_lost": self._states.lost + self._commands.lost + recorder_dropped,
                "recorder_dropped": recorder_dropped, "rejected_payloads": self.rejected,
                "foreign_messages": self.foreign, "foreign_truths": self.foreign_truths,
                "alpha_ip_source": self._alpha_ip_source, "alpha_ip_camera": self._alpha_ip_camera,
                "foreign_alpha_ip": dict(self.foreign_alpha_ip),
                "law_ticks": self._law_ticks, "saturated_ticks": self._saturated_ticks,
                "saturated_by_cable": list(self._saturated_by_cable),
            }

    def close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()

    def __enter__(self) -> CampaignMonitor:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def drive_estop(state: bus.MotorState) -> tuple[bool, str]:
    """(engaged, reason) of the bridge's latched e-stop from one of its states (``MotorState`` v2);
    drives disabled without it (a bridge stopping) are not an e-stop but get a reason too."""
    if state.estop_engaged:
        return True, state.estop_reason or "e-stop engaged"
    if state.drive == "disabled":  # a stopping bridge says why in its last state
        return False, bus.plain_text(state.hold_reason) or "the bridge's drives are disabled"
    return False, ""


def assess(counters: dict[str, Any], realtime: bool, limits: QualityThresholds = THRESHOLDS) -> list[str]:
    """The reasons (sentences) a campaign with these counters is degraded; [] if none."""
    reasons = []
    ticks = int(counters.get("ticks", 0))
    expected = ticks + int(counters.get("states", 0)) + int(counters.get("messages_lost", 0))
    lost = int(counters.get("messages_lost", 0))
    if expected and lost / expected > limits.lost_fraction_max:
        reasons.append(f"record gaps: {lost} of {expected} messages lost in {counters.get('record_gaps', 0)} gap(s) "
                       f"({100 * lost / expected:.2f} % > {100 * limits.lost_fraction_max:.2f} %)")
    controller_ticks = int(counters.get("controller_ticks", 0)) or ticks
    if realtime and controller_ticks:
        misses = int(counters.get("deadline_misses", 0))
        if misses / controller_ticks > limits.deadline_miss_rate_max:
            reasons.append(f"deadline misses: {misses} in {controller_ticks} ticks "
                           f"({100 * misses / controller_ticks:.1f} % > {100 * limits.deadline_miss_rate_max:.0f} %)")
        rate = float(counters.get("rate_hz", 0.0))
        floor = limits.rate_min_fraction * limits.nominal_rate_hz
        if ticks > 1 and rate < floor:
            reasons.append(f"rate {rate:.0f} Hz below {100 * limits.rate_min_fraction:.0f} % of the nominal "
                           f"{limits.nominal_rate_hz:.0f} Hz ({floor:.0f} Hz)")
    return reasons


def saturation_note(counters: dict[str, Any], fraction: float = SATURATION_NOTE_FRACTION) -> str:
    """The sentence an identification's message gets when its cables sat at f_max in more than
    ``fraction`` of the law's ticks (module docstring, "Cables at f_max"); '' otherwise, and for a
    record made before the count (no ``law_ticks``)."""
    law_ticks, saturated = int(counters.get("law_ticks", 0)), int(counters.get("saturated_ticks", 0))
    if not law_ticks or saturated / law_ticks <= fraction:
        return ""
    by_cable = [int(n) for n in counters.get("saturated_by_cable") or []]
    most = f", cable {by_cable.index(max(by_cable)) + 1} most ({max(by_cable)} ticks; by cable " \
           f"{', '.join(map(str, by_cable))})" if by_cable else ""
    return (f"cables at f_max in {100 * saturated / law_ticks:.1f} % of the law's ticks ({saturated} of {law_ticks}, "
            f"> {100 * fraction:g} %){most}: the law asked more than f_max, so the excitation was tracked less "
            f"closely than designed (the forces recorded are those applied: the fit's data stand, its σ says the cost)")


def camera_note(counters: dict[str, Any]) -> str:
    """The sentence a campaign's message gets when α_IP of other cameras was set aside (module
    docstring, "One camera"); '' when there was none."""
    foreign = counters.get("foreign_alpha_ip") or {}
    if not foreign:
        return ""
    others = ", ".join(f"{name!r} ({n})" for name, n in sorted(foreign.items(), key=lambda kv: -kv[1]))
    recorded = camera_name(str(counters.get("alpha_ip_source")), str(counters.get("alpha_ip_camera") or ""))
    return (f"α_IP recorded from one camera, {recorded!r}; {sum(foreign.values())} α_IP "
            f"message(s) of another camera on the bus set aside: {others}")


#: The camera name of α_IP that carries a bridge run's attachment instead of a camera's: the
#: campaign's twin's own camera (rendered in its driver, or its white noise). A runner whose twin
#: renders its camera expects it (server.campaign_runner): a stray camera process of the same source
#: was adopted first and both recorded, interleaved (audit of 2026-11-29).
TWIN_CAMERA = "twin"


def camera_name(source: str, camera: str) -> str:
    """A camera as the campaign's quality names it: ``<source>@<camera>``, or its source if it names none."""
    return f"{source}@{camera}" if camera else source


def thresholds_dict(limits: QualityThresholds = THRESHOLDS) -> dict[str, float]:
    return asdict(limits)


__all__ = ["SATURATION_NOTE_FRACTION", "THRESHOLDS", "TWIN_CAMERA", "CampaignMonitor", "QualityThresholds", "assess", "camera_name", "camera_note", "drive_estop",
           "saturation_note", "thresholds_dict"]
