"""Random schedules of transitions through the controller's campaign service on the robot truth:
where the applied forces step, the neck moves fast, a command is non-finite or an exception
escapes (the rule: every enable, hold or restart is bumpless).

    .venv/bin/python docs/safety/transition_fuzz.py --seeds 10 --law 2          # about 2 min
    .venv/bin/python docs/safety/transition_fuzz.py --seed-list 7 --law 1 --trace   # one schedule, its log
    .venv/bin/python docs/safety/transition_fuzz.py --law 2 --script start_ct@0.5 glitch:2,-29.3@3 \
        start_ct@3.004 --window 3.004 0.5                                       # a fixed schedule (parse_script)

The controller's :class:`controller.service.CampaignService` closed on the twin (robot truth, no
camera) through the bridge's rules (:class:`bridge.safety.Safety`, the encoders' hold rule, the
motors' speeds), one state per 2 ms tick, as :class:`controller.offline.ServiceLoop` does, with
faults injected as docs/safety/watchdog_handback.py does:

- ``start``: a campaign request (the §7 control test, the identification, or a jog to a random
  pose within ±40°); while one runs it is a second request (refused, or a jog queued);
- ``stop``: the user's stop of the campaign last asked for;
- ``lost D``: the commands do not reach the bridge for D (2-300 ms; the states go on, its
  watchdog holds after 10 ms);
- ``stale D``: no state reaches the controller for D (2-300 ms): it answers none for 10 ms, then
  holds by itself (``svc.stale``) on the last state's stamp, which the bridge takes while that
  state is one of its last 50 ms, then refuses;
- ``estop`` / ``release``: an e-stop engaged (a release follows 0.05-1.5 s later; the controller
  then takes up the slack, controller/take_up.py);
- ``glitch``: one encoder reads off by 5-60 rad for one state (a fault latch), usually followed
  by a new campaign 0-1 s later.

:func:`run` plays the second round's events too (docs/safety/transition_fuzz2.py: another
controller owning the bridge, restarts of either process, clock steps, queued jogs).

Events come in bursts (1-4 events within 0-50 ms of each other), a few bursts per run, then a
quiet tail in which the service must come back to the law (not hold forever) unless latched.

Per tick: the applied force step (largest over the cables), the truth's joint speeds, |α|, the
command's finiteness, the service's state. Per seed: the worst applied step outside the e-stop's
drop (and the events in the 50 ms before it), the worst joint speed (and the events in the 0.5 s
before it), NaN commands, exceptions, a service still holding at the end with the drives active
and nothing latched, a campaign that did not advance over the tail. ``--baseline``: the same
seed with its campaign starts only (no faults), to tell tracking from transitions.
"""

from __future__ import annotations

import argparse
import math
import sys
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import msgspec
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bridge import bus
from bridge.motor_speed import MotorSpeed
from bridge.safety import Inputs, Safety
from controller.laws import LawConfig
from controller.offline import ServiceLoop
from controller.service import CampaignService
from controller.trajectory import Trajectory, control_test_trajectory, identification_trajectory
from twin.model.params import load_params
from twin.sim.simulator import TwinConfig

DT = 0.002
# the first 0.1 s: the twin's start (the neck sags 1.5° at 145°/s at zero force), no transition
START_TICKS = 50
STEP_FINDING_N = 6.0  # applied step per tick above which a transition's step is a finding
SPEED_LIMIT_DEG_S = 86.0  # TrajectoryLimits().per_joint(3)
_TRAJ = {}
REBIND_TICKS = 125  # StateGate.rebind_s 0.25 s
SKEW_S = 0.045  # under StateGate.skew_s 0.05
TRACE_FROM = [0.0]


def _trajectory(name: str) -> Trajectory:
    if name not in _TRAJ:
        _TRAJ[name] = control_test_trajectory() if name == "control" else identification_trajectory()
    return _TRAJ[name]


