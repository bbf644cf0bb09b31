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
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from bridge import bus
from bridge.safety import Inputs
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


def _trajectory(name: str) -> Trajectory:
    if name not in _TRAJ:
        _TRAJ[name] = control_test_trajectory() if name == "control" else identification_trajectory()
    return _TRAJ[name]


@dataclass
class Event:
    k: int  # tick
    kind: str  # start_ct, start_id, jog, stop, lost, stale, estop, release, glitch
    arg: Any = None  # duration in ticks (lost, stale), pose (jog), (encoder, rad) (glitch)

    def __str__(self) -> str:
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


def run(params, law: int, seed: int, events: list[Event], duration_s: float, tail_s: float,
        trace: bool = False) -> Result:
    res = Result(seed, law, events)
    loop = ServiceLoop(params, LawConfig(law=law), TwinConfig(camera=False, seed=seed, truth="robot"), settle_s=0.5)
    twin, svc, safety, hold_rule, speed, tick = loop.twin, loop.svc, loop.safety, loop.hold_rule, loop.speed, loop.tick
    n = round((duration_s + tail_s) / DT)
    by_k: dict[int, list[Event]] = {}
    for e in events:
        by_k.setdefault(e.k, []).append(e)
    lost_until = stale_from = stale_until = -1
    age, seq, last_id = 0, 0, ""
    applied_prev = np.zeros(params.n_cables)
    steps, speeds, alphas = np.zeros(n), np.zeros(n), np.zeros(n)
    out = None
    law_ran_tail = 0
    progress_at_tail = None
    k = 0
    try:
        for k in range(n):
            estop: list[tuple[bool, str]] = []
            glitch = np.zeros(params.n_cables)
            for e in by_k.get(k, ()):
                if e.kind in ("start_ct", "start_id", "jog"):
                    seq += 1
                    last_id = f"{e.kind}-{seq}"
                    traj = (_trajectory("control") if e.kind == "start_ct" else _trajectory("ident") if e.kind == "start_id"
                            else Trajectory.from_degrees([list(e.arg)], [], 0.0, "jog"))
                    svc.handle(bus.CampaignRequest(seq=seq, stamp_s=0.0, campaign_id=last_id, action="start", law=law,  # type: ignore[arg-type]
                                                   kind="jog" if e.kind == "jog" else "campaign",  # pyright: ignore[reportArgumentType]
                                                   trajectory_json=traj.to_json()), tick.t_s)
                elif e.kind == "stop":
                    seq += 1
                    svc.handle(bus.CampaignRequest(seq=seq, stamp_s=0.0, campaign_id=last_id, action="stop"), tick.t_s)
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
            theta = tick.theta_meas + glitch  # what the bridge reports (its hold rule reads it too)
            svc.drive_reason = safety.estop_reason if safety.drive == "disabled" else safety.hold_reason
            stale = stale_from <= k <= stale_until
            if stale:
                gap_k = k - stale_from
                if gap_k >= 5:
                    out = svc.stale("stale state", DT * (gap_k + 1))
                taken = 5 <= gap_k < 25
                command = out.force_N.tolist() if taken and out is not None else None
            else:
                out = svc.control(theta, tick.t_s, safety.drive, np.asarray(safety.force))
                if out.law_ran:
                    svc.advance(tick.t_s)
                command = out.force_N.tolist()
            if out is not None and not np.all(np.isfinite(out.force_N)):
                res.nonfinite.append(k)
            for ev in svc.drain_events():
                if ev.event != "progress":
                    res.campaign_log.append(f"{tick.t_s:.3f}s {ev.campaign_id} {ev.event} {ev.message[:90]}")
            if k <= lost_until:
                command = None
            age = 0 if command is not None else age + 1
            was = safety.drive
            d = safety.step(Inputs(command_N=command, command_age_s=DT * age, states_unanswered=age,
                                   estop=tuple(estop), hold_N=hold_rule(theta).tolist(), sender="c",
                                   speed_rad_s=speed.rad_s))
            applied = np.asarray(d.force_N, dtype=float)
            steps[k] = float(np.abs(applied - applied_prev).max())
            if safety.drive == "disabled" and was != "disabled":
                res.estop_ticks.add(k)
            applied_prev = applied
            res.drive.append(safety.drive)
            res.state.append(_state(svc, out, stale))
            if trace:
                print(f"{k:5d} {tick.t_s:7.3f} {safety.drive:8s} step {steps[k]:5.2f} {res.state[-1]} "
                      f"cmd {np.round(out.force_N, 1).tolist() if out is not None else None} "
                      f"applied {np.round(applied, 1).tolist()}")
            tick = twin.tick(applied)
            speed.update(tick.theta_meas.tolist())  # (the glitch is not in the motor speeds)
            speeds[k] = math.degrees(float(np.abs(tick.alpha_dot).max()))
            alphas[k] = math.degrees(float(np.abs(tick.alpha).max()))
            if k >= n - round(1.0 / DT):
                law_ran_tail += int(out is not None and out.law_ran)
            if k == n - round(tail_s / DT) and svc.running:
                progress_at_tail = (svc.campaign_id, svc.campaign_time(tick.t_s)[0])
    except Exception:  # noqa: BLE001 - the fuzz reports it
        res.exception = f"tick {k} ({k * DT:.3f}s): " + traceback.format_exc(limit=6)
    res.step, res.speed, res.alpha = steps[: k + 1], speeds[: k + 1], alphas[: k + 1]
    if not res.exception:
        if safety.drive == "active" and not svc.latched and law_ran_tail == 0:
            res.end_problems.append(f"holds over the last 1 s with the drives active, not latched: {svc.hold_reason!r}")
        if progress_at_tail is not None and svc.running and svc.campaign_id == progress_at_tail[0]:
            t_now = svc.campaign_time(tick.t_s)[0]
            if t_now - progress_at_tail[1] < 0.5 * tail_s:
                res.end_problems.append(f"campaign {svc.campaign_id} advanced {t_now - progress_at_tail[1]:.2f} s "
                                        f"over the {tail_s:g} s tail")
        if safety.drive in ("disabled", "inactive") and not safety.estop_engaged and k > 10:
            res.end_problems.append(f"bridge {safety.drive} at the end without an e-stop")
        if svc._starting is not None or (svc._next_jog is not None and not svc.running):
            res.end_problems.append("a campaign still waits to start at the end")
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
