"""Second round of transition_fuzz.py: event families the first round did not cover.

    .venv/bin/python docs/safety/transition_fuzz2.py --seeds 6 --law 2
    .venv/bin/python docs/safety/transition_fuzz2.py --law 2 --script start_ct@0.5 foreign:0,300,20@2 --window 2 1

Same loop as transition_fuzz.py (CampaignService on the robot truth through bridge.safety.Safety,
one state per 2 ms tick, the same per-tick measures and report), with these events on top of its
own (start_ct, start_id, jog, stop, lost, stale, estop, release, glitch):

- ``foreign G,D,L``: our liveliness token vanishes (owner ""), our commands are lost for G ms,
  then another controller ``o`` (a second CampaignService, initialised on the state it first sees,
  holding, sometimes jogging) owns the bridge and commands it for D ms; it then goes silent and its
  token lingers L ms (owner still ``o``: our commands refused, the bridge's watchdog holds), then
  vanishes: owner "", our next command is admitted (sender change, bumpless at 1 N/tick). Our
  service gets ``obeyed=False`` and the process's drive_reason while the owner is ``o``.
- ``ctlrestart R``: the controller process dies (no state handled, no command) for R ms, then a
  fresh CampaignService is initialised on the first state (θ and the applied forces, as
  controller/process.py) and controls from that same state on.
- ``bridgerestart R``: the bridge dies (drives off, zero force, no states) for R ms; a fresh
  Safety (inactive, zero force; e-stop engaged again if it was) on a new clock (stamps from 0),
  encoders kept. The controller holds on stale states meanwhile; the first new-epoch state is
  taken after the gate's rebind (0.25 s since the last taken, confirmed by the next), then
  ``svc.new_bridge_run`` and control, as controller/process.py.
- ``clock S``: the bridge's clock steps by S s. Within the gate's skew (0 < S <= 0.045): the
  states keep coming with a gap in stamps. Else: the gate refuses them 0.25 s (the controller
  holds on stale states, the bridge refuses those stale-stamped commands), the next one is a
  candidate and the following confirms it: ``svc.clock_stepped(S)`` then control.
- ``jogs N``: N jogs within 0-10 ms of each other; ``stopother``: a stop of an id not running;
  ``start_law L``: a control test with law L; ``start_tmin``: a control test with a parameter
  set whose t_min is raised to 14 N.
"""

from __future__ import annotations

import argparse
import math
import sys
import traceback
from pathlib import Path
from typing import Any, cast

import msgspec
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import transition_fuzz as tf
from transition_fuzz import DT, Event, Result, _state, _trajectory, after, report

from bridge import bus
from bridge.motor_speed import MotorSpeed
from bridge.safety import Inputs, Safety
from controller.laws import LawConfig
from controller.offline import ServiceLoop
from controller.service import CampaignService
from controller.trajectory import Trajectory
from twin.model.params import load_params
from twin.sim.simulator import TwinConfig

REBIND_TICKS = 125  # StateGate.rebind_s 0.25 s
SKEW_S = 0.045  # under StateGate.skew_s 0.05
TRACE_FROM = [0.0]


def _str(e: Event) -> str:
    if e.kind == "foreign":
        g, d, l_ = e.arg
        return f"foreign G{g * 2}ms D{d * 2}ms L{l_ * 2}ms{' jog' if e.arg2 else ''}@{e.k * DT:.3f}s"
    if e.kind in ("ctlrestart", "bridgerestart"):
        return f"{e.kind} {e.arg * 2}ms@{e.k * DT:.3f}s"
    if e.kind == "clock":
        return f"clock {e.arg:+.3f}s@{e.k * DT:.3f}s"
    if e.kind == "start_law":
        return f"start_law{e.arg}@{e.k * DT:.3f}s"
    return Event.__str__(e)


class Ev(Event):
    arg2: object = None

    def __str__(self) -> str:
        return _str(self)


def ev(k: int, kind: str, arg=None, arg2=None) -> Ev:
    e = Ev(k, kind, arg)
    e.arg2 = arg2
    return e


