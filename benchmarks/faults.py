"""Fault benchmark (issue 13): the attacks of the fault table on a real `xneck up`-like stack.

    .venv/bin/python benchmarks/faults.py [--garbage-s 1.0] [--cycles 3] [--out table.md]

Starts, on 127.0.0.1, the console (``xneck server``, the hub), a twin bridge (``xneck bridge
--driver twin``, real time, 500 Hz) and the controller service (``xneck controller``) as separate
processes, exactly as ``xneck up`` does, plus an observer session linked to all three. Then it
attacks, one after the other, and prints one row per attack:

- **garbage <key>**: 10 kHz of hostile payloads (random bytes, JSON of the wrong shape, a wrong
  version, 1 MB of nesting, huge arrays) on every key a process subscribes to, for ``--garbage-s``.
  Garbage on ``xneck/estop`` must engage the e-stop (fail safe): its reaction time is that, and
  it is released afterwards; every other key must change nothing.
- **campaign under garbage**: a short real-time campaign while a flood (10 kHz, 3 s) cycles
  over every key but the e-stop; its outcome, as the console records it, must be honest.
- **forged future state**: ``MotorState``s with ``stamp_s = 1e12`` from a forged bridge at 500 Hz
  for 1 s; the controller must keep answering the real bridge (reaction: the longest pause of
  its commands from the forgery's start to 2 s after it).
- **e-stop cycle k**: engage through the console's REST API, 1 s, release, 1 s; reaction: from
  the request to the first disabled state; force step: the largest after the release (bumpless).
- **kill -9 <process>**: SIGKILL of the controller (reaction: to the bridge's hold), of the
  bridge (restarted after 1 s: the force step of its re-enable, and how soon the controller
  answers the new bridge run, recognised by its epoch), of the console (nothing may change on the
  control path); each is restarted after 1 s.

Columns: reaction time (ms, "-" when nothing should react), max force step (N per 2 ms tick, the
largest change of an applied force between two states of one bridge run in the attack's window,
divided by the ticks between them; the enable ramp's bound is 1 N per tick), data lost (``MotorState``s missing from the bridge's
sequence, and the longest gap between states), and whether every process survived.
Bounded: every attack has a fixed duration, the whole run stops after ``--budget-s`` (300 s)
and always stops every process it started. Twin only (the BeagleBone needs the robot).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import httpx
import msgspec
import numpy as np

from bridge import bus
from bridge.session import ENV_CONNECT, ENV_LISTEN, free_tcp_port, open_session
from server.child_processes import isolate, isolate_self

TOKEN = "fault-benchmark-token-0123456789"
GARBAGE_HZ = 10_000.0
N_MOTORS = 4
KEYS = [bus.MOTOR_STATE, bus.MOTOR_COMMAND, bus.CAMERA_ALPHA, bus.TWIN_TRUTH, bus.CONTROLLER_STATUS,
        bus.CAMPAIGN_EVENTS, bus.CAMPAIGN_REQUEST, bus.ESTOP]


# -- the stack -----------------------------------------------------------------------------------

@dataclass
class Stack:
    """The three processes, their endpoints and logs; :meth:`start` (re)starts one by name."""

    workdir: Path
    port: int = field(default_factory=free_tcp_port)
    hub: str = field(default_factory=lambda: f"tcp/127.0.0.1:{free_tcp_port()}")
    bridge_ep: str = ""  # Unix sockets in workdir, as xneck up's (server/cli/up.py)
    controller_ep: str = ""
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.bridge_ep = self.bridge_ep or f"unixsock-stream/{self.workdir / 'bridge.sock'}"
        self.controller_ep = self.controller_ep or f"unixsock-stream/{self.workdir / 'controller.sock'}"

    @property
    def base(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def args(self, name: str) -> list[str]:
        return {
            # xneck up's layout (server/cli/up.py): the console connects to the bridge and the
            # controller, the controller to the bridge, nothing on the control path to the console.
            "server": ["server", "--port", str(self.port), "--data-dir", str(self.workdir / "data"), "--hub", self.hub,
                       "--connect", self.bridge_ep, "--connect", self.controller_ep, "--mode", "twin"],
            "bridge": ["bridge", "--driver", "twin", "--listen", self.bridge_ep],
            "controller": ["controller", "--law", "2", "--listen", self.controller_ep, "--connect", self.bridge_ep],
        }[name]

    def start(self, name: str) -> None:
        log = open(self.workdir / f"{name}.log", "ab")  # noqa: SIM115 - the child keeps it
        env = {**{k: v for k, v in os.environ.items() if k not in (ENV_LISTEN, ENV_CONNECT)},  # as xneck up
               "XNECK_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"}
        self.procs[name] = subprocess.Popen([sys.executable, "-m", "server.cli", *self.args(name)], stdout=log,
                                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                            start_new_session=True)
        # As xneck up schedules them: the loop's processes at real-time priority on the last CPU,
        # the console off it (XNECK_REALTIME=0 leaves scheduling alone).
        isolate(self.procs[name].pid, name)

    def kill9(self, name: str) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.procs[name].pid, signal.SIGKILL)
        self.procs[name].wait(10)

    def alive(self) -> dict[str, bool]:
        return {n: p.poll() is None for n, p in self.procs.items()}

    def stop(self) -> None:
        for name in ("controller", "bridge", "server"):
            p = self.procs.get(name)
            if p is not None and p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs.values():
            try:
                p.wait(8)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)

    def healthy(self) -> bool:
        try:
            return httpx.get(self.base + "/api/system/health", timeout=1).status_code == 200
        except httpx.HTTPError:
            return False


# -- what the bus shows --------------------------------------------------------------------------

class Observer:
    """Every MotorState and ForceCommand with its receive time (``time.monotonic()``)."""

    def __init__(self, session) -> None:
        self._lock = threading.Lock()
        self.states: list[tuple[float, bus.MotorState]] = []
        self.commands: list[tuple[float, bus.ForceCommand]] = []
        self._subs = [session.declare_subscriber(bus.MOTOR_STATE, self._on(bus.MotorState, self.states)),
                      session.declare_subscriber(bus.MOTOR_COMMAND, self._on(bus.ForceCommand, self.commands))]

    def _on(self, msg_type, into):
        def callback(sample) -> None:
            now = time.monotonic()
            try:
                msg = bus.decode(msg_type, sample.payload.to_bytes())
            except bus.BusDecodeError:
                return  # our own garbage, or a forgery of another version
            with self._lock:
                into.append((now, msg))
        return callback

    def window(self, t0: float, t1: float) -> tuple[list, list]:
        with self._lock:
            return ([s for s in self.states if t0 <= s[0] <= t1], [c for c in self.commands if t0 <= c[0] <= t1])

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()


def _bridge_of(msg: bus.MotorState) -> str:
    return str(getattr(msg, "epoch", "") or getattr(msg, "bridge", "") or "")


def force_step(states: list) -> tuple[float, str]:
    """Largest change of one applied force per tick of the same bridge run (over the ticks between
    two received states, when some were lost on the way), except into ``disabled``: the drives
    off (zero torque) is the e-stop's purpose, not a step. Also says where: the drive states
    before and after it."""
    step, where = 0.0, ""
    prev: dict[str, tuple[int, np.ndarray, str]] = {}
    for _, m in states:
        key = _bridge_of(m)
        f = np.asarray(m.force_applied_N, dtype=float)
        if key in prev and m.seq > prev[key][0] and m.drive != "disabled":
            ticks = m.seq - prev[key][0]
            change = float(np.max(np.abs(f - prev[key][1]))) / ticks
            if change > step:
                step, where = change, f"{prev[key][2]}→{m.drive}"
        prev[key] = (m.seq, f, m.drive)
    return step, where


def data_lost(states: list) -> str:
    """Missing states of each bridge run's sequence and the longest gap between any two states.
    Without an epoch (contract v1) a jump back of ``seq`` starts a new run."""
    missing = 0
    last: dict[str, int] = {}
    for _, m in states:
        key = _bridge_of(m)
        if key in last and m.seq > last[key] + 1:
            missing += m.seq - last[key] - 1
        last[key] = m.seq if key not in last or m.seq < last[key] - 1000 else max(m.seq, last[key])
    gaps = np.diff([t for t, _ in states]) if len(states) > 1 else np.array([0.0])
    return f"{missing} states, gap {1e3 * float(gaps.max()):.0f} ms"


# -- hostile payloads ----------------------------------------------------------------------------

def hostile_payloads(rng: random.Random) -> tuple[list[bytes], list[bytes]]:
    """(small, big) hostile payloads; a big one goes out every :data:`BIG_EVERY` messages, so the
    flood tests the receivers' parsing, not the loopback's bandwidth."""
    small = [
        bytes(rng.getrandbits(8) for _ in range(64)),
        b"",
        b"null",
        b'{"v": 1}',
        b'{"v": 999, "seq": 1, "stamp_s": 0}',
        b'{"v": 1, "seq": "x", "stamp_s": 1e999}',
        json.dumps({"v": 1, "seq": 1, "stamp_s": 0.0, "force_N": [1e9] * 4, "source": "x"}).encode(),
        json.dumps({"v": 2, "seq": 1, "stamp_s": 0.0, "force_N": [float("nan")] * 4}).encode(),
    ]
    big = [b"[" * 10_000 + b"]" * 10_000,
           json.dumps({"v": 2, "seq": 1, "stamp_s": 0.0, "force_N": [0.0] * 10_000, "source": "x"}).encode()]
    return small, big


BIG_EVERY = 100


def flood(session, key: str, duration_s: float, rate_hz: float, payloads: tuple[list[bytes], list[bytes]]) -> int:
    """Put hostile payloads on ``key`` (comma-separated keys: in turn) at ``rate_hz`` for
    ``duration_s``; returns the number sent."""
    small, big = payloads
    pubs = [session.declare_publisher(k) for k in key.split(",")]
    sent, t0 = 0, time.monotonic()
    try:
        while (now := time.monotonic()) - t0 < duration_s:
            due = int((now - t0) * rate_hz)
            while sent < due:
                pubs[sent % len(pubs)].put(big[sent // BIG_EVERY % len(big)] if sent % BIG_EVERY == 0
                                           else small[sent % len(small)])
                sent += 1
            time.sleep(0.0005)
    finally:
        for pub in pubs:
            pub.undeclare()
    return sent


def flood_from_another_process(endpoints: list[str], key: str, duration_s: float) -> tuple[float, int]:
    """:func:`flood` from a child process with its own session (an attacker is another process,
    and this one's observer must not starve under the flooding loop): (start, messages sent), the
    start in ``time.monotonic()``, which is one clock for every process on Linux."""
    out = subprocess.run([sys.executable, __file__, "--flood", key, "--garbage-s", str(duration_s),
                          *[a for e in endpoints for a in ("--connect", e)]],
                         capture_output=True, text=True, timeout=duration_s + 60, check=True)
    report = json.loads(out.stdout.strip().splitlines()[-1])
    return float(report["start"]), int(report["sent"])


def _flood_main(args: argparse.Namespace) -> None:
    with open_session(listen=["tcp/127.0.0.1:0"], connect=args.connect) as s:
        time.sleep(0.5)  # let the session link to its peers
        start = time.monotonic()
        sent = flood(s, args.flood, args.garbage_s, GARBAGE_HZ, hostile_payloads(random.Random(13)))
    print(json.dumps({"start": start, "sent": sent}))


def forged_state(seq: int) -> bus.MotorState:
    """A well-formed MotorState from the future and from no real bridge (v1 or v2 of the contract)."""
    names = {f.name for f in msgspec.structs.fields(bus.MotorState)}
    kw = {"seq": seq, "stamp_s": 1e12, "theta_rad": [0.3] * N_MOTORS, "force_applied_N": [80.0] * N_MOTORS,
          "drive": "active"}
    kw.update({k: v for k, v in (("epoch", "forged"), ("bridge", "forged-bridge")) if k in names})
    return bus.MotorState(**kw)


# -- the run -------------------------------------------------------------------------------------

@dataclass
class Row:
    attack: str
    reaction_ms: str
    step: tuple[float, str]  # N per tick, and between which drive states
    lost: str
    survived: str


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{1e3 * seconds:.0f}"


def first_after(states: list, t0: float, predicate) -> float | None:
    for t, m in states:
        if t >= t0 and predicate(m):
            return t - t0
    return None


def longest_pause(commands: list, t0: float, t1: float) -> float:
    times = [t0] + [t for t, _ in commands if t0 <= t <= t1] + [t1]
    return float(np.max(np.diff(times)))


def run(args: argparse.Namespace) -> list[Row]:
    deadline = time.monotonic() + args.budget_s
    rows: list[Row] = []
    workdir = Path(tempfile.mkdtemp(prefix="xneck-faults-"))
    stack = Stack(workdir)
    auth = {"Authorization": f"Bearer {TOKEN}"}

    def wait(predicate, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not predicate():
            if time.monotonic() > end:
                raise RuntimeError(f"{what} within {timeout_s:.0f} s (logs in {workdir})")
            time.sleep(0.1)

    def survived() -> str:
        dead = [n for n, a in stack.alive().items() if not a]
        return "all" if not dead else "DIED: " + ", ".join(dead)

    def estop(engaged: bool) -> None:
        httpx.post(stack.base + "/api/system/estop", json={"engaged": engaged, "reason": "benchmark"}, headers=auth,
                   timeout=5)

    def driven(obs: Observer, timeout_s: float, what: str) -> None:
        wait(lambda: any(m.drive == "active" for _, m in obs.window(time.monotonic() - 0.3, time.monotonic())[0]),
             timeout_s, what)

    def baseline(s, obs: Observer) -> None:
        t0 = time.monotonic()
        time.sleep(1.0)
        states, _ = obs.window(t0, time.monotonic())
        rows.append(Row("baseline (1 s, holding)", "-", force_step(states), data_lost(states), survived()))

    def garbage(key: str):
        def attack(s, obs: Observer) -> None:
            t0, sent = flood_from_another_process([stack.hub, stack.bridge_ep, stack.controller_ep], key,
                                                  args.garbage_s)
            time.sleep(0.3)
            reaction = None
            if key == bus.ESTOP:  # fail safe: it engages; released by the console afterwards
                reaction = first_after(obs.window(t0, time.monotonic())[0], t0, lambda m: m.drive == "disabled")
                estop(False)
                driven(obs, 20, "the drives did not come back after the e-stop release")
                time.sleep(0.5)
            states, _ = obs.window(t0, time.monotonic())
            rows.append(Row(f"garbage {key} ({sent / args.garbage_s / 1e3:.1f} kHz)", _ms(reaction),
                            force_step(states), data_lost(states), survived()))
        return attack

    def campaign_under_garbage(s, obs: Observer) -> None:
        """A real-time campaign while every key but the e-stop is flooded: its outcome must be
        honest (``finished`` or ``degraded`` with reasons; aborted only with a reason)."""
        body = {"kind": "control", "law": 2, "waypoints": {"name": "gentle", "durations_s": 2.0, "dwell_s": 0.3,
                                                           "waypoints_deg": [[0, 0, 0], [8, 6, 4], [0, 0, 0]]}}
        r = httpx.post(stack.base + "/api/campaigns", json=body, headers=auth, timeout=120)
        if r.status_code != 201:
            rows.append(Row(f"campaign under garbage: refused {r.status_code}", "-", (0.0, ""), "-", survived()))
            return
        cid = r.json()["id"]
        rec: dict = {}

        def ended() -> bool:
            rec.update(httpx.get(f"{stack.base}/api/campaigns/{cid}", timeout=5).json())
            return rec["status"] != "running"

        wait(lambda: ended() or rec["progress"] > 0.05, 60, "the campaign did not start")
        t0, _ = flood_from_another_process([stack.hub, stack.bridge_ep, stack.controller_ep],
                                           ",".join(k for k in KEYS if k != bus.ESTOP), 3.0)
        wait(ended, 60, "the campaign did not end")
        states, _ = obs.window(t0, time.monotonic())
        why = "; ".join((rec.get("quality") or {}).get("reasons") or []) or rec.get("message", "")[:80]
        rows.append(Row(f"campaign under garbage on 7 keys (3 s): {rec['status']}" + (f" ({why})" if why else ""),
                        "-", force_step(states), data_lost(states), survived()))

    def forged(s, obs: Observer) -> None:
        pub = s.declare_publisher(bus.MOTOR_STATE)
        t0 = time.monotonic()
        k = 0
        while time.monotonic() - t0 < 1.0:
            pub.put(bus.encode(forged_state(10**9 + k)))
            k += 1
            time.sleep(0.002)
        pub.undeclare()
        time.sleep(2.0)
        states, commands = obs.window(t0, time.monotonic())
        real = [(t, m) for t, m in states if m.stamp_s < 1e9]
        rows.append(Row("forged future state (1 s, 500 Hz)", _ms(longest_pause(commands, t0, time.monotonic())),
                        force_step(real), data_lost(real), survived()))

    def estop_cycle(cycle: int):
        def attack(s, obs: Observer) -> None:
            t0 = time.monotonic()
            estop(True)
            time.sleep(1.0)
            t_release = time.monotonic()
            estop(False)
            time.sleep(1.0)
            states, _ = obs.window(t0, time.monotonic())
            after = [x for x in states if x[0] >= t_release]
            rows.append(Row(f"e-stop cycle {cycle} (1 s engaged)", _ms(first_after(states, t0, lambda m: m.drive == "disabled")),
                            force_step(after), data_lost(states), survived()))
        return attack

    def kill(name: str):
        def attack(s, obs: Observer) -> None:
            t0 = time.monotonic()
            stack.kill9(name)
            time.sleep(1.0)
            states, _ = obs.window(t0, time.monotonic())
            reaction = first_after(states, t0, lambda m: m.drive == "hold") if name == "controller" else None
            t_restart = time.monotonic()
            stack.start(name)
            if name == "server":
                wait(stack.healthy, 60, "the console did not come back")
            driven(obs, 90, f"the drives did not come back after restarting the {name}")
            time.sleep(1.0)
            states, _ = obs.window(t0, time.monotonic())
            rows.append(Row(f"kill -9 {name} (restarted after 1 s)", _ms(reaction), force_step(states),
                            data_lost(states), survived()))
            if name == "bridge":  # how soon the controller answers the new bridge run
                new = [x for x in states if x[0] >= t_restart]
                first_new = new[0][0] if new else t_restart
                cmds = obs.window(first_new, time.monotonic())[1]
                rows.append(Row("  controller answers the restarted bridge", _ms((cmds[0][0] - first_new) if cmds else None),
                                force_step(new), data_lost(new), survived()))
        return attack

    # The campaign first: an e-stop lets the twin's neck fall (no cable tension), and the controller
    # then holds with "diverging estimate" until a person looks (as on the robot).
    attacks = [("baseline", baseline), ("garbage campaign", campaign_under_garbage),
               *[(f"garbage {k}", garbage(k)) for k in KEYS], ("forged", forged),
               *[(f"estop cycle {c + 1}", estop_cycle(c + 1)) for c in range(args.cycles)],
               *[(f"kill {n}", kill(n)) for n in ("controller", "bridge", "server")]]
    try:
        stack.start("server")
        wait(stack.healthy, 60, "the console did not answer")
        stack.start("bridge")
        stack.start("controller")
        with open_session(listen=["tcp/127.0.0.1:0"], connect=[stack.hub, stack.bridge_ep, stack.controller_ep]) as s:
            obs = Observer(s)
            driven(obs, 90, "the bridge was not driven by the controller")
            time.sleep(1.0)
            for name, attack in attacks:
                if args.only not in name:
                    continue
                if time.monotonic() > deadline:
                    print(f"stopped early: budget of {args.budget_s:.0f} s spent", file=sys.stderr)
                    break
                attack(s, obs)
            obs.close()
    finally:
        stack.stop()
    return rows


def table(rows: list[Row]) -> str:
    out = ["| attack | reaction (ms) | max force step (N/tick, where) | data lost | processes |",
           "|---|---:|---|---|---|"]
    out += [f"| {r.attack} | {r.reaction_ms} | {r.step[0]:.2f} ({r.step[1] or '-'}) | {r.lost} | {r.survived} |"
            for r in rows]
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--garbage-s", type=float, default=1.0, help="Duration of each garbage flood (s).")
    parser.add_argument("--cycles", type=int, default=3, help="E-stop cycles.")
    parser.add_argument("--budget-s", type=float, default=300.0, help="Stop after this long whatever happens (s).")
    parser.add_argument("--only", default="", help="Run only the attacks whose name contains this (e.g. kill).")
    parser.add_argument("--flood", default="", help=argparse.SUPPRESS)  # the child of a garbage attack
    parser.add_argument("--connect", action="append", default=[], help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, default=None, help="Also write the table (Markdown) here.")
    args = parser.parse_args()
    if args.flood:
        _flood_main(args)
        return
    isolate_self("up")  # the observer as xneck up itself: off the loop's CPU
    rows = run(args)
    text = table(rows)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
