"""The controller's campaign service as a pure state machine: no bus, no clock, no threads.

:class:`controller.process.ControllerNode` is the shell around it: it turns bus messages into
calls of :class:`CampaignService` and the answers back into bus messages. Everything that decides
what the neck does lives here, so it is tested without Zenoh (tests/test_controller_service.py).

Life cycle of one campaign::

    idle --request--> starting --prepared--> running --trajectory + settle_s--> finished
                         |                      |--estimate diverges / stop request--> aborted
                         '--refused-----------> aborted (with the reason)

``finished`` and ``aborted`` are idle again for the next request. Between campaigns the law holds
the neck at ``hold_target`` (the last waypoint, or where it was when the service started), with
the service's own law and parameter set: a campaign's own are given back when it ends (``_go_home``). A
campaign starts bumplessly from that hold, as a jog does: α^d approaches the first waypoint from
where it rests, and the law (or the new law) goes on with its filtered velocities and its
integral's share of the command (``_switch_law``).

Holds: :meth:`CampaignService.hold` commands Z f = g(α) with every cable at t_min
(:func:`controller.laws.hold_forces`) at α̂, or at the last sane α̂ when the estimate is not
(non-finite or beyond the joint limits). A diverging estimate latches the hold until the next
campaign starts. A trajectory's pretension (raised floor, controller.trajectory) is followed while
the campaign runs; once it stops, the floor falls back to t_min at ``PRETENSION_RELEASE_N_S``,
in the law and in the hold alike, so an abort at high tension drops no force in one tick. A
campaign that starts on a raised floor (an aborted campaign's, a take-up's) lets it go at that
rate too, under its own pretension.

Drives and re-starts (issue 13): while the bridge says the drives are ``disabled`` (e-stop) or
``inactive`` (until a command enables them) the law does not run: α̂ follows the encoders and the
applied forces (:meth:`controller.laws.ComputedTorque.observe`), the integral stays at zero and
the command is the hold forces at α̂, so nothing grows while the drives are off and the first
command that enables them is one that holds the neck where it is. When the drives are ``active``
again (also after a watchdog ``hold`` of the bridge of more than a period, ``HOLD_RESTART_S``: for
one tick the law runs on, its next command ending the hold; and after a hold of the controller's
own for stale states) the
law re-starts from the measurement: a fresh integral and α^d starting at α̂, blended back to the
trajectory by a cycloid as gentle as :func:`controller.trajectory.approach`. The campaign's clock
stops meanwhile (at the last state before stale states, once the bridge's holds add up to
``HOLD_RESTART_S``, more than a period, or when the drives go off) and comes back up to speed from rest over
:meth:`CampaignService.resume_duration_s` (a cycloid in the clock's rate,
:meth:`CampaignService.campaign_time`; none where the trajectory rests, a dwell's or its start): the
law takes over at α̇^d = 0 and the campaign resumes where it was, ending later by the time it was
stopped plus half the ramp (α̇^d had been the trajectory's at once: 128-130°/s after a 0.3 s
watchdog hold mid-move, past the trajectories' 86°/s; session 43). A controller starved for
good (its bridge flapping hold/active) thus stops its campaign's clock for as long: the campaign
makes no progress rather than running on a neck it does not control. Taking over from its own
hold (stale states, the bridge obeying it), the law's command winds down from the hold's at the
take-up's 1 N a tick until it meets the law's (it had stepped 10 N, then 6.5 N). A campaign during which the drives were disabled ends
``aborted`` with the reason, and none starts while they are. After an e-stop the law does not
take over at once: the fall left cables slack that the hold's forces cannot wind in, and α̂ off
the neck, so every cable's floor is first raised past the motors' friction at α̂ until the motors
stop winding in (:mod:`controller.take_up`); a campaign asked for meanwhile starts after it. A
take-up that ends, or that a latch cuts short, winds down: the command keeps its 1 N a tick
until it meets the law's or the hold's. A service that joins a bridge run under way (a
controller restarted) cannot know whether an e-stop left slack: it takes one up too before its
law runs, and re-reads α̂ from the taut cables after it when its first state showed slack
(:meth:`CampaignService.initialise`).

Jogs (kind ``jog``, the console's sliders): a jog is a campaign of one waypoint reached by the
gentle approach from α̂. A jog asked for while a jog runs is prepared, then waits (the newest one
only; an older waiting one is answered ``aborted``, superseded) until the running one finishes at
rest on its pose, and starts from there: moves chain without a step in α^d or α̇^d. Stopping or
aborting the running jog drops the waiting one.

Stops: a stop request (the user's, or the console's on a silent bridge or a timeout) while the law
tracks brings α^d to rest from where it is at its speed and acceleration (:func:`controller.trajectory.brake_at`,
at most the trajectories' 3 rad/s², firmer where that would cross a joint limit) and holds there,
as any jog or campaign does, through a re-start of the law too; a campaign asked for meanwhile
starts when α^d rests. Faults (a latch, drives off, a new bridge run) hold at α̂ instead and answer
a campaign waiting for the brake with the reason.

Untrusted input: :func:`controller.prepare.prepare` parses and validates a request (JSON text only,
bounded waypoint count and duration, a time budget for the force check);
:class:`controller.state_gate.StateGate` admits motor states of one bridge run on a clock
consistent with the controller's own.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np

from bridge import bus
from controller import take_up as take_up_rules
from controller.encoder_check import THRESHOLD_M, EncoderConsistency, detector_model, residuals
from controller.laws import ComputedTorque, LawConfig, hold_forces
from controller.prepare import Prepared, Refused, prepare
from controller.take_up import TakeUp, take_up_peak_N
from controller.trajectory import (
    BRAKE_RELEASE_ACCELERATION_MAX_RAD_S2,
    Trajectory,
    approach,
    approach_duration_s,
    brake_at,
    brake_duration_s,
    cycloid_at,
    release_duration_s,
)
from twin.model.estimation import alpha_hat_3, static_elongation
from twin.model.params import Params

DIVERGENCE_MARGIN = math.radians(20.0)  # rad beyond the joint limit that counts as diverging
PROGRESS_PERIOD_S = 0.5  # s of campaign time between two progress events
# s without states after which the law re-starts from the measurement: any gap its own hold
# covered (the process holds after its stale_s, 10 ms). It was 0.1 s: after a shorter gap the law
# went on from its hold, its commands stepping 10 N a tick back to the law's, and after 30-50 ms
# with the trajectory's clock that had run on while the neck was held (57-70°/s; 65-135°/s when
# the bridge took the hold throughout); re-started, at most 1.8 N a tick and 52°/s (control test,
# robot truth, laws 1-3: docs/safety/watchdog_handback.py --stale, session 46). The price: the
# campaign's clock stops and comes back to speed after each such gap.
STALE_RESTART_S = 0.0
# s the bridge must obey on end before its watchdog holds are no longer summed (HOLD_RESTART_S)
HOLDS_FORGOTTEN_S = 0.1
# s of the bridge's watchdog holds (summed until it obeys HOLDS_FORGOTTEN_S on end) after which the
# law re-starts as after stale states: more than one 500 Hz period, so one late command is no
# loss. It was 0.1 s: a loss of 20-98 ms (a 10-88 ms hold) mid-move left the law
# running on the held neck, its commands climbing to f_max and the trajectory's clock running on,
# and at the hand-back the neck reached 74-157°/s, past the trajectories' 86°/s, |α| 55°
# (docs/safety/watchdog_handback.py, session 46); re-started, 37-53°/s.
HOLD_RESTART_S = 0.003
# A campaign whose clock advanced less than PROGRESS_MIN_RATIO of RESTARTS_WINDOW_S s over that
# long while its law re-started at least RESTARTS_MIN times is aborted naming why: every re-start
# stops its clock and brings it back up to speed, so one-tick holds 60-90 ms apart (a controller
# whose commands come late all the time) held a campaign at 15 % of its trajectory until the
# console's 600 s timeout, which does not say why (review of session 46). Counting re-starts alone
# (20 in 10 s) aborted campaigns that still progressed on a loaded machine (a stray bridge
# starting on the bus, CI).
# s over which a hold the controller enters from the law's commands (stale states, a fault's latch)
# reaches the hold forces, linearly per cable, as the bridge's own hold does (bridge.node.NodeConfig
# hold_ramp_s); at least HOLD_STEP_MIN_N a tick, so a hold whose α̂ moves still follows it. Within
# the law's 10 N a tick only, the stale hold had stepped 10 and 4.9 N (control test, robot truth,
# law 2: docs/safety/watchdog_handback.py --stale, session 47).
HOLD_RAMP_S = 0.010
HOLD_STEP_MIN_N = 1.0
RESTARTS_WINDOW_S = 10.0
RESTARTS_MIN = 5
PROGRESS_MIN_RATIO = 0.25
# No motor shaft turns faster: an encoder whose reading moved more than this allows between two
# states is faulty (an offset, a runaway) and latches a hold (audit of 2026-11-26: a 60 rad step
# moved α̂ a few degrees and the law drove the real joint to 85°). EC-max 40: about 785 rad/s
# without load (robot_truth.toml); twice that for margin.
MOTOR_SPEED_MAX_RAD_S = 1600.0
# s after the drives come back (first enable, e-stop release, another controller's hand-over)
# before the stuck-encoder check judges again: the bridge's ramp brings the forces back from zero,
# the cables that went slack meanwhile snap taut or stay slack, and the stretch the check predicts
# from the forces is wrong on them (audit of 2026-11-26: −13 mm of parity 60 ms after an e-stop
# release at [35, −25, 20]°; the slack was taken up after about 225 ms). Over this window the
# check measures the slack it then allows (``settling``; controller.encoder_check, "Slack"): a
# moving neck dropped by an e-stop left three cables slack for more than 10 s, which no wait
# covers (audit of 2026-11-28: "encoder 1 or 4 stuck" 0.55 s after the release, 3 runs of 3).
ENCODER_CHECK_SETTLE_S = 0.5
#: s a bridge run's clock must step by to end the running campaign (:meth:`CampaignService.clock_stepped`).
#: Under load a twin's simulated clock and the controller's view of it drift apart and re-bind by
#: up to about half a second (a fresh-clone CI run, 2026-11-27: +0.53 s aborted a healthy campaign
#: under `xneck up`); a clock set by NTP at boot is off by far more.
CLOCK_STEP_ABORT_S = 5.0
BLEND_TOLERANCE_RAD = math.radians(0.05)  # |α̂ − α^d| below which the law re-starts without a blend
JOG_SETTLE_S = 0.2  # s a jog holds its pose before ``finished``: the next jog waits for it
# N/s at which a pretension left over by an aborted campaign is let go (the law's floor and the
# hold's): half the trajectories' bound (controller.trajectory.TrajectoryLimits), so an abort at
# the highest pretension returns to t_min within a couple of seconds, 0.1 N per tick.
PRETENSION_RELEASE_N_S = 50.0
# rad/s² the campaign clock's ramp back to speed may add to α̈^d (α̇ of the trajectory times the
# rate's derivative): half the trajectories' own bound (the trajectory's own α̈ comes on top, scaled
# by the rate squared: 1.6 rad/s² at most on the control test, 3.0 on one built at the limits)
RESUME_ACCELERATION_MAX_RAD_S2 = 1.5
RESUME_DURATION_MIN_S = 0.2  # s: the shortest ramp back to speed

Phase = Literal["idle", "starting", "running", "finished", "aborted"]


@dataclass(frozen=True)
class Event:
    """A campaign event for the shell to publish (a :class:`bridge.bus.CampaignEvent`)."""

    campaign_id: str
    kind: str
    event: bus.CampaignEventKind
    progress: float = 0.0
    message: str = ""
    ticks: int = 0
    overruns: int = 0
    deadline_misses: int = 0


class Output(NamedTuple):
    """What to command for one state, and what to report in the status."""

    force_N: np.ndarray  # (n_cables,) N
    alpha_hat_rad: np.ndarray  # (N,)
    alpha_d_rad: np.ndarray  # (N,)
    e_rad: np.ndarray  # (N,)
    saturated: np.ndarray  # (n_cables,) bool
    law_ran: bool  # False for a hold

#: m of cable at the drums (ρ·|θ|) beyond which a first reading is a run under way, not the
#: calibrated neck of a bridge's start (eq. 20): past the gears' backlash, which a start's reading
#: can show (0.44 rad at the shaft on the robot truth, 0.35 mm of cable), with a margin.
UNDER_WAY_M = 1e-3
#: N of applied force above which a first state is a run under way: a bridge starts with its
#: drives inactive, at zero force.
UNDER_WAY_N = 0.5
#: m of parity (controller.encoder_check) below which a first state under way shows slack, and the
#: take-up it owes ends by reading α̂ again (session 37's audit, robot truth, seeds 0-2): a restart
#: on the slack of an e-stop read −16 mm early in its take-up, −5.3 to −8.1 mm late in it (one
#: cable slack, α̂ 12-22° off; missed at 9 mm, it was still 6-9° off 6 s later); taut joins, at
#: rest or killed at 22-53°/s, −3.1 to +2.4 mm. A false alarm costs about 2° (eq. 33 read at the
#: take-up's peak floor), a miss up to 9°.
SLACK_SEEN_M = 4.0e-3


def _sane(alpha: np.ndarray, limit: float, f: np.ndarray) -> bool:
    """Whether α̂ is finite and within ±``limit`` and the forces are finite: on plain floats, a
    fifth of the cost of numpy's reductions over a few values (20 µs per tick here, issue 21)."""
    return all(abs(a) <= limit for a in alpha.tolist()) and all(map(math.isfinite, f.tolist()))