def schedule(seed: int, duration_s: float, tail_s: float, law: int, family: str = "all") -> list[Ev]:
    rng = np.random.default_rng(10_000 + seed)
    n = round(duration_s / DT)
    events: list[Ev] = []

    def start(k: int) -> None:
        r = rng.random()
        if r < 0.35:
            events.append(ev(k, "start_ct"))
        elif r < 0.45:
            events.append(ev(k, "start_id"))
        elif r < 0.55:
            events.append(ev(k, "start_law", int(rng.choice([x for x in (1, 2, 3) if x != law]))))
        elif r < 0.6:
            events.append(ev(k, "start_tmin"))
        else:
            events.append(ev(k, "jog", rng.uniform(-40.0, 40.0, 3)))

    fam = {"all": (["start", "stop", "lost", "stale", "estop", "glitch", "foreign", "ctlrestart", "bridgerestart",
                    "clock", "jogs", "stopother"],
                   [0.12, 0.06, 0.07, 0.08, 0.07, 0.03, 0.13, 0.1, 0.07, 0.13, 0.09, 0.05]),
           "own": (["start", "stop", "lost", "stale", "estop", "foreign", "jogs"], [0.15, 0.05, 0.1, 0.1, 0.15, 0.35, 0.1]),
           "restart": (["start", "stop", "lost", "stale", "estop", "ctlrestart", "bridgerestart", "jogs"],
                       [0.15, 0.05, 0.08, 0.08, 0.14, 0.25, 0.15, 0.1]),
           "clock": (["start", "stop", "lost", "stale", "estop", "clock", "jogs"], [0.15, 0.08, 0.12, 0.15, 0.1, 0.3, 0.1]),
           "jog": (["start", "stop", "stopother", "jogs", "lost", "stale", "estop"], [0.25, 0.2, 0.1, 0.25, 0.07, 0.07, 0.06]),
           }[family]
    start(int(rng.integers(100, 600)))
    for _ in range(int(rng.integers(2, 6))):
        k0 = int(rng.integers(500, n))
        for _ in range(int(rng.integers(1, 5))):
            k = k0 + int(rng.integers(0, 26))  # within 50 ms
            kind = str(rng.choice(fam[0], p=np.array(fam[1]) / sum(fam[1])))
            if kind == "start":
                start(k)
            elif kind in ("lost", "stale"):
                events.append(ev(k, kind, int(rng.integers(1, 151))))
            elif kind == "estop":
                events.append(ev(k, "estop"))
                events.append(ev(k + int(rng.integers(25, 751)), "release"))
            elif kind == "glitch":
                events.append(ev(k, "glitch", (int(rng.integers(0, 4)), float(rng.choice([-1, 1]) * rng.uniform(5, 60)))))
                if rng.random() < 0.8:
                    start(k + int(rng.integers(1, 500)))
            elif kind == "stop":
                events.append(ev(k, "stop"))
            elif kind == "stopother":
                events.append(ev(k, "stopother"))
            elif kind == "foreign":
                events.append(ev(k, "foreign", (int(rng.integers(0, 26)), int(rng.integers(25, 751)),
                                                int(rng.choice([0, 0, int(rng.integers(1, 51))]))), bool(rng.random() < 0.5)))
            elif kind == "ctlrestart":
                events.append(ev(k, "ctlrestart", int(rng.integers(25, 501))))
            elif kind == "bridgerestart":
                events.append(ev(k, "bridgerestart", int(rng.integers(25, 501))))
            elif kind == "clock":
                r = rng.random()
                s = (float(rng.uniform(0.002, SKEW_S)) if r < 0.25 else float(-rng.uniform(0.002, 4.0)) if r < 0.55
                     else float(rng.uniform(0.06, 4.0)) if r < 0.8 else float(rng.choice([-1, 1]) * rng.uniform(5.0, 100.0)))
                events.append(ev(k, "clock", s))
            elif kind == "jogs":
                for _ in range(int(rng.integers(2, 4))):
                    events.append(ev(k + int(rng.integers(0, 6)), "jog", rng.uniform(-40.0, 40.0, 3)))
    events.sort(key=lambda e: e.k)
    return [e for e in events if e.k < n]


