"""One process per name on a bus: a bridge or controller refuses to start beside a live one of its name.

Bridges: two BeagleBones with the factory hostname ``beaglebone`` both take the default name
``beaglebone-beaglebone`` (:func:`server.cli.processes.default_instance`); joined to one hub, each
one's states and the other's answer to them alternate under one name, and a camera following the
bridge's clock, the console and the controller see one bridge restarting at 500 Hz. The board lock
(:mod:`bridge.drivers.board_lock`) keeps two bridges off one board; this keeps two bridges of one
name off one bus.

Controllers: a second ``xneck controller --instance C`` beside a running one (a lab's unit with a
fixed name started twice, or beside a manual run) was obeyed by the bridge as the same owner; the
two commanded in turn and the forces swung 10 N every tick, bounded only by the bridge's rate limit,
while the console showed one controller (audit of 2026-11-29, session 39).

:func:`check_name_free` runs after the bus is open and before the process declares its own
token. With no peer linked (a process that only listens and nobody has connected yet) there is no
one to ask and it returns at once. Otherwise it watches the name's liveliness token (with its
history) and the name's traffic (:data:`EVIDENCE`: a bridge's motor states, a controller's
commands, either's health) for :data:`WATCH_S`:

- traffic of the name: another process of that name is running, refused;
- the token alive, no traffic yet: wait up to :data:`LEASE_WAIT_S` for traffic (refused) or for the
  token to go (a process cut off without a goodbye keeps its token until Zenoh's lease ends: then
  start); a token that neither goes nor speaks, not even its health (about 1 Hz), is a hung process
  or a lockstep twin waiting for its controller, refused too;
- nothing: the name is free.

A race remains: two processes of one name started within the same :data:`WATCH_S` both start.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import zenoh

from bridge import bus
from bridge.session import payload_of, replayed

#: s: how long a process watches for another of its name once it has a peer. States and commands
#: come at 500 Hz and a linked peer's token within 5-15 ms (measured on loopback through a hub,
#: session 39).
WATCH_S = 0.3
#: s: how long a token without traffic may take to vanish: Zenoh's link lease (10 s) and a margin.
LEASE_WAIT_S = 12.0


def _state_of(name: str) -> Callable[[zenoh.Sample], bool]:
    def match(sample: zenoh.Sample) -> bool:
        return bus.decode(bus.MotorState, payload_of(sample, bus.MotorState)).bridge == name
    return match


def _command_of(name: str) -> Callable[[zenoh.Sample], bool]:
    def match(sample: zenoh.Sample) -> bool:
        return bus.decode(bus.ForceCommand, payload_of(sample, bus.ForceCommand)).sender == name
    return match


#: Per process kind: (key, what it says in the refusal, the sample's test given the name).
EVIDENCE: dict[str, tuple[tuple[str, str, Callable[[str], Callable[[zenoh.Sample], bool]]], ...]] = {
    "bridge": ((bus.MOTOR_STATE, "its motor states arrive", _state_of),),
    "controller": ((bus.MOTOR_COMMAND, "its force commands arrive", _command_of),),
}


class NameTaken(RuntimeError):
    """Another process of this kind holds this name on the bus; the message says what to do."""


def check_name_free(session: zenoh.Session, name: str, *, kind: str = "bridge", watch_s: float = WATCH_S,
                    lease_wait_s: float = LEASE_WAIT_S, stop: threading.Event | None = None) -> None:
    """Return when no other ``kind`` process (``bridge`` or ``controller``) named ``name`` is on the
    bus of ``session``; raise :class:`NameTaken` when one is (module docstring). Blocks at most
    ``watch_s`` when the name is free and ``watch_s + lease_wait_s`` (s) when a silent token holds it;
    returns at once once ``stop`` is set (a SIGTERM during the wait: the caller then stops)."""
    if kind not in EVIDENCE:
        raise ValueError(f"no name check for a {kind!r} (one of {', '.join(EVIDENCE)})")
    if not name or not list(session.info.peers_zid()):
        return
    heard: list[str] = []  # what of the name's traffic arrived (first first)
    spoke = threading.Event()
    token = {"alive": False}

    def listener(what: str, test: Callable[[zenoh.Sample], bool]) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            if replayed(sample):
                return  # a replay republishes a recorded process's messages under its name: not that process
            try:
                if not test(sample):
                    return
            except bus.BusDecodeError:
                return  # a malformed message is the recorder's and the console's business, not a name's
            heard.append(what)
            spoke.set()
        return on_sample

    def on_token(sample: zenoh.Sample) -> None:
        token["alive"] = sample.kind == zenoh.SampleKind.PUT

    evidence = [(key, what, make(name)) for key, what, make in EVIDENCE[kind]]
    evidence.append((bus.health_key(kind, name), "its health arrives", lambda _sample: True))
    subs = [session.declare_subscriber(key, listener(what, test)) for key, what, test in evidence]
    subs.append(session.liveliness().declare_subscriber(bus.liveliness_key(kind, name), on_token, history=True))
    try:
        if not spoke.wait(watch_s):
            if not token["alive"]:
                return
            deadline = time.monotonic() + lease_wait_s
            while token["alive"] and not spoke.wait(0.05) and time.monotonic() < deadline:
                if stop is not None and stop.is_set():
                    return
            if not token["alive"] and not spoke.is_set():
                return
        why = heard[0] if heard else (
            f"it holds the name but sent nothing for {watch_s + lease_wait_s:.0f} s: a hung process"
            + (", or a lockstep twin waiting for its controller" if kind == "bridge" else ""))
        hint = " (two boards with the factory hostname take the same default name)" if kind == "bridge" else ""
        raise NameTaken(f"another {kind} named {name!r} is on this bus ({why}): stop it first, or start this one "
                        f"with --instance NAME{hint}; docs/bridge.md, deployment")
    finally:
        for sub in subs:
            sub.undeclare()


__all__ = ["EVIDENCE", "LEASE_WAIT_S", "WATCH_S", "NameTaken", "check_name_free"]