@dataclass
class CampaignService:
    """The campaign life cycle and the law around one robot (module docstring).

    ``service``: campaigns come as requests (``xneck controller`` without ``--trajectory``); else
    the one campaign given to :meth:`begin` is the process's whole job. ``settle_s``: hold at the
    last waypoint this long before ``finished``.
    """

    params: Params
    law: LawConfig
    service: bool = True
    settle_s: float = 1.0
    campaign_id: str = ""
    kind: str = "control"
    phase: Phase = "idle"
    outcome: str = ""
    hold_reason: str = ""
    latched: bool = False
    latch_reason: str = ""  # why the hold latched (a take-up under the latch says it, then goes back to it)
    overruns: int = 0  # these three count since the campaign started (or the last one ended)
    deadline_misses: int = 0
    ticks: int = 0
    drive: str = "inactive"  # the bridge's drive state in the last state taken
    drive_reason: str = ""  # why, when it is not active (e-stop reason, bridge hold reason)
    trajectory: Trajectory | None = None
    events: list[Event] = field(default_factory=list)
    #: start requests ignored as the start of a campaign already running, prepared or waiting
    duplicate_starts: int = 0
    # m: the stuck-encoder check's threshold (controller.encoder_check, measured on the robot
    # truth; re-measure it on the robot); None turns the check off.
    encoder_threshold_m: float | None = THRESHOLD_M

    def __post_init__(self) -> None:
        self.ctl = ComputedTorque(self.params, self.law)
        # the set and law the service holds with between campaigns (``xneck controller --law``):
        # a campaign's own are taken back when it ends (_end)
        self._home = (self.params, self.law)
        self.encoder_check = self._make_encoder_check()
        n_joints = self.ctl.model.n_joints
        self.last_sane = np.zeros(n_joints)
        self.hold_target = np.zeros(n_joints)
        self._t0, self._total, self._next_progress = 0.0, math.inf, 0.0
        # the campaign clock (campaign_time): stopped at this campaign time while the law
        # re-starts, then back up to speed from (stamp s, campaign time s, duration s)
        self._paused_at: float | None = None
        self._resume: tuple[float, float, float] | None = None
        self._resume_max_s = RESUME_DURATION_MIN_S  # the ramp the trajectory's peak speed needs
        self._restarts: collections.deque[float] = collections.deque()  # stamps (s) of the campaign's re-starts
        self._window = (0.0, 0.0)  # (stamp s, campaign time s) where the progress window began (_stalled)
        self._limit = math.radians(self.params.limits.alpha_max_deg) + DIVERGENCE_MARGIN
        self._restart = False  # the law takes over again at the next active state
        self._drives_off = False  # the drives were off since the law last ran
        # the bridge's drives were active under this service's commands since they were last off: an
        # "inactive" state after that is an e-stop engaged and released between two states seen
        self._enabled = False
        self.pretension_N = 0.0  # the floor added to t_min at the last tick (N, module docstring)
        # N, the floor in force when the running campaign started (a take-up's, an aborted
        # campaign's), let go at PRETENSION_RELEASE_N_S under the trajectory's own pretension
        self._leftover_N = 0.0
        self._blend: tuple[float, np.ndarray, float] | None = None  # (start stamp, α̂ − α^d, duration)
        # (start stamp, α^d₀, α̇^d₀, duration, α̈^d₀) of a stop's brake
        self._brake: tuple[float, np.ndarray, np.ndarray, float, np.ndarray] | None = None
        # the request being prepared: the object itself, since a stopped request's id may be reused
        # by the next one before the stopped one's preparation ends (audit of 2026-11-27)
        self._starting: bus.CampaignRequest | None = None
        self._next_jog: Prepared | None = None  # a jog waiting for the running jog to finish
        self._alpha_max = math.radians(self.params.limits.alpha_max_deg)
        self._theta_last: tuple[float, list[float]] | None = None  # (stamp s, θ rad) of the last state
        self._check_armed_at = math.inf  # the drives have not been active yet (ENCODER_CHECK_SETTLE_S)
        # s of the bridge's watchdog hold summed over its recent holds, and the stamp of the first
        # state of the present run of active ones (None: not active), which clears the sum once it
        # lasts HOLDS_FORGOTTEN_S (a run of short holds re-starts the law as one long one does)
        self._held_s = 0.0
        self._active_since: float | None = None
        self._bridge_held = False  # the bridge's watchdog held since the law last ran with it active
        self._estopped = False  # the drives were disabled (e-stop) since the law last held the neck
        self._take_up: TakeUp | None = None  # the slack an e-stop left being taken up (controller.take_up)
        self._hold_sent: np.ndarray | None = None  # N, the last hold's command (a take-up's rate bound)
        # N a tick per cable of the ramp into a hold entered from the law's commands (HOLD_RAMP_S);
        # ``_from_law``: the last command was the law's, so the next hold starts such a ramp
        self._hold_step_N: np.ndarray | None = None
        self._from_law = False
        # a take-up ended (or was cut short) and the command still moves at most its FORCE_STEP_N a
        # tick, until it meets what the law or the hold asks (``_wind_down_bound``)
        self._wind_down = False
        # the law re-starts from a hold of its own (stale states) that the bridge obeyed: it takes
        # over winding down from it (``control``)
        self._own_hold = False
        # the take-up was for a run joined under way (initialise), not an e-stop this service saw
        self._joined = False
        # α̂ came from a reading of slack cables (a run joined under way whose first parity showed
        # slack, initialise): the take-up ends by re-estimating it from the taut cables
        self._reestimate_when_taut = False
        # the model of eq. 33's stretch (eq. 58 at rest) and of the parity: the parameter file's
        # cables whatever the law's (law 2's rigid eq. 33 started 3-5.5° off on the robot truth)
        self._stretch_model = detector_model(self.params)
        self._own_waiting: Trajectory | None = None  # the process's own campaign, behind a take-up (begin_own)

    # -- outputs to the shell -----------------------------------------------------------------
    def drain_events(self) -> list[Event]:
        out, self.events = self.events, []
        return out

    def _event(self, event: bus.CampaignEventKind, progress: float = 0.0, message: str = "") -> None:
        self.events.append(Event(self.campaign_id, self.kind, event, progress, message,
                                 self.ticks, self.overruns, self.deadline_misses))

    @property
    def running(self) -> bool:
        return self.trajectory is not None

    # -- start-up -----------------------------------------------------------------------------
    def warm_up(self) -> None:
        """One throw-away tick of each kind (the law, the estimate alone as with the drives off,
        the hold) so the first real one does not pay for first calls (LAPACK, numba's cache: a
        kernel loaded inside a tick took 45 ms). :meth:`initialise` starts the estimate afresh."""
        z, zc = np.zeros(self.ctl.model.n_joints), np.zeros(self.ctl.model.n_cables)
        self.ctl.step(zc, z, z, z)
        self.ctl.observe(zc, zc)
        hold_forces(self.params, z)
        alpha_hat_3(self.ctl.model, zc)  # eq. 33: a first state off zero (initialise), a latch's re-estimate

    def initialise(self, theta_rad: np.ndarray, force_N: np.ndarray | None = None) -> None:
        """The first state this service sees of a bridge run: the estimate starts from the encoders'
        absolute reading (eq. 33, with the stretch the state's forces ``force_N`` hold at rest,
        eq. 58), and the service holds there. At a bridge's start the encoders read zero with the
        neck straight (eq. 20), which gives α̂ = 0 as before; a controller restarted while the
        bridge runs meets a bent neck, which it had taken for straight: α̂ 45° off the neck
        45° up (audit of 2026-11-29). A run met under way (beyond ``UNDER_WAY_M`` of cable or
        ``UNDER_WAY_N`` of force) owes a take-up, its cables possibly slack from an e-stop this
        service never saw; with slack seen in the first state (:meth:`_slack_seen`) the take-up
        ends by reading α̂ again (:meth:`_reestimate_taut`). Session 37: restarted 0.3 s into a
        take-up, the cables stayed slack and α̂ 31° off 6 s later (docs/safety.md)."""
        theta = np.asarray(theta_rad, dtype=float)
        model = self.ctl.model
        forces_ok = force_N is not None and bool(np.all(np.isfinite(force_N)))
        f = np.asarray(force_N, dtype=float) if forces_ok else np.zeros(model.n_cables)
        absolute = bool(np.all(np.isfinite(theta))) and (np.any(theta) or np.any(f > 0.0))
        alpha = self._absolute_alpha(theta, f) if absolute else None
        x_c = static_elongation(model, f) if alpha is not None else np.zeros(model.n_cables)
        self.ctl.reset(alpha=alpha, theta=theta)
        self.ctl.estimator.x_c[:] = x_c
        # held within the joint limits, as after a latch's re-estimate: eq. 33 answers any reading
        self.last_sane = np.clip(self.ctl.estimator.alpha_hat, -self._alpha_max, self._alpha_max)
        self.hold_target = self.last_sane.copy()
        self._restart, self._blend, self._brake, self._theta_last = True, None, None, None
        # A run's first enable takes none (the encoders' zero is the calibrated, taut neck), but a
        # run joined under way may have had an e-stop this service never saw, or its take-up cut
        # short (a controller restarted): its cables could be slack, below the motors' stiction,
        # and α̂ from them 12-28° off (session 37). It takes the slack up as after a release.
        self._joined = bool(np.max(f) > UNDER_WAY_N) or bool(
            np.all(np.isfinite(theta)) and model.rho * np.max(np.abs(theta), initial=0.0) > UNDER_WAY_M)
        self._reestimate_when_taut = alpha is not None and self._joined and self._slack_seen(theta, alpha, f)
        self._estopped, self._take_up, self._hold_sent = self._joined, None, None
        self._enabled = False
        self._wind_down = self._own_hold = self._from_law = False
        self._hold_step_N = None
        self._check_armed_at: float | None = math.inf  # stamp from which the stuck-encoder check looks
        if self.encoder_check is not None:
            self.encoder_check.reset()

    def _reestimate(self) -> None:
        """After a latch, α̂ again from the encoders' absolute reading (eq. 33): the incremental
        estimate (eq. 35) kept the divergence, and a new campaign copying it aborted on its first
        tick (audit of 2026-11-26). The forces of the last period stay those sent."""
        if self._theta_last is None:
            return
        stamp, theta = self._theta_last[0], np.array(self._theta_last[1])
        f_sent = self.ctl.f_prev.copy()
        alpha = alpha_hat_3(self.ctl.model, theta)
        if not np.all(np.isfinite(alpha)):
            return
        self.ctl.reset(alpha=alpha, theta=theta, stamp_s=stamp)  # the next gap from that state's stamp
        self.ctl.f_prev[:] = f_sent
        if self.encoder_check is not None:
            self.encoder_check.reset()
        self.last_sane = np.clip(alpha, -self._alpha_max, self._alpha_max)

    def _absolute_alpha(self, theta: np.ndarray, force_N: np.ndarray,
                        guess: np.ndarray | None = None) -> np.ndarray | None:
        """Eq. 33 on the encoders' reading ``theta`` with the stretch ``force_N`` holds at rest
        (eq. 58, on Table 1's variable stiffness whatever the law's cable model: a restarted law 2
        started 3-5.5° off on the robot truth with its rigid cables, 2026-11-29); None if it has
        no finite answer."""
        model = self._stretch_model
        alpha = alpha_hat_3(model, theta, static_elongation(model, force_N), guess=guess)
        return alpha if np.all(np.isfinite(alpha)) else None

    def _take_up_cause(self) -> str:
        return ("the controller started on a bridge run under way, which may have left it" if self._joined
                else "after the e-stop")

    def _slack_seen(self, theta: np.ndarray, alpha: np.ndarray, force_N: np.ndarray) -> bool:
        """The four encoders disagree with eq. 33's α̂ the way slack does: the parity of
        :mod:`controller.encoder_check` below −:data:`SLACK_SEEN_M`."""
        s = float(residuals(self._stretch_model, theta, alpha, force_N)[0])
        return math.isfinite(s) and s < -SLACK_SEEN_M

    def _reestimate_taut(self, theta: np.ndarray, force_N: np.ndarray, stamp_s: float | None = None) -> None:
        """α̂ again from the encoders' absolute reading (eq. 33) with the stretch the forces hold
        at rest (eq. 58), once a take-up has the cables taut and the motors still. A run joined
        under way started α̂ from cables that may have been slack (28° off on the robot truth, the
        restart of session 37), and the incremental estimate (eq. 35) kept that offset after they
        were wound in (12° off 10 s later); taut and still, eq. 33 reads the neck again (3-4° on
        that truth, the law's usual error). The forces sent stay as they were (bumpless)."""
        alpha = self._absolute_alpha(theta, force_N, guess=self.ctl.estimator.alpha_hat)
        self._reestimate_when_taut = False
        if alpha is None:
            return  # the incremental estimate goes on: the hold's divergence checks still watch it
        f_sent = self.ctl.f_prev.copy()
        self.ctl.reset(alpha=alpha, theta=theta, stamp_s=stamp_s)  # the next gap from this state's stamp
        self.ctl.f_prev[:] = f_sent
        self.ctl.estimator.x_c[:] = static_elongation(self.ctl.model, force_N)
        if self.encoder_check is not None:
            self.encoder_check.reset()
        self.last_sane = np.clip(alpha, -self._alpha_max, self._alpha_max)

    def new_bridge_run(self, theta_rad: np.ndarray, stamp_s: float, bridge: str,
                       force_N: np.ndarray | None = None) -> None:
        """The bridge restarted (a new epoch): its clock and encoders start again, so a running
        campaign cannot go on; the estimate starts again from the encoders and the forces its state
        says are applied (:meth:`initialise`: a run met under way holds its cables stretched, and
        without them α̂ was 3-5.5° off and an owed take-up could be skipped; review of session 53)."""
        if self.running:
            self._end("aborted", f"the bridge restarted ({bridge}): the campaign cannot continue",
                      self._progress(stamp_s), self.ctl.estimator.alpha_hat)
        self._drop_waiting(f"the bridge restarted ({bridge})")
        self.initialise(theta_rad, force_N)

    def clock_stepped(self, step_s: float, stamp_s: float) -> None:
        """The bridge's clock stepped by ``step_s`` within one run (a wall clock set by NTP: the
        BeagleBone has no RTC battery), now at ``stamp_s``; a step under :data:`CLOCK_STEP_ABORT_S`
        changes nothing here. The trajectory runs on the states'
        stamps, so a running campaign cannot go on: a step forward had it end ``finished`` at once
        with most of its trajectory never run, a step back kept it going for as long again (audit
        of 2026-11-27). It ends ``aborted`` with the reason; the estimate goes on (same encoders),
        and what was timed on the old clock starts again."""
        # Whatever its size the step is no time that passed: the law's next gap (controller.laws,
        # "Time step") leaves it out, as the take-up's times do.
        self.ctl.clock_stepped(step_s)
        if self._take_up is not None:
            # it goes on, on the new clock: forward, its floor had jumped to the peak and its time
            # limit ended it at once, handing over with 10 N steps (audit of 2026-11-29); a step
            # under CLOCK_STEP_ABORT_S too (review of session 53: +0.3 s took the neck to 62°/s)
            self._take_up.clock_stepped(step_s)
        if self.encoder_check is not None:
            self.encoder_check.clock_stepped(step_s)
        if abs(step_s) < CLOCK_STEP_ABORT_S:
            if self._check_armed_at is not None and math.isfinite(self._check_armed_at):
                self._check_armed_at += step_s  # the settling after the drives came on, on the new clock
            if self._theta_last is not None:
                # The encoders' speed check spans the time that passed, as the law's gap does: a
                # step back after a stall had it measure the stall's motion over no time and abort
                # the campaign ("encoder 4 moved 3.82 rad in 0 ms"; audit of session 44).
                self._theta_last = (self._theta_last[0] + step_s, self._theta_last[1])
            if self._active_since is not None:
                self._active_since += step_s
            return  # a stall's catch-up, not a clock set: the campaign goes on, as before the check
        reason = f"the bridge's clock stepped by {step_s:+.3g} s"
        last_stamp = self._theta_last[0] if self._theta_last is not None else stamp_s
        if self.running:
            self._end("aborted", f"{reason}: the campaign cannot continue", self._progress(last_stamp),
                      self.ctl.estimator.alpha_hat)
        self._drop_waiting(reason)
        self._theta_last = self._active_since = None
        self._held_s = 0.0
        if self._check_armed_at is not None and math.isfinite(self._check_armed_at):
            self._check_armed_at = stamp_s + ENCODER_CHECK_SETTLE_S
        self._restart = True  # the law re-starts from the measurement, bumplessly

    # -- campaigns ----------------------------------------------------------------------------
    def begin_own(self, trajectory: Trajectory, stamp_s: float) -> None:
        """The process's own campaign (``xneck controller --trajectory``, controller/process.py),
        from its first state: at once on a bridge's fresh run; on a run joined under way, after the
        take-up it owes, approaching the first waypoint from α̂ then (:meth:`advance`). Begun at once,
        it had run its trajectory on the slack of an e-stop: the neck past 60°, α̂ 18° off at its
        ``finished`` (session 37's audit)."""
        if self._joined and self._estopped:
            self._own_waiting = trajectory
            return
        self.begin(trajectory, stamp_s)

    def begin(self, trajectory: Trajectory, stamp_s: float) -> None:
        """Run ``trajectory`` from ``stamp_s`` (the states' clock) on; the counters start at zero."""
        self.trajectory = trajectory
        self.phase = "running"
        self._restarts.clear()
        self._window = (stamp_s, 0.0)  # (stamp s, campaign time s) where the progress window began
        self._t0 = stamp_s
        self._paused_at = self._resume = None
        peak_rad_s = float(np.max(trajectory.segment_peak_velocity(), initial=0.0))
        self._resume_max_s = max(RESUME_DURATION_MIN_S, 2.0 * peak_rad_s / RESUME_ACCELERATION_MAX_RAD_S2)
        self._total = trajectory.duration_s + (JOG_SETTLE_S if self.kind == "jog" else self.settle_s)
        self._next_progress = 0.0
        self.outcome = ""
        self._leftover_N = self.pretension_N  # let go under the trajectory's (``_pretension``)
        self._lift_latch()
        self.ticks = self.overruns = self.deadline_misses = 0
        self._blend = self._brake = None
        self._event("started", message=f"{self.law.name}, trajectory {trajectory.name}")

    def _lift_latch(self) -> None:
        """A new campaign lifts a latched hold: α̂ again from the encoders (:meth:`_reestimate`)."""
        if self.latched:
            self._reestimate()
            self._restart = True  # the law takes over from the new estimate, bumplessly
            # from the latch's hold, which the bridge obeyed: the law's first commands wind down
            # from it at the take-up's 1 N a tick, as after its own stale hold (a campaign asked for
            # within 20 ms of a latch had the law take over at 10 N a tick, transition_fuzz.py)
            self._own_hold = True
            if self.drive == "active":
                # and whatever came before the latch's hold (drives off, a bridge hold, both of which
                # skip that wind-down): it is what the bridge applies now (review of session 47: an
                # e-stop under the latch, then a campaign, 4.4 N a tick)
                self._wind_down = True
        self.latched, self.latch_reason = False, ""

    def _end(self, outcome: Literal["finished", "aborted"], message: str, progress: float, hold_at: np.ndarray) -> None:
        self.outcome = outcome
        self.phase = outcome
        self._event(outcome, progress, message)
        self.trajectory = None
        self._paused_at = self._resume = None
        if outcome != "finished":  # held where it is; a finished one holds its last waypoint, blend and all
            self._blend = None
        self.hold_target = np.array(hold_at, dtype=float)
        self.ticks = self.overruns = self.deadline_misses = 0
        if self.service and self.kind != "jog":
            self._go_home()
        waiting, self._next_jog = self._next_jog, None
        if waiting is not None and outcome != "finished":
            self.refuse(waiting.campaign_id, waiting.kind, f"dropped: jog {self.campaign_id} ended {outcome} ({message})")
        elif waiting is not None:
            self._next_jog = waiting  # started by advance() once this one has ended
        starting = self._starting
        if starting is not None and outcome != "finished" and self.kind == "jog":
            # Being prepared behind this jog: its approach is validated from this jog's target
            # (start_pose), where the neck will not be (review of session 40).
            self.refuse(starting.campaign_id, starting.kind, f"dropped: jog {self.campaign_id} ended {outcome} "
                                                             f"({message}) before it reached the pose its approach was checked from")
            self._starting = None

    def _stalled(self, stamp_s: float, t: float) -> bool:
        """Whether the running campaign was just aborted for making no progress while its law kept
        re-starting (:data:`RESTARTS_WINDOW_S`); checked once a window, on the states' clock."""
        since_s, since_t = self._window
        if stamp_s - since_s < RESTARTS_WINDOW_S:
            return False
        restarts = self._restarts
        while restarts and stamp_s - restarts[0] > stamp_s - since_s:
            restarts.popleft()
        n, advanced_s = len(restarts), t - since_t
        self._window = (stamp_s, t)
        restarts.clear()
        if n < RESTARTS_MIN or advanced_s >= PROGRESS_MIN_RATIO * (stamp_s - since_s):
            return False
        self._end("aborted", f"the law re-started {n} times in {stamp_s - since_s:.0f} s (the bridge's holds or stale "
                             f"states: the commands come late or the states stall), each stopping the campaign's clock: "
                             f"it advanced {advanced_s:.1f} s of its trajectory meanwhile",
                  self._progress(stamp_s), self.hold_alpha())
        return True

    def _progress(self, stamp_s: float) -> float:
        return min(max(self.campaign_time(stamp_s)[0] / self._total, 0.0), 1.0)

    def stop(self, campaign_id: str, stamp_s: float) -> None:
        """A stop request: aborts the campaign ``campaign_id`` if it runs or is being prepared."""
        if self._next_jog is not None and self._next_jog.campaign_id == campaign_id:
            self.refuse(campaign_id, self._next_jog.kind, "stopped by the user before it started")
            self._next_jog = None
        elif self.running and campaign_id == self.campaign_id:
            brake = self._brake_from(stamp_s)
            self._end("aborted", "stopped by the user", self._progress(stamp_s), self.ctl.estimator.alpha_hat)
            if brake is not None:
                end_s = max(brake[3], release_duration_s(brake[4]))
                self._brake, self.hold_target = brake, brake_at(brake[1], brake[2], brake[3], end_s, brake[4])[0]
        elif self._starting is not None and self._starting.campaign_id == campaign_id:
            self.refuse(campaign_id, self._starting.kind, "stopped by the user before it started")
            self._starting, self.phase = None, self._phase_beside()

    def stoppable(self) -> frozenset[str]:
        """The campaign ids a stop request may concern now (:meth:`stop`): the running campaign,
        the one being prepared, the one waiting to start. The shell keeps stops of these only, so
        a flood of stops of other ids takes no room (:mod:`controller.process`)."""
        ids = {self._next_jog.campaign_id if self._next_jog is not None else "",
               self._starting.campaign_id if self._starting is not None else "",
               self.campaign_id if self.running else ""}
        return frozenset(ids - {""})

    def wants(self, req: bus.CampaignRequest) -> bool:
        """Whether the preparation of request ``req`` is still worth finishing: it is the very
        request being prepared, not stopped or superseded meanwhile (:meth:`prepared` would drop
        its result). One attribute read: the shell's worker asks it without the tick lock."""
        return self._starting is req

    def start_pose(self) -> np.ndarray | None:
        """Where a campaign asked for now would start (rad): the last waypoint of the running
        jog (a jog waits for it and starts there), where a stop's brake brings α^d to rest, else
        α̂; None while the slack of an e-stop is being taken up: α̂ is off by the slack (5-13°,
        docs/safety.md "After an e-stop") until the take-up has wound it in, and the campaign
        waits for it anyway. Read by the shell's worker without the tick lock, to validate the
        approach (:func:`controller.prepare.approach_move`, :func:`controller.prepare.start_pose_when_known`)."""
        traj, brake = self.trajectory, self._brake
        if self.running and self.kind == "jog" and traj is not None:
            return np.array(traj.waypoints_rad[-1], dtype=np.float64)
        if self.taking_up:
            return None
        if brake is not None:
            return np.array(self.hold_target, dtype=np.float64)
        return np.array(self.ctl.estimator.alpha_hat, dtype=np.float64)

    def _brake_from(self, stamp_s: float) -> tuple[float, np.ndarray, np.ndarray, float, np.ndarray] | None:
        """A controlled stop from where α^d is at ``stamp_s`` (:func:`controller.trajectory.brake_at`),
        while the law tracks it (drives active, no hold, no re-start due); ``None`` otherwise (the
        hold at α̂ then applies, bounded by the law's force rate)."""
        if self.latched or self._restart or self.drive != "active" or self.hold_reason:
            return None
        a_d, a_d_dot, a_d_ddot = (np.array(x, dtype=float) for x in self.reference(stamp_s))
        a_d_ddot = np.clip(a_d_ddot, -BRAKE_RELEASE_ACCELERATION_MAX_RAD_S2, BRAKE_RELEASE_ACCELERATION_MAX_RAD_S2)
        return stamp_s, a_d, a_d_dot, brake_duration_s(a_d, a_d_dot, self._alpha_max, a_d_ddot), a_d_ddot

    def _drop_waiting(self, reason: str) -> None:
        """Answer the campaign waiting for the brake to end (none waits behind a running one
        here: :meth:`_end` answers those) and give the brake up: ``reason`` ends it."""
        self._brake = None
        if self._next_jog is not None and not self.running:
            waiting, self._next_jog = self._next_jog, None
            self.refuse(waiting.campaign_id, waiting.kind, f"dropped before it started: {reason}")
        if self._own_waiting is not None:
            self._own_waiting = None
            self._end("aborted", f"dropped before it started: {reason}", 0.0, self.hold_alpha())

    @property
    def taking_up(self) -> bool:
        """The slack an e-stop left is (to be) taken up before the law holds the neck again."""
        return self._take_up is not None or (self._estopped and self.drive != "disabled"
                                             and (self._drives_off or self._joined))

    @property
    def braking(self) -> bool:
        """α^d is still coming to rest after a stop (:meth:`stop`)."""
        return self._brake is not None

    def refuse(self, campaign_id: str, kind: str, message: str) -> None:
        """Answer a request the service will not run with an ``aborted`` event of its id."""
        self.events.append(Event(campaign_id, kind, "aborted", 0.0, message))

    def busy_reason(self, kind: str = "") -> str:
        """Why a new campaign of ``kind`` cannot start now ("" if it can); a jog may follow a
        running jog (module docstring)."""
        if self.running and not (kind == "jog" and self.kind == "jog"):
            return f"the controller is running campaign {self.campaign_id}"
        if self._starting is not None:
            return f"the controller is preparing campaign {self._starting.campaign_id}"
        if self.drive == "disabled":
            return f"drives disabled ({self.drive_reason or 'e-stop'}): release the e-stop first"
        return ""  # a latched hold too: a new campaign is how it is lifted

    def request_start(self, req: bus.CampaignRequest) -> bool:
        """A start request arrived: True if it is to be prepared (the service is ``starting``);
        otherwise it was refused with the reason. During a take-up the request being prepared
        waits for the pose it will start from (:meth:`start_pose`), seconds maybe: a newer one
        supersedes it, the newest only, as behind a stop's brake (a slider dragged on right
        after a release had ended at its first position: review of session 41).

        A start of a campaign that runs, is being prepared or waits (the same request delivered
        twice, or re-published by another peer) is ignored and counted (``duplicate_starts``):
        refused, its ``aborted`` event under the campaign's own id had ended the campaign on the
        console, which then sent no stop while this service ran it on (review of session 53)."""
        if req.campaign_id in self.stoppable():
            self.duplicate_starts += 1
            return False
        waiting = self._starting
        if waiting is not None and self.taking_up and not self.running:
            self._starting = None  # busy_reason without it
            busy = self.busy_reason(req.kind)
            if busy:
                self._starting = waiting
                self.refuse(req.campaign_id, req.kind, f"refused: {busy}")
                return False
            self.refuse(waiting.campaign_id, waiting.kind, f"superseded by {req.campaign_id} (asked for while the "
                                                           "cables' slack was taken up)")
            self._starting, self.phase = req, self._phase_beside("starting")
            return True
        busy = self.busy_reason(req.kind)
        if busy:
            self.refuse(req.campaign_id, req.kind, f"refused: {busy}")
            return False
        self._starting, self.phase = req, self._phase_beside("starting")
        return True

    def _phase_beside(self, otherwise: Phase = "idle") -> Phase:
        """The phase while a request is prepared or after it: the running campaign's, if one runs
        (a jog asked for during a jog waits for it; the status had said ``idle`` meanwhile,
        transition_fuzz2.py, session 47), else ``otherwise``."""
        return "running" if self.running else otherwise

    def prepared(self, result: Prepared | Refused, req: bus.CampaignRequest, stamp_s: float) -> None:
        """The preparation of request ``req`` ended: start it, or pass the refusal on. Dropped if
        that request was stopped meanwhile (it was answered then), even when a later request
        with the same id is being prepared now: only the very request prepared may start."""
        if self._starting is not req:
            return
        self._starting, self.phase = None, self._phase_beside()
        if isinstance(result, Refused):
            self.refuse(req.campaign_id, req.kind, result.reason)
            return
        self.start(result, stamp_s)

    def start(self, prepared: Prepared, stamp_s: float) -> None:
        """Start a prepared campaign, approaching its first waypoint gently from α̂ (a jog asked
        for while a jog runs waits for it: module docstring)."""
        busy = self.busy_reason(prepared.kind)
        if not busy and self.running:
            if self._next_jog is not None:
                self.refuse(self._next_jog.campaign_id, "jog", f"superseded by jog {prepared.campaign_id}")
            self._next_jog = prepared
            return
        if busy:
            self.refuse(prepared.campaign_id, prepared.kind, f"refused: {busy}")
            return
        if self.latched and self._estopped:
            # The e-stop's release found the hold latched, and the take-up it owes waited for the
            # latch: every campaign waited for it forever (audit of 2026-11-29). This one lifts the
            # latch now, and starts after the take-up.
            self._lift_latch()
        if self._brake is not None or self.taking_up:
            # α^d is still coming to rest after a stop, or the slack of an e-stop is being taken
            # up: the campaign starts from where the neck then rests (advance()), as a jog waits
            # for the running one, the newest one only.
            if self._next_jog is not None:
                self.refuse(self._next_jog.campaign_id, self._next_jog.kind, f"superseded by {prepared.campaign_id}")
            self._next_jog = prepared
            return
        self.campaign_id, self.kind = prepared.campaign_id, prepared.kind
        start_at = self.ctl.estimator.alpha_hat
        # Bumpless: the law, its integral and α^d go on; the move starts where α^d rests (α̂ while
        # the law is not running or re-starting). A campaign as a jog: from an idle hold on the
        # robot truth, starting at α̂ with a fresh integral stepped the forces 10 N a tick for
        # several ticks (audit of 2026-11-28).
        if not self._restart and self._blend is None and self.drive == "active":
            start_at = self.reference(stamp_s)[0]
        if prepared.kind != "jog":
            old_limits, old_law = self.params.limits, self.law
            self.params = prepared.params
            self._switch_law(prepared.law)
            if self.drive == "active" and (prepared.params.limits != old_limits or prepared.law != old_law):
                # Another floor (t_min, f_min) or law starts from the last command at the
                # take-up's 1 N a tick: a set raising t_min stepped 10 N a tick for 2 ticks, law
                # 2 → 3 one tick of 7 N (its stretch estimate starts anew; audit of session 43).
                self._wind_down = True
        self.begin(approach(prepared.trajectory, start_at), stamp_s)

    def handle(self, req: bus.CampaignRequest, stamp_s: float) -> None:
        """A campaign request, prepared here and now (tests; the process prepares off its loop)."""
        if req.action == "stop":
            self.stop(req.campaign_id, stamp_s)
            return
        if not self.request_start(req):
            return
        try:
            result: Prepared | Refused = prepare(req, self.params, self.law)
        except Refused as exc:
            result = exc
        self.prepared(result, req, stamp_s)

    def _go_home(self) -> None:
        """Hold with the service's own set and law again once a campaign that brought its own
        ended (user audit of session 46: after an identification the stack held, and jogged, with
        law 1 until the next campaign of another law), from the last command at the take-up's
        1 N a tick, as a campaign's own law starts."""
        params, law = self._home
        if params is self.params and law == self.law:
            return
        old_limits, old_law = self.params.limits, self.law
        self.params = params
        self._switch_law(law)
        if self.drive == "active" and (params.limits != old_limits or law != old_law):
            self._wind_down = True

    def _switch_law(self, law: LawConfig) -> None:
        """A new law continues from the current estimate (α̂, θ and, when both models are
        elastic, the predicted stretch), its filtered velocities and its integral's share of the
        command (ki·∫e, eq. 59): a fresh integral dropped what held the neck against what the
        model does not know, a force step at every campaign start (audit of 2026-11-28)."""
        old, old_ctl = self.ctl.estimator, self.ctl
        ctl = ComputedTorque(self.params, law)
        ctl.reset(alpha=old.alpha_hat, theta=old.theta, stamp_s=old_ctl.stamp_s)  # the next gap from the same state
        if ctl.model.cable_model == old_ctl.model.cable_model:
            ctl.estimator.x_c = old.x_c.copy()
        ctl.theta_dot = old_ctl.theta_dot.copy()
        ctl.alpha_hat_dot = old_ctl.alpha_hat_dot.copy()
        ctl.integral = old_ctl.integral * (old_ctl.ki / ctl.ki)
        ctl.f_prev = old_ctl.f_prev.copy()
        self.ctl, self.law = ctl, law
        if self.encoder_check is not None and self._encoder_check_params is not self.params:
            old_check = self.encoder_check
            self.encoder_check = self._make_encoder_check()  # the new set's geometry (< 1 ms once loaded)
            if self.encoder_check is not None:
                self.encoder_check.keep_slack(old_check)  # the same cables, slack and all
        self._alpha_max = math.radians(self.params.limits.alpha_max_deg)
        self._limit = self._alpha_max + DIVERGENCE_MARGIN

    # -- one tick -----------------------------------------------------------------------------
    def hold_alpha(self) -> np.ndarray:
        """α̂, or the last sane α̂ when the estimate is not (non-finite or beyond the joint limits);
        never beyond ±alpha_max (the bridge's own hold clips there too)."""
        alpha = self.ctl.estimator.alpha_hat
        if self.latched or not np.all(np.isfinite(alpha)) or np.any(np.abs(alpha) > self._alpha_max):
            return np.clip(self.last_sane, -self._alpha_max, self._alpha_max)
        return alpha

    def hold(self, reason: str) -> Output:
        """The forces that hold the neck still where it is (module docstring), with ``reason``.
        While the bridge obeys (it passes commands through), they keep the law's force rate from
        what was last sent, and the law resumes from what was sent (audit of 2026-11-26: a stale
        gap's hold stepped 21.9 N in one tick, and the law's return another 21.9 N). During a
        take-up (:mod:`controller.take_up`) they carry its floor and motor damping, within its
        tighter bound per tick, whatever the hold is for (a stale gap's too). Entered from the
        law's commands, they reach the hold linearly over ``HOLD_RAMP_S``, as the bridge's hold."""
        self.hold_reason = reason
        alpha = self.hold_alpha().copy()  # the law's α̂ changes in place at its next tick
        f = hold_forces(self.params, alpha, self._pretension(None))
        step = self.law.force_rate_max_N_s * self.ctl.dt
        if self._take_up is not None:
            f = np.clip(f + self._take_up.damping_N, self.params.limits.f_min, self.params.limits.f_max)
            step = min(step, take_up_rules.FORCE_STEP_N)
        if self.drive in ("active", "hold"):  # a command ends the bridge's hold, which ramps to it
            f_prev = self.ctl.f_prev
            if self._from_law:
                ticks = max(1, round(HOLD_RAMP_S / self.ctl.dt))
                self._hold_step_N = np.maximum(np.abs(f - f_prev) / ticks, HOLD_STEP_MIN_N)
            if self._take_up is None and self._hold_step_N is not None:
                step = np.minimum(step, self._hold_step_N)
            f = self._wind_down_bound(f, f_prev) if self._wind_down else np.clip(f, f_prev - step, f_prev + step)
            f_prev[:] = f
        self._hold_sent, self._from_law = f, False
        zeros = np.zeros_like(alpha)
        return Output(f, alpha, alpha, zeros, np.zeros(len(f), dtype=bool), False)

    def _wind_down_bound(self, f: np.ndarray, sent: np.ndarray) -> np.ndarray:
        """``f`` within the take-up's ``FORCE_STEP_N`` of ``sent`` (the last command) while a take-up
        winds down (ended, or cut short by a latch), which it does until ``f`` is met within that
        step: the damping and the command's lag are let go at the take-up's rate, never at the
        law's (10 N a tick)."""
        step = take_up_rules.FORCE_STEP_N
        if float(np.max(np.abs(f - sent))) <= step:
            self._wind_down = False
            return f
        return np.clip(f, sent - step, sent + step)

    def _make_encoder_check(self) -> EncoderConsistency | None:
        if self.encoder_threshold_m is None:
            return None
        self._encoder_check_params = self.params  # which set it was built for (a campaign may bring another)
        return EncoderConsistency(self.params, self.encoder_threshold_m)

    def _check_phase(self, active: bool, stamp_s: float) -> tuple[bool, bool]:
        """(judged, settling) for this state: the stuck-encoder check judges it with the drives
        active, except for ``ENCODER_CHECK_SETTLE_S`` after they came back (first enable, e-stop
        release, hand-over, a bridge hold), over which it measures the slack the cables were left
        with (``settling``) instead."""
        if not active:
            self._check_armed_at = math.inf
            return False, False
        if self._check_armed_at is None:
            return True, False
        if self._check_armed_at == math.inf:
            self._check_armed_at = stamp_s + ENCODER_CHECK_SETTLE_S
        if stamp_s < self._check_armed_at:
            return False, True
        self._check_armed_at = None
        return True, False

    def _encoder_fault(self, theta_rad: np.ndarray, stamp_s: float, force_applied_N: np.ndarray | None = None,
                       active: bool = True, settling: bool = False) -> str:
        """Why the encoders cannot be right ("" if they can): one moved more than a motor turns in
        the time since the last state (``MOTOR_SPEED_MAX_RAD_S``), or the four disagree with α̂
        beyond what the cables' stretch, friction and the slack left when the drives came back
        explain, for long enough: one is stuck (:mod:`controller.encoder_check`, while the drives
        are ``active`` only; ``settling``: :meth:`_check_phase`)."""
        last, theta = self._theta_last, [float(x) for x in theta_rad]
        self._theta_last = (stamp_s, theta)
        if last is not None:
            allowed = MOTOR_SPEED_MAX_RAD_S * max(stamp_s - last[0], self.ctl.dt)
            for j, (a, b) in enumerate(zip(last[1], theta, strict=True)):
                if not abs(b - a) <= allowed:  # also for a NaN
                    return (f"encoder {j + 1} moved {b - a:.3g} rad in {max(stamp_s - last[0], 0.0) * 1e3:.0f} ms, "
                            f"more than a motor turns ({MOTOR_SPEED_MAX_RAD_S:g} rad/s): encoder fault")
        if self.encoder_check is None:
            return ""
        ctl = self.ctl
        force = ctl.f_prev if force_applied_N is None else force_applied_N  # what acted over the last period
        return self.encoder_check.update(theta_rad, ctl.estimator.alpha_hat, force, ctl.theta_dot, stamp_s,
                                         active=active and not self.latched, settling=settling and not self.latched)

    def _pretension(self, stamp_s: float | None) -> float:
        """The floor added to t_min this tick (N): the running trajectory's pretension at
        ``stamp_s`` (``None``: a hold within the campaign keeps the last one, so the law resumes
        where it was), else, with no campaign, the last one let go at ``PRETENSION_RELEASE_N_S``.
        A campaign that starts on a raised floor (a take-up's, an aborted campaign's) lets it go
        at that rate too, under its own pretension: dropping it to the trajectory's stepped the
        forces by 10 N a tick for three ticks (audit of 2026-11-29)."""
        if self.trajectory is not None:
            if stamp_s is not None:
                self._leftover_N = max(0.0, self._leftover_N - PRETENSION_RELEASE_N_S * self.ctl.dt)
                self.pretension_N = max(self.trajectory.pretension_at(self.campaign_time(stamp_s)[0]),
                                        self._leftover_N)
        elif self._take_up is not None:
            self.pretension_N = self._take_up.level_N
        elif self.pretension_N > 0.0:
            self.pretension_N = max(0.0, self.pretension_N - PRETENSION_RELEASE_N_S * self.ctl.dt)
        return self.pretension_N

    def stale(self, reason: str, stale_for_s: float) -> Output:
        """No new state for ``stale_for_s``: hold; after a gap of ``STALE_RESTART_S`` (any the
        process holds for) the law re-starts from the measurement when states return."""
        if stale_for_s >= STALE_RESTART_S:
            self._restart = self._own_hold = True
            if self._theta_last is not None:
                self._pause(self._theta_last[0])
        return self.hold(reason)

    def campaign_time(self, stamp_s: float) -> tuple[float, float, float]:
        """The running campaign's clock at ``stamp_s`` (the states' clock): its time t (s, 0 at the
        start), rate dt/ds and the rate's derivative (1/s). It runs with the states' clock, except
        that it stops while the law re-starts and, from the take-over, comes back up to speed over
        :meth:`resume_duration_s`: rate = s(x), the cycloid of x = (stamp − take-over)/duration, so
        t = t_paused + duration·∫₀ˣ s = t_paused + duration·(x²/2 + (cos 2πx − 1)/4π²), and past
        the ramp it lags the states' clock by the time held plus half the ramp."""
        if self._paused_at is not None:
            return self._paused_at, 0.0, 0.0
        if self._resume is not None:
            start_s, paused_t, duration_s = self._resume
            x = (stamp_s - start_s) / duration_s
            if x < 1.0:
                x = max(x, 0.0)
                s, ds, _ = cycloid_at(x)
                integral = 0.5 * x * x + (math.cos(2.0 * math.pi * x) - 1.0) / (4.0 * math.pi**2)
                return paused_t + duration_s * integral, s, ds / duration_s
            return stamp_s - (start_s + 0.5 * duration_s - paused_t), 1.0, 0.0
        return stamp_s - self._t0, 1.0, 0.0

    def resume_duration_s(self, paused_t: float) -> float:
        """s over which the campaign clock stopped at ``paused_t`` (campaign time, s) comes back to
        speed: 0 where the trajectory rests there (α̇^d = α̈^d = 0: a dwell, its start; resuming
        at once is bumpless), else long enough that the rate's rise adds at most
        ``RESUME_ACCELERATION_MAX_RAD_S2`` (2·v/T with v the largest speed over the half ramp the
        clock covers meanwhile), at least ``RESUME_DURATION_MIN_S``. The trajectory's start
        (pausing while the drives are inactive at a first enable) had waited 0.58 s for a ramp
        over its dwell."""
        traj = self.trajectory
        if traj is None:
            return 0.0
        _a, v0, a0 = traj.sample_at(paused_t)
        if float(np.max(np.abs(v0))) < 1e-9 and float(np.max(np.abs(a0))) < 1e-9:
            return 0.0
        duration_s = self._resume_max_s
        for _ in range(3):  # shorter while the speed over the half ramp allows (never longer)
            window = traj.sample(np.linspace(paused_t, min(paused_t + duration_s / 2, traj.duration_s), 25))
            v = float(np.max(np.abs(window.alpha_dot)))
            duration_s = max(RESUME_DURATION_MIN_S, min(duration_s, 2.0 * v / RESUME_ACCELERATION_MAX_RAD_S2))
        return duration_s

    def _pause(self, stamp_s: float) -> None:
        """Stop the running campaign's clock at ``stamp_s`` until the law takes over again."""
        if self.trajectory is not None and self._paused_at is None:
            self._paused_at = self.campaign_time(stamp_s)[0]

    def reference(self, stamp_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """α^d, α̇^d, α̈^d at ``stamp_s``: the campaign's trajectory or the hold target, plus the
        re-start blend while it lasts: (α̂₀ − α^d₀)(1 − s(τ)) with the cycloid s over the blend's
        duration, so α^d starts at α̂ and joins the trajectory at rest relative to it. (α̇^d is the
        trajectory's from the start: the k_v term then damps whatever motion the neck has, rather
        than following an α̂̇ that is mostly the jolt of the drives coming back.)"""
        if self.trajectory is not None:
            t, rate, rate_dot = self.campaign_time(stamp_s)
            a_d, a_d_dot, a_d_ddot = self.trajectory.sample_at(t)
            if rate != 1.0:  # d/dt of α(τ(t)): α' τ̇ and α'' τ̇² + α' τ̈
                a_d_ddot = a_d_ddot * rate**2 + a_d_dot * rate_dot
                a_d_dot = a_d_dot * rate
        elif self._brake is not None:
            start_s, a0, v0, duration_s, acc0 = self._brake
            if stamp_s - start_s >= max(duration_s, release_duration_s(acc0)):
                self._brake = None
                a_d = self.hold_target
                a_d_dot = a_d_ddot = np.zeros_like(a_d)
            else:
                a_d, a_d_dot, a_d_ddot = brake_at(a0, v0, duration_s, stamp_s - start_s, acc0)
        else:
            a_d = self.hold_target
            a_d_dot = a_d_ddot = np.zeros_like(a_d)
        if self._blend is not None:
            start_s, offset, duration_s = self._blend
            tau = (stamp_s - start_s) / duration_s
            if tau >= 1.0:
                self._blend = None
            else:
                s, ds, dds = cycloid_at(tau)
                a_d = a_d + offset * (1.0 - s)
                a_d_dot = a_d_dot - offset * (ds / duration_s)
                a_d_ddot = a_d_ddot - offset * (dds / duration_s**2)
        return a_d, a_d_dot, a_d_ddot

    def _take_over(self, stamp_s: float) -> None:
        """The law re-starts from the measured state: fresh integral, α^d from α̂ (module docstring)."""
        self._restart = False
        self.ctl.restart_integral()
        if self.running:
            self._restarts.append(stamp_s)
        if self._paused_at is not None:
            duration_s = self.resume_duration_s(self._paused_at)
            if duration_s > 0.0:
                self._resume = (stamp_s, self._paused_at, duration_s)
            else:  # at rest there: the clock goes on at once, from where it stopped
                self._t0, self._resume = stamp_s - self._paused_at, None
            self._paused_at = None
        alpha_hat = self.hold_alpha()
        brake, self._blend, self._brake = self._brake, None, None
        drives_were_off, self._drives_off = self._drives_off, False
        if brake is not None and not drives_were_off:
            # A stop's brake through a re-start (a watchdog hold, stale states) ends there: the law
            # holds the neck where it finds it. The brake had gone on, on the states' clock, while
            # the hold stopped the neck, and the law took over asking 50°/s of a neck at 3°/s: it
            # reached 104-183°/s (review of session 46); planned again from α̂ and α̂̇ (the jolt of
            # the drives coming back), still 94°/s after a 20 ms loss. Held at α̂: at most 52°/s.
            # (Dropping it had set α^d to α̂ at rest with a force step, audit of 2026-11-26, before
            # the take-over took its rate bound from the forces applied.)
            self._cut_brake(alpha_hat)
            return
        elif not self.running and (drives_were_off or self.kind != "jog" or self.outcome != "finished"):
            self.hold_target = alpha_hat.copy()
            return
        # A finished jog's pose is where the operator put the neck: a stall of the states does not
        # move it (after the drives were off the neck stays where it is, above).
        offset = alpha_hat - self.reference(stamp_s)[0]
        delta = float(np.max(np.abs(offset)))
        if delta > BLEND_TOLERANCE_RAD:
            self._blend = (stamp_s, offset, approach_duration_s(delta))

    def _cut_brake(self, alpha_hat: np.ndarray) -> None:
        """Hold at α̂ instead of a stop's brake (:meth:`_take_over`); a jog waiting for the brake
        was checked from where it would have ended: it is dropped."""
        self.hold_target = np.array(alpha_hat, dtype=float)
        if self._next_jog is not None and not self.running:
            waiting, self._next_jog = self._next_jog, None
            self.refuse(waiting.campaign_id, waiting.kind, "dropped before it started: a hold cut short the stop's "
                                                           "brake it waited for, the neck is held elsewhere: ask again")

    def control(self, theta_rad: np.ndarray, stamp_s: float, drive: str = "active",
                force_applied_N: np.ndarray | None = None, obeyed: bool = True) -> Output:
        """One tick on a new state: encoders θ at ``stamp_s``, the bridge's ``drive`` state and the
        forces it applies. A diverging estimate (non-finite, or beyond the joint limit plus a
        margin) latches a hold and aborts the campaign; drives that are not active get the hold
        forces at α̂ and the law re-starts bumplessly when they are (module docstring).
        ``obeyed``: False while the bridge obeys another controller (its state's ``owner``): this
        one only observes, as with the drives off (a law running on refused commands winds its
        integral up, and its first admitted command was a 91.5 N step: audit of 2026-11-26), and a
        campaign it runs is aborted."""
        self.ticks += 1
        self.drive = drive
        gap_s = max(stamp_s - self._theta_last[0], 0.0) if self._theta_last is not None else 0.0
        fault = self._encoder_fault(theta_rad, stamp_s, force_applied_N,
                                    *self._check_phase(drive == "active" and obeyed, stamp_s))
        if fault and not self.latched:
            self.latched, self.latch_reason = True, fault
            self._drop_waiting(fault)
            out = self.hold(fault)
            if self.running or (not self.service and not self.outcome):  # not ended by _drop_waiting
                self._end("aborted", fault, self._progress(stamp_s) if self.running else 0.0, self.hold_alpha())
            return out
        estop_seen = drive == "disabled"  # whoever the bridge obeys: the neck falls all the same
        if not obeyed:
            drive = "inactive"
        elif drive == "inactive" and self._enabled:
            # Drives inactive after they were active under our commands: only an e-stop's release
            # leaves them so (bridge.safety), engaged and released while no state reached this
            # service (a stale gap). The neck fell meanwhile: as after a seen e-stop, the campaign
            # is aborted and the slack taken up (it had run on, and no take-up, transition_fuzz.py).
            drive, estop_seen = "disabled", True
            self.drive_reason = ("an e-stop was engaged and released while no state reached the controller "
                                 "(the drives came back inactive)")
        if drive == "active":
            self._enabled = True
        elif estop_seen:
            self._enabled = False
        if drive == "active":
            if self._active_since is None:
                self._active_since = stamp_s
            if stamp_s - self._active_since >= HOLDS_FORGOTTEN_S:
                self._held_s = 0.0
        else:
            self._active_since = None
        if drive == "hold":
            # The bridge's watchdog holds because our commands came late: the next one ends the
            # hold (the bridge ramps to it), so the law keeps running (a hold command here would be
            # one more step), its integral frozen (below). After holds of more than a period
            # (HOLD_RESTART_S) it re-starts from the measurement once the bridge obeys again; after
            # one tick it goes on (re-starting had stepped the commands 8.6 N a tick, 2026-11-26,
            # before the take-over took its rate bound from the forces applied; now under 2 N).
            # The hold time is summed until the bridge obeys for HOLDS_FORGOTTEN_S on end: a
            # starved controller (40 ms stopped, 8 ms running) made the bridge flap hold/active
            # every 50 ms, no single hold lasted 0.1 s (the threshold then), the law ran on while the neck was
            # held and its commands climbed to f_max; at the hand-back the neck reached 217-378°/s
            # and α 71.9° (audit of session 43).
            self._held_s += gap_s
            self._bridge_held = True
            if self._held_s >= HOLD_RESTART_S:
                self._restart = True
                self._pause(stamp_s)
            if self._restart and self._take_up is None and not (self._joined and self._estopped and not self.running):
                # Re-starting: α̂ follows the encoders and the forces applied, as with the drives off,
                # and the command is the hold at α̂ (the bridge's own), within the law's rate of the
                # last command (as in a take-up): the law's command at the last hold tick had ended
                # the hold, and the bridge ramped to it (100 N on a cable) before the law took over
                # (audit of session 43).
                applied = self.ctl.f_prev if force_applied_N is None else np.asarray(force_applied_N, dtype=float)
                sent = self.ctl.f_prev.copy()
                self.ctl.observe(np.asarray(theta_rad, dtype=float), applied, stamp_s)
                self.ctl.f_prev[:] = sent
                if self.latched:
                    return self.hold(self.latch_reason)
                return self.hold("drives hold" + (f": {self.drive_reason}" if self.drive_reason else ""))
            if self._joined and self._estopped and not self.running:
                # A run joined during the bridge's hold (the controller restarted: the bridge held
                # since its commands stopped) owes a take-up before the law runs: the hold at α̂
                # ends the bridge's, and the take-up starts at the first active state.
                return self.hold(f"taking up the cables' slack {self._take_up_cause()}: waiting for the drives")
        elif drive != "active":
            applied = self.ctl.f_prev if force_applied_N is None else np.asarray(force_applied_N, dtype=float)
            self.ctl.observe(np.asarray(theta_rad, dtype=float), applied, stamp_s)
            self._restart = self._drives_off = True
            self._pause(stamp_s)
            if estop_seen:
                # A take-up starts again at the release, also when the bridge obeyed another
                # controller meanwhile: handed back during that one's take-up, the law had run at
                # once on slack cables, α̂ 12° off 3 s later (transition_fuzz2.py, session 47).
                self._estopped, self._take_up = True, None
                self._joined = False  # that take-up is the e-stop's (a re-estimate owed stays owed)
                self._wind_down = False  # the bridge ramps from zero at the release
            if not obeyed:
                reason = self.drive_reason or "the bridge obeys another controller"
            else:
                reason = f"drives {drive}" + (f": {self.drive_reason}" if self.drive_reason else "")
            if (drive == "disabled" or not obeyed) and self.running:
                self._end("aborted", f"{reason} during the campaign", self._progress(stamp_s), self.hold_alpha())
            elif drive == "disabled" or not obeyed:
                self._drop_waiting(reason)
            return self.hold(self.latch_reason if self.latched else reason)
        if self._restart and drive == "active" and self._estopped:
            self._estopped = False
            peak = take_up_peak_N(self.params)
            if peak > 0.0 and not self.running:
                self._take_up = TakeUp(peak, take_up_rules.TAKE_UP_RATE_N_S, start_N=self.pretension_N)
            else:  # none (a campaign of its own runs, or the take-up is off): nothing is owed
                self._joined = self._reestimate_when_taut = False
        if self._take_up is not None:
            # Under a latch too, at the last sane α̂ (hold_alpha), and on to the latch's hold: held
            # without it, the slack cables' drums wound in undamped at the release and the neck
            # reached 500-845°/s (docs/safety/transition_fuzz.py, session 47; the take-up had
            # waited for the latch to be lifted, or been cut short by one).
            return self._taking_up(theta_rad, stamp_s, drive, force_applied_N)
        if self.latched:  # the latch's hold, at the last sane α̂; a new campaign lifts it
            self.reference(stamp_s)
            return self.hold(self.latch_reason)
        if self._restart and drive == "active":
            if self._bridge_held and force_applied_N is not None:
                # After the bridge's hold the law's rate bound runs from what the bridge applies
                # (its hold, ramping to our commands), not from a command it did not apply: the
                # first commands had chased the one sent last during the hold (audit of session 43).
                self.ctl.f_prev[:] = force_applied_N
            elif self._own_hold and not self._drives_off:
                # From the hold it sent on stale states, which the bridge applied: the law's first
                # commands had stepped 10 and 6.5 N a tick from it (its friction and velocity
                # terms; audit of session 44), now let go at the take-up's rate.
                self._wind_down = True
            self._own_hold = False
            self._take_over(stamp_s)
        if drive == "active":
            self._bridge_held = False
        a_d, a_d_dot, a_d_ddot = self.reference(stamp_s)
        sent = self.ctl.f_prev.copy()  # what was last commanded: a wind-down's bound, a divergence's hold
        # While the bridge holds, the neck does not follow the law: its integral would wind up on
        # an error the law's commands do not act on (audit of session 43: to f_max), so it stays.
        integral = self.ctl.integral.copy() if drive == "hold" else None
        cmd = self.ctl.step(np.asarray(theta_rad), a_d, a_d_dot, a_d_ddot, self._pretension(stamp_s), stamp_s)
        if integral is not None:
            self.ctl.integral[:] = integral
        if self._wind_down:
            cmd.f[:] = self._wind_down_bound(cmd.f, sent)
            self.ctl.f_prev[:] = cmd.f
        if not _sane(cmd.alpha_hat, self._limit, cmd.f):
            # The hold ramps from what was sent, not from this command, which is not (a non-finite
            # one had made every hold command NaN, session 47).
            self.ctl.f_prev[:] = sent
            self.latched = True
            out = self.hold(f"diverging estimate α̂ = {np.round(np.degrees(cmd.alpha_hat), 1).tolist()}°")
            self.latch_reason = self.hold_reason
            self._drop_waiting(self.hold_reason)
            if self.running or (not self.service and not self.outcome):  # not ended by _drop_waiting
                self._end("aborted", self.hold_reason, self._progress(stamp_s) if self.running else 0.0,
                          self.last_sane)
            return out
        # where a hold would aim: never beyond the joint limit (audit of 2026-11-26)
        self.last_sane = np.clip(cmd.alpha_hat, -self._alpha_max, self._alpha_max)
        self.hold_reason = ""
        self._from_law, self._hold_step_N = True, None
        # The law's arrays change in place at its next tick: the Output keeps its own (a few µs).
        return Output(cmd.f.copy(), cmd.alpha_hat.copy(), np.array(a_d), cmd.e.copy(), cmd.saturated.copy(), True)

    def _taking_up(self, theta_rad: np.ndarray, stamp_s: float, drive: str,
                   force_applied_N: np.ndarray | None) -> Output:
        """One state of the take-up after an e-stop (:mod:`controller.take_up`): α̂ follows the
        encoders as with the drives off (the integral stays at zero), the command is the hold at
        α̂ on the raised floor, and once the motors have wound the slack in the law takes over
        from there at the next state (:meth:`_take_over`: α^d = α̂, a fresh integral; the floor
        then falls back at ``PRETENSION_RELEASE_N_S``)."""
        take_up = self._take_up
        assert take_up is not None
        applied = self.ctl.f_prev if force_applied_N is None else np.asarray(force_applied_N, dtype=float)
        # The estimate takes the forces that acted; the hold's rate bound runs from what was sent
        # (with the drives just back the bridge still ramps from zero: from there the first
        # command had dropped 7 N).
        sent = self.ctl.f_prev.copy() if self._hold_sent is None else self._hold_sent.copy()
        self.ctl.observe(np.asarray(theta_rad, dtype=float), applied, stamp_s)
        self.ctl.f_prev[:] = sent
        take_up.damp(self.ctl.theta_dot, self.ctl.gap_s)  # its low-pass over the time the speeds span
        # the floor at which the hold at α̂ stays PEAK_FORCE_FRACTION under f_max (audit of
        # 2026-11-29: the distribution loaded cables to f_max at ordinary poses)
        cap = take_up_rules.floor_cap_N(self.params, self.hold_alpha()) if drive == "active" else math.inf
        if drive != "active" or take_up.step(stamp_s, cap):  # a bridge hold: wait, level kept
            waiting = self._next_jog
            own = f"; {self.kind} {self.campaign_id} waits for it" if self._own_waiting is not None else ""
            latched = f"; latched: {self.latch_reason}" if self.latched else ""
            return self.hold(f"taking up the cables' slack {self._take_up_cause()}: floor t_min + {take_up.level_N:.0f} N "
                             f"(peak {take_up.peak_N:.0f} N)"
                             + (f"; {waiting.kind} {waiting.campaign_id} waits for it" if waiting is not None else own)
                             + latched)
        # The law takes over at the next state (``_restart`` is still set), from this command at
        # the take-up's rate: a motor still turning at ``PEAK_MAX_S`` left up to 10 N of damping
        # in it, which the law's first command dropped at once (audit of 2026-11-29).
        self._take_up, self._wind_down = None, True
        self.pretension_N = take_up.level_N
        if self.latched and (self._next_jog is not None or self._own_waiting is not None):
            # A campaign waits behind a take-up the latch went through: it lifts the latch, as any new
            # campaign does, α̂ again from the taut cables (eq. 33; the law takes over at the next state).
            self.latched, self.latch_reason = False, ""
            self._reestimate_when_taut = True
        if self._reestimate_when_taut:
            self._reestimate_taut(np.asarray(theta_rad, dtype=float), applied, stamp_s)
        self._joined = False
        # said once, in the status and the process's log (a new hold reason): how it ended
        if self.latched:
            return self.hold(f"the cables' slack is taken up ({take_up.done_reason}); latched: {self.latch_reason}")
        return self.hold(f"the cables' slack is taken up ({take_up.done_reason}): the law takes over")

    def count_timing(self, overrun: bool, deadline_missed: bool) -> None:
        """The shell's measure of the tick just commanded: compute over the period, command late."""
        self.overruns += int(overrun)
        self.deadline_misses += int(deadline_missed)

    def advance(self, stamp_s: float) -> None:
        """Progress events every 0.5 s of campaign time, ``finished`` after the settle time."""
        if self.trajectory is None:
            if self._brake is None and not self.taking_up and self._own_waiting is not None:  # begin_own
                own, self._own_waiting = self._own_waiting, None
                self.begin(approach(own, self.ctl.estimator.alpha_hat), stamp_s)
            elif self._brake is None and not self.taking_up and self._next_jog is not None:  # one waited for a brake or a take-up
                waiting, self._next_jog = self._next_jog, None
                self.start(waiting, stamp_s)
            return
        t = self.campaign_time(stamp_s)[0]
        if self._stalled(stamp_s, t):
            return
        if t >= self._next_progress:
            self._event("progress", min(t / self._total, 1.0))
            self._next_progress += PROGRESS_PERIOD_S
        if t >= self._total:
            self._end("finished", f"overruns {self.overruns}, deadline misses {self.deadline_misses}", 1.0,
                      self.trajectory.waypoints_rad[-1])
            waiting, self._next_jog = self._next_jog, None
            if waiting is not None:
                self.start(waiting, stamp_s)
