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
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import transition_fuzz as tf
from transition_fuzz import DT, SKEW_S, TRACE_FROM, Event, after, report, run

from twin.model.params import load_params


def ev(k: int, kind: str, arg=None, arg2=None) -> Event:
    return Event(k, kind, arg, arg2)


def schedule(seed: int, duration_s: float, tail_s: float, law: int, family: str = "all") -> list[Event]:
    rng = np.random.default_rng(10_000 + seed)
    n = round(duration_s / DT)
    events: list[Event] = []

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


def parse_script(text: list[str]) -> list[Event]:
    """tf.parse_script words plus ``foreign:G,D,L[,jog]@s`` (ms), ``ctlrestart:R@s``,
    ``bridgerestart:R@s`` (ms), ``clock:S@s`` (s), ``start_law:L@s``, ``start_tmin@s``, ``stopother@s``."""
    out: list[Event] = []
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
