"""One bridge per name on a bus: a bridge refuses to start beside a live bridge of its name.

Two BeagleBones with the factory hostname ``beaglebone`` both take the default name
``beaglebone-beaglebone`` (:func:`server.cli.processes.default_instance`); joined to one hub, each
one's states and the other's answer to them alternate under one name, and a camera following the
bridge's clock, the console and the controller see one bridge restarting at 500 Hz. The board lock
(:mod:`bridge.drivers.board_lock`) keeps two bridges off one board; this keeps two bridges of one
name off one bus.

:func:`check_name_free` runs after the bus is open and before the bridge declares its own token.
With no peer linked (a bridge that only listens and nobody has connected yet) there is no one to
ask and it returns at once. Otherwise it watches the name's liveliness token (with its history)
and the motor states for :data:`WATCH_S`:

- a ``MotorState`` whose ``bridge`` is the name: another bridge of that name is running, refused;
- the token alive, no state: a bridge whose link was cut without a goodbye leaves its token until
  Zenoh's lease ends (10 s): wait up to :data:`LEASE_WAIT_S` for it to go (then start) or for a
  state (refused); a token that neither goes nor publishes is a hung bridge or a lockstep twin
  waiting for its controller, refused too;
- nothing: the name is free.

A race remains: two bridges of one name started within the same :data:`WATCH_S` both start.
"""

from __future__ import annotations

import threading
import time

import zenoh

from bridge import bus
from bridge.session import payload_of

#: s: how long a bridge watches for another of its name once it has a peer. States come at 500 Hz
#: and a linked peer's token within 5-15 ms (measured on loopback through a hub, session 39).
WATCH_S = 0.3
#: s: how long a token without states may take to vanish: Zenoh's link lease (10 s) and a margin.
LEASE_WAIT_S = 12.0


class NameTaken(RuntimeError):
    """Another bridge holds this name on the bus; the message says what to do."""


def check_name_free(session: zenoh.Session, name: str, *, watch_s: float = WATCH_S,
                    lease_wait_s: float = LEASE_WAIT_S) -> None:
    """Return when no other bridge named ``name`` is on the bus of ``session``; raise
    :class:`NameTaken` when one is (module docstring). Blocks at most ``watch_s`` when the name is
    free and ``watch_s + lease_wait_s`` (s) when a silent token holds it."""
    if not name or not list(session.info.peers_zid()):
        return
    seen = threading.Event()  # a state of a bridge of this name
    token = {"alive": False}

    def on_state(sample: zenoh.Sample) -> None:
        try:
            state = bus.decode(bus.MotorState, payload_of(sample, bus.MotorState))
        except bus.BusDecodeError:
            return  # a malformed state is the recorder's and the console's business, not a name
        if state.bridge == name:
            seen.set()

    def on_token(sample: zenoh.Sample) -> None:
        token["alive"] = sample.kind == zenoh.SampleKind.PUT

    subs = [session.declare_subscriber(bus.MOTOR_STATE, on_state),
            session.liveliness().declare_subscriber(bus.liveliness_key("bridge", name), on_token, history=True)]
    try:
        if seen.wait(watch_s):
            raise NameTaken(
                f"another bridge named {name!r} is on this bus (its motor states arrive): stop it first, or start "
                f"this one with --instance NAME (two boards with the factory hostname take the same default name; "
                f"docs/bridge.md, deployment)")
        if not token["alive"]:
            return
        deadline = time.monotonic() + lease_wait_s
        while token["alive"] and not seen.wait(0.05) and time.monotonic() < deadline:
            pass
        if seen.is_set() or token["alive"]:
            why = "its motor states arrive" if seen.is_set() else (
                f"it holds the name but published no motor state for {watch_s + lease_wait_s:.0f} s: a hung bridge, or "
                f"a lockstep twin waiting for its controller")
            raise NameTaken(f"another bridge named {name!r} is on this bus ({why}): stop it first, or start this one "
                            f"with --instance NAME (docs/bridge.md, deployment)")
    finally:
        for sub in subs:
            sub.undeclare()


__all__ = ["LEASE_WAIT_S", "WATCH_S", "NameTaken", "check_name_free"]