def _tmin_toml(params) -> str:
    q = msgspec.structs.replace(params, limits=msgspec.structs.replace(params.limits, t_min=14.0))
    return q.to_toml()


def run(params, law: int, seed: int, events: list[Any], duration_s: float, tail_s: float, trace: bool = False) -> Result:
    res = Result(seed, law, events)
    res.requests = {}  # id -> [kind, svc generation, events...]
    loop = ServiceLoop(params, LawConfig(law=law), TwinConfig(camera=False, seed=seed, truth="robot"), settle_s=0.5)
    twin, svc, safety, hold_rule, speed, tick = loop.twin, loop.svc, loop.safety, loop.hold_rule, loop.speed, loop.tick
    new_svc = lambda: CampaignService(params, LawConfig(law=law), settle_s=0.5, service=True)  # noqa: E731
    cfg = safety.config  # a restarted bridge's
    gen = 0
    n = round((duration_s + tail_s) / DT)
    by_k: dict[int, list[Ev]] = {}
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


def parse_script(text: list[str]) -> list[Ev]:
    """tf.parse_script words plus ``foreign:G,D,L[,jog]@s`` (ms), ``ctlrestart:R@s``,
    ``bridgerestart:R@s`` (ms), ``clock:S@s`` (s), ``start_law:L@s``, ``start_tmin@s``, ``stopother@s``."""
    out: list[Ev] = []
    for word in text:
        head, at = word.rsplit("@", 1)
        kind, _, arg = head.partition(":")
        k = round(float(at) / DT)
        if kind == "foreign":
            parts = arg.split(",")
            g, d, l_ = (max(0, round(float(x) * 1e-3 / DT)) for x in parts[:3])
            out.append(ev(k, kind, (g, max(1, d), l_), len(parts) > 3))
        elif kind in ("ctlrestart", "bridgerestart"):
            out.append(ev(k, kind, max(1, round(float(arg) * 1e-3 / DT))))
        elif kind == "clock":
            out.append(ev(k, kind, float(arg)))
        elif kind == "start_law":
            out.append(ev(k, kind, int(arg)))
        elif kind in ("start_tmin", "stopother"):
            out.append(ev(k, kind))
        else:
            e = tf.parse_script([word])[0]
            out.append(ev(e.k, e.kind, e.arg))
    return sorted(out, key=lambda e: e.k)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--seed-list", type=int, nargs="+")
    ap.add_argument("--law", type=int, nargs="+", default=[2])
    ap.add_argument("--family", default="all", choices=["all", "own", "restart", "clock", "jog"])
    ap.add_argument("--duration", type=float, default=6.0)
    ap.add_argument("--tail", type=float, default=4.0)
    ap.add_argument("--trace", action="store_true")
    ap.add_argument("--trace-from", type=float, default=0.0)
    ap.add_argument("--events", action="store_true")
    ap.add_argument("--script", nargs="+")
    ap.add_argument("--window", type=float, nargs=2, metavar=("FROM_S", "LENGTH_S"))
    args = ap.parse_args()
    params = load_params()
    TRACE_FROM[0] = args.trace_from
    seeds = args.seed_list or list(range(args.first, args.first + args.seeds))
    for law in args.law:
        for seed in seeds:
            events = parse_script(args.script) if args.script else schedule(seed, args.duration, args.tail, law, args.family)
            res = run(params, law, seed, events, args.duration, args.tail, trace=args.trace)
            print(f"law {law} seed {seed} {args.family} schedule: " + "; ".join(map(str, events)))
            if args.events:
                for line in res.campaign_log:
                    print("    " + line)
            for line in report(res):
                print(line, flush=True)
            if args.window:
                print(f"law {law} seed {seed}: " + after(res, *args.window), flush=True)


if __name__ == "__main__":
    main()