@dataclass
class Event:
    k: int  # tick
    kind: str  # start_ct, start_id, jog, stop, lost, stale, estop, release, glitch
    arg: Any = None  # duration in ticks (lost, stale), pose (jog), (encoder, rad) (glitch)
    arg2: Any = None  # foreign (transition_fuzz2.py): whether the other controller jogs

    def __str__(self) -> str:
        if self.kind == "foreign":
            g, d, l_ = self.arg
            return f"foreign G{g * 2}ms D{d * 2}ms L{l_ * 2}ms{' jog' if self.arg2 else ''}@{self.k * DT:.3f}s"
        if self.kind in ("ctlrestart", "bridgerestart"):
            return f"{self.kind} {self.arg * 2}ms@{self.k * DT:.3f}s"
        if self.kind == "clock":
            return f"clock {self.arg:+.3f}s@{self.k * DT:.3f}s"
        if self.kind == "start_law":
            return f"start_law{self.arg}@{self.k * DT:.3f}s"
        if self.kind in ("lost", "stale"):
            return f"{self.kind} {self.arg * DT * 1e3:.0f}ms@{self.k * DT:.3f}s"
        if self.kind == "jog":
            return f"jog {np.round(self.arg, 1).tolist()}@{self.k * DT:.3f}s"
        if self.kind == "glitch":
            return f"glitch enc{self.arg[0] + 1} {self.arg[1]:+.1f}rad@{self.k * DT:.3f}s"
        return f"{self.kind}@{self.k * DT:.3f}s"


def schedule(seed: int, duration_s: float, tail_s: float) -> list[Event]:
    """A random schedule: a campaign start first, then bursts of events (module docstring)."""
    rng = np.random.default_rng(seed)
    n = round(duration_s / DT)
    events: list[Event] = []

    def start(k: int) -> None:
        r = rng.random()
        if r < 0.45:
            events.append(Event(k, "start_ct"))
        elif r < 0.6:
            events.append(Event(k, "start_id"))
        else:
            events.append(Event(k, "jog", rng.uniform(-40.0, 40.0, 3)))

    start(int(rng.integers(100, 600)))
    for _ in range(int(rng.integers(2, 6))):
        k0 = int(rng.integers(500, n))
        for _ in range(int(rng.integers(1, 5))):
            k = k0 + int(rng.integers(0, 26))  # within 50 ms
            kind = rng.choice(["start", "stop", "lost", "stale", "estop", "glitch"],
                              p=[0.22, 0.16, 0.22, 0.22, 0.1, 0.08])
            if kind == "start":
                start(k)
            elif kind in ("lost", "stale"):
                events.append(Event(k, str(kind), int(rng.integers(1, 151))))
            elif kind == "estop":
                events.append(Event(k, "estop"))
                events.append(Event(k + int(rng.integers(25, 751)), "release"))
            elif kind == "glitch":
                events.append(Event(k, "glitch", (int(rng.integers(0, 4)), float(rng.choice([-1, 1]) * rng.uniform(5, 60)))))
                if rng.random() < 0.8:
                    start(k + int(rng.integers(1, 500)))
            else:
                events.append(Event(k, "stop"))
    events.sort(key=lambda e: e.k)
    return [e for e in events if e.k < n]  # the tail (tail_s) stays quiet


@dataclass
class Result:
    seed: int
    law: int
    events: list[Event]
    step: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) applied step, N/tick
    speed: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) largest |α̇|, °/s
    alpha: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (T,) largest |α|, °
    drive: list[str] = field(default_factory=list)
    state: list[str] = field(default_factory=list)  # the service's state per tick (short)
    nonfinite: list[int] = field(default_factory=list)
    exception: str = ""
    campaign_log: list[str] = field(default_factory=list)
    end_problems: list[str] = field(default_factory=list)
    estop_ticks: set = field(default_factory=set)  # ticks whose step is the e-stop's drop
    requests: dict = field(default_factory=dict)  # id -> [kind, controller generation, its events...]


def _tmin_toml(params) -> str:
    q = msgspec.structs.replace(params, limits=msgspec.structs.replace(params.limits, t_min=14.0))
    return q.to_toml()


def run(params, law: int, seed: int, events: list[Any], duration_s: float, tail_s: float, trace: bool = False) -> Result:
    res = Result(seed, law, events)
    loop = ServiceLoop(params, LawConfig(law=law), TwinConfig(camera=False, seed=seed, truth="robot"), settle_s=0.5)
    twin, svc, safety, hold_rule, speed, tick = loop.twin, loop.svc, loop.safety, loop.hold_rule, loop.speed, loop.tick
    new_svc = lambda: CampaignService(params, LawConfig(law=law), settle_s=0.5, service=True)  # noqa: E731
    cfg = safety.config  # a restarted bridge's
    gen = 0
    n = round((duration_s + tail_s) / DT)
    by_k: dict[int, list[Event]] = {}
    for e in events:
        by_k.setdefault(e.k, []).append(e)
    lost_until = stale_from = stale_until = -1
    age, seq, last_id = 0, 0, ""
    applied_prev = np.zeros(params.n_cables)
    steps, speeds, alphas = np.zeros(n), np.zeros(n), np.zeros(n)
    out = None
    law_ran_tail, progress_at_tail, k = 0, None, 0
    tmin_toml = _tmin_toml(params)
    stamp_off = 0.0
    # ownership: owner on the bridge; the foreign controller's service and its phases
    owner, svc_o = "c", None
    f_lost_until = f_cmd_from = f_cmd_until = f_vanish_at = -1
    f_jog_at, f_jog = -1, None
    # gates (clock step / bridge restart): states refused from gate_from until gate_take, then action
    gate_from, gate_take = -1, -1
    gate_action: Any = cast(Any, None)
    dead_until, bridge_down_until, bridge_down_from = -1, -1, -1
    last_taken_k = 0
    last_stamp = tick.t_s  # requests are served on the last state's stamp (controller/process.py)
    try:
        for k in range(n):
            estop: list[tuple[bool, str]] = []
            glitch = np.zeros(params.n_cables)
            for e in by_k.get(k, ()):
                if e.kind in ("start_ct", "start_id", "jog", "start_law", "start_tmin"):
                    seq += 1
                    last_id = f"{e.kind}-{seq}"
                    traj = (_trajectory("control") if e.kind in ("start_ct", "start_law", "start_tmin")
                            else _trajectory("ident") if e.kind == "start_id"
                            else Trajectory.from_degrees([list(e.arg)], [], 0.0, "jog"))
                    res.requests[last_id] = [e.kind, gen]
                    if k <= dead_until:
                        res.requests[last_id].append("lost: controller down")
                        continue
                    svc.handle(bus.CampaignRequest(seq=seq, stamp_s=0.0, campaign_id=last_id, action="start",
                                                   law=e.arg if e.kind == "start_law" else law,  # pyright: ignore[reportArgumentType]
                                                   kind="jog" if e.kind == "jog" else "campaign",  # pyright: ignore[reportArgumentType]
                                                   parameters_toml=tmin_toml if e.kind == "start_tmin" else "",
                                                   trajectory_json=traj.to_json()), last_stamp)
                elif e.kind in ("stop", "stopother"):
                    seq += 1
                    if k > dead_until:
                        svc.handle(bus.CampaignRequest(seq=seq, stamp_s=0.0, action="stop",
                                                       campaign_id=last_id if e.kind == "stop" else f"nope-{seq}"),
                                   last_stamp)
                elif e.kind == "lost":
                    lost_until = max(lost_until, k + int(e.arg) - 1)
                elif e.kind == "stale":
                    if stale_until < k:
                        stale_from = k
                    stale_until = max(stale_until, k + int(e.arg) - 1)
                elif e.kind == "estop":
                    estop.append((True, "fuzz e-stop"))
                elif e.kind == "release":
                    estop.append((False, "fuzz release"))
                elif e.kind == "glitch":
                    glitch[e.arg[0]] = e.arg[1]
                elif e.kind == "foreign" and f_vanish_at < k:
                    g, d, l_ = e.arg
                    owner = ""
                    f_lost_until = k + g - 1
                    f_cmd_from, f_cmd_until, f_vanish_at = k + g, k + g + d - 1, k + g + d + l_
                    svc_o = None
                    if e.arg2:
                        f_jog_at, f_jog = k + g + 10, np.random.default_rng(seed + k).uniform(-25, 25, 3)
                elif e.kind == "ctlrestart":
                    dead_until = max(dead_until, k + int(e.arg) - 1)
                elif e.kind == "bridgerestart" and bridge_down_until < k:
                    bridge_down_from, bridge_down_until = k, k + int(e.arg) - 1
                elif e.kind == "clock":
                    s = float(e.arg)
                    stamp_off += s
                    if not (0.0 < s <= SKEW_S) and gate_action is None:
                        gate_from = k
                        first = max(k, last_taken_k + REBIND_TICKS)
                        gate_take, gate_action = first + 1, ("clock", s)
                    elif not (0.0 < s <= SKEW_S) and gate_action is not None and gate_action[0] == "clock":
                        gate_action = ("clock", gate_action[1] + s)
            # -- the bridge's side: dead, restarting
            bridge_down = bridge_down_from <= k <= bridge_down_until
            if k == bridge_down_until + 1 and bridge_down_from >= 0:
                was_engaged = safety.estop_engaged
                safety = Safety(cfg)
                speed = MotorSpeed(params.n_cables, DT)
                speed.update(tick.theta_meas.tolist())
                if was_engaged:
                    safety.apply_estop([(True, "fuzz e-stop (token)")])
                age, owner = 0, "c"
                stamp_off = -tick.t_s  # the new run's clock starts at 0
                first = max(k, last_taken_k + REBIND_TICKS)
                gate_from, gate_take, gate_action = bridge_down_from, first + 1, ("bridge", 0.0)
                bridge_down_from = -1
            theta = tick.theta_meas + glitch
            stamp = tick.t_s + stamp_off
            if owner == "" and k == f_cmd_from:
                owner = "o"
            if owner == "o" and k >= f_vanish_at:
                owner = ""
            # -- the foreign controller
            o_cmd = None
            if f_cmd_from <= k <= f_cmd_until and not bridge_down:
                if svc_o is None:
                    svc_o = new_svc()
                    svc_o.initialise(theta, np.asarray(safety.force))
                if k == f_jog_at and f_jog is not None:
                    svc_o.handle(bus.CampaignRequest(seq=1, stamp_s=0.0, campaign_id="ojog", action="start", kind="jog",
                                                     trajectory_json=Trajectory.from_degrees([list(f_jog)], [], 0.0, "jog").to_json()),
                                 stamp)
                svc_o.drive_reason = safety.estop_reason if safety.drive == "disabled" else safety.hold_reason
                oo = svc_o.control(theta, stamp, safety.drive, np.asarray(safety.force))
                if oo.law_ran:
                    svc_o.advance(stamp)
                svc_o.drain_events()
                o_cmd = oo.force_N.tolist()
            # -- the controller's side
            dead = k <= dead_until
            gated = gate_from <= k < gate_take
            stale = (stale_from <= k <= stale_until) or gated or bridge_down
            command = None
            if dead:
                out = None
                if k == dead_until:  # the next state is the new process's first
                    svc = new_svc()
                    gen += 1
                    svc._fresh = True
            elif stale and getattr(svc, "_fresh", False):
                out = None  # a new process sends nothing before its first state
            elif stale:
                gap_k = k - last_taken_k - 1
                if gap_k >= 5:
                    out = svc.stale("stale state", DT * (gap_k + 1))
                taken = 5 <= gap_k < 25 and not gated and not bridge_down
                command = out.force_N.tolist() if taken and out is not None else None
            else:
                if k == gate_take and gate_action is not None:
                    if gate_action[0] == "clock":
                        svc.clock_stepped(gate_action[1], stamp)
                    else:
                        svc.new_bridge_run(theta, stamp, "b2")
                    gate_action = None
                applied_now = np.asarray(safety.force)
                if getattr(svc, "_fresh", False):
                    svc.initialise(theta, applied_now)
                    svc._fresh = False
                obeyed = owner != "o"
                svc.drive_reason = safety.estop_reason if safety.drive == "disabled" else safety.hold_reason
                if not obeyed:
                    svc.drive_reason = "the bridge obeys controller o, not this one"
                out = svc.control(theta, stamp, safety.drive, applied_now, obeyed)
                if out.law_ran:
                    svc.advance(stamp)
                last_taken_k, last_stamp = k, stamp
                command = out.force_N.tolist() if obeyed else None
            if out is not None and not np.all(np.isfinite(out.force_N)):
                res.nonfinite.append(k)
            for cev in svc.drain_events():
                if cev.event != "progress":
                    res.campaign_log.append(f"{tick.t_s:.3f}s g{gen} {cev.campaign_id} {cev.event} {cev.message[:110]}")
                    if cev.campaign_id in res.requests:
                        res.requests[cev.campaign_id].append(cev.event)
            if k <= lost_until or k <= f_lost_until:
                command = None
            sender = "c"
            if o_cmd is not None:
                command, sender = o_cmd, "o"
            if command is not None and sender == "c" and owner == "":
                owner = "c"
            age = 0 if command is not None else age + 1
            was = safety.drive
            if bridge_down:
                applied = np.zeros(params.n_cables)
                if was != "down":
                    res.estop_ticks.add(k)
                drive_rec = "inactive"
                safety.drive = safety.drive  # untouched; replaced at the restart
            else:
                d = safety.step(Inputs(command_N=command, command_age_s=DT * age, states_unanswered=age,
                                       estop=tuple(estop), hold_N=hold_rule(theta).tolist(), sender=sender,
                                       speed_rad_s=speed.rad_s))
                applied = np.asarray(d.force_N, dtype=float)
                drive_rec = safety.drive
                if safety.drive == "disabled" and was != "disabled":
                    res.estop_ticks.add(k)
            steps[k] = float(np.abs(applied - applied_prev).max())
            applied_prev = applied
            res.drive.append(drive_rec)
            res.state.append(("DEAD" if dead else "") + (f"own:{owner}," if owner != "c" else "") + _state(svc, out, stale))
            if trace and tick.t_s >= TRACE_FROM[0]:
                print(f"{k:5d} {tick.t_s:7.3f} {drive_rec:8s} step {steps[k]:5.2f} {res.state[-1]} "
                      f"cmd {np.round(out.force_N, 1).tolist() if out is not None else None} "
                      f"applied {np.round(applied, 1).tolist()}")
            tick = twin.tick(applied)
            speed.update(tick.theta_meas.tolist())
            speeds[k] = math.degrees(float(np.abs(tick.alpha_dot).max()))
            alphas[k] = math.degrees(float(np.abs(tick.alpha).max()))
            if k >= n - round(1.0 / DT):
                law_ran_tail += int(out is not None and out.law_ran)
            if k == n - round(tail_s / DT) and svc.running:
                progress_at_tail = (svc.campaign_id, svc.campaign_time(tick.t_s + stamp_off)[0])
    except Exception:  # noqa: BLE001
        res.exception = f"tick {k} ({k * DT:.3f}s): " + traceback.format_exc(limit=8)
    res.step, res.speed, res.alpha = steps[: k + 1], speeds[: k + 1], alphas[: k + 1]
    if not res.exception:
        res.end_problems.append(f"(info) at the end |α̂ − α| = {math.degrees(float(np.abs(svc.ctl.estimator.alpha_hat - tick.alpha).max())):.1f}° "
                                f"α = {np.round(np.degrees(tick.alpha), 1).tolist()}° phase {svc.phase} hold {svc.hold_reason[:40]!r}")
        if safety.drive == "active" and not svc.latched and law_ran_tail == 0:
            res.end_problems.append(f"holds over the last 1 s with the drives active, not latched: {svc.hold_reason!r}")
        if progress_at_tail is not None and svc.running and svc.campaign_id == progress_at_tail[0]:
            t_now = svc.campaign_time(tick.t_s + stamp_off)[0]
            if t_now - progress_at_tail[1] < 0.5 * tail_s:
                res.end_problems.append(f"campaign {svc.campaign_id} advanced {t_now - progress_at_tail[1]:.2f} s "
                                        f"over the {tail_s:g} s tail")
        if safety.drive in ("disabled", "inactive") and not safety.estop_engaged and k > 10:
            res.end_problems.append(f"bridge {safety.drive} at the end without an e-stop")
        if svc._starting is not None or (svc._next_jog is not None and not svc.running):
            res.end_problems.append("a campaign still waits to start at the end")
        for cid, rec in res.requests.items():
            _kind, g, evs = rec[0], rec[1], rec[2:]
            if any(str(x).startswith("lost") for x in evs):
                continue
            if g != gen and not evs:
                continue  # in flight when the controller died
            if not evs:
                res.end_problems.append(f"request {cid} never answered (no started/aborted)")
            elif evs[-1] == "started" and not (svc.running and svc.campaign_id == cid) and g == gen:
                res.end_problems.append(f"campaign {cid} started and never ended: {evs}")
    return res


def _state(svc: CampaignService, out, stale: bool) -> str:
    parts = [svc.phase[:4]]
    if stale:
        parts.append("STALE")
    if out is not None and out.law_ran:
        parts.append("law")
    else:
        parts.append("hold:" + svc.hold_reason.split(":")[0][:28])
    if svc.latched:
        parts.append("LATCH")
    if svc.taking_up:
        parts.append("takeup")
    if svc.braking:
        parts.append("brake")
    return ",".join(parts)


def context(events: list[Event], k: int, window_ticks: int) -> str:
    near = [str(e) for e in events if k - window_ticks <= e.k <= k
            or (e.kind in ("lost", "stale") and e.k <= k <= e.k + e.arg + window_ticks)]
    return "; ".join(near) if near else "(no event: tracking)"


def report(res: Result, baseline: Result | None = None) -> list[str]:
    """Lines for one run: the worst step (outside the e-stop's drop) and speed, with context."""
    lines = []
    steps = res.step.copy()
    for k in res.estop_ticks:
        if k < len(steps):
            steps[k] = 0.0
    head = f"law {res.law} seed {res.seed}"
    if len(steps):
        k = int(np.argmax(steps))
        lines.append(f"{head}: worst step {steps[k]:.2f} N/tick at {k * DT:.3f}s [{res.drive[k]}; {res.state[k]}] "
                     f"after: {context(res.events, k, 25)}")
        # the neck falls while the drives are off (e-stop, or inactive after its release until a
        # command comes): its speed then is the e-stop's drop, reported apart
        off = np.array([dr in ("disabled", "inactive") for dr in res.drive])
        driven = res.speed.copy()
        driven[:START_TICKS] = 0.0
        fall = float(np.where(off, driven, 0.0).max()) if off.any() else 0.0
        driven[off] = 0.0
        ks = int(np.argmax(driven))
        base = f" (baseline worst {baseline.speed[START_TICKS:].max():.0f})" if baseline is not None and len(baseline.speed) else ""
        lines.append(f"{head}: worst speed (drives on) {res.speed[ks]:.0f}°/s at {ks * DT:.3f}s [{res.drive[ks]}; {res.state[ks]}] "
                     f"max|α| {res.alpha[START_TICKS:].max():.1f}°{base}, drives off {fall:.0f}°/s; after: "
                     f"{context(res.events, ks, 250)}")
        big = [j for j in np.flatnonzero(steps > STEP_FINDING_N)]
        if big:
            lines.append(f"{head}: {len(big)} ticks > {STEP_FINDING_N:g} N: "
                         + ", ".join(f"{steps[j]:.1f}@{j * DT:.3f}s[{res.state[j]}]" for j in big[:8]))
    if res.nonfinite:
        lines.append(f"{head}: NON-FINITE commands at ticks {res.nonfinite[:10]}")
    if res.exception:
        lines.append(f"{head}: EXCEPTION {res.exception}")
    for p in res.end_problems:
        lines.append(f"{head}: END {p}")
    return lines


def parse_script(text: list[str]) -> list[Event]:
    """Events from ``kind[:args]@seconds`` words (a deterministic reproduction): ``start_ct@0.5``,
    ``start_id@1``, ``jog:10,-20,5@1`` (degrees), ``stop@2``, ``lost:120@3`` and ``stale:120@3``
    (ms), ``estop@4``, ``release@4.3``, ``glitch:2,-29.3@3`` (encoder 1-4, rad)."""
    events = []
    for word in text:
        head, at = word.rsplit("@", 1)
        kind, _, arg = head.partition(":")
        k = round(float(at) / DT)
        if kind in ("lost", "stale"):
            events.append(Event(k, kind, max(1, round(float(arg) * 1e-3 / DT))))
        elif kind == "jog":
            events.append(Event(k, kind, np.array([float(x) for x in arg.split(",")])))
        elif kind == "glitch":
            enc, rad = arg.split(",")
            events.append(Event(k, kind, (int(enc) - 1, float(rad))))
        elif kind in ("start_ct", "start_id", "stop", "estop", "release"):
            events.append(Event(k, kind))
        else:
            raise SystemExit(f"unknown event {word!r}")
    return sorted(events, key=lambda e: e.k)


def after(res: Result, from_s: float, window_s: float = 1.0) -> str:
    """The worst applied step and driven speed from ``from_s`` over ``window_s`` (a script's figures)."""
    a, b = round(from_s / DT), round((from_s + window_s) / DT)
    steps = res.step.copy()
    for k in res.estop_ticks:
        steps[k] = 0.0
    off = np.array([dr in ("disabled", "inactive") for dr in res.drive])
    speed = np.where(off, 0.0, res.speed)
    ka, ks = a + int(np.argmax(steps[a:b])), a + int(np.argmax(speed[a:b]))
    return (f"from {from_s:g} s over {window_s:g} s: worst step {steps[ka]:.2f} N/tick at {ka * DT:.3f}s "
            f"[{res.drive[ka]}; {res.state[ka]}], worst speed (drives on) {speed[ks]:.0f}°/s at {ks * DT:.3f}s "
            f"[{res.drive[ks]}; {res.state[ks]}], max|α| {res.alpha[a:b].max():.1f}°")


def main() -> None:
    ap = argparse.ArgumentParser(description="Random transition schedules through the campaign service (robot truth).")
    ap.add_argument("--seeds", type=int, default=5, help="seeds 0..N-1 (with --first)")
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--seed-list", type=int, nargs="+", help="these seeds instead")
    ap.add_argument("--law", type=int, nargs="+", default=[2])
    ap.add_argument("--duration", type=float, default=6.0, help="s over which events come")
    ap.add_argument("--tail", type=float, default=4.0, help="s of quiet after them")
    ap.add_argument("--baseline", action="store_true", help="also each seed's campaign starts alone")
    ap.add_argument("--trace", action="store_true", help="print every tick (one seed)")
    ap.add_argument("--events", action="store_true", help="print each schedule and the campaign events")
    ap.add_argument("--script", nargs="+", help="run these events instead of random ones (parse_script)")
    ap.add_argument("--window", type=float, nargs=2, metavar=("FROM_S", "LENGTH_S"),
                    help="with --script: also the worst step and speed over this window")
    args = ap.parse_args()
    params = load_params()
    if args.script:
        events = parse_script(args.script)
        for law in args.law:
            for seed in args.seed_list or [args.first]:
                res = run(params, law, seed, events, args.duration, args.tail, trace=args.trace)
                print(f"law {law} seed {seed} script: " + "; ".join(map(str, events)))
                if args.events:
                    for line in res.campaign_log:
                        print("    " + line)
                for line in report(res):
                    print(line)
                if args.window:
                    print(f"law {law} seed {seed}: " + after(res, *args.window), flush=True)
        return
    seeds = args.seed_list or list(range(args.first, args.first + args.seeds))
    for law in args.law:
        for seed in seeds:
            events = schedule(seed, args.duration, args.tail)
            res = run(params, law, seed, events, args.duration, args.tail, trace=args.trace)
            base = None
            if args.baseline:
                starts = [e for e in events if e.kind in ("start_ct", "start_id", "jog")][:1]
                base = run(params, law, seed, starts, args.duration, args.tail)
            if args.events:
                print(f"law {law} seed {seed} schedule: " + "; ".join(map(str, events)))
                for line in res.campaign_log:
                    print("    " + line)
            for line in report(res, base):
                print(line, flush=True)


if __name__ == "__main__":
    main()
