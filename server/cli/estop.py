"""`xneck estop engage|release|status`: the e-stop from a terminal, beside the console's button.

The same e-stop as the console's (docs/safety.md, "E-stop"): this command is an e-stop holder
(:class:`bridge.estop_holder.EStopHolder`). It connects straight to the bridge (or to the hub of
an ``xneck up`` stack), so it works when the console is down or hung, over SSH, or from a script
a lab wires to a button on the PC. Every answer is the bridges' own word: their ``MotorState``
(``estop_engaged``, ``drive``) heard after the message went out, never what was sent.

- ``engage`` ends once a bridge has confirmed (exit 0), or after ``--wait-s`` with none (exit 1:
  the e-stop reached no bridge). With ``--hold`` it then keeps holding the e-stop until Ctrl-C or
  SIGTERM, so a bridge that starts or links back meanwhile starts latched. On leaving, the
  bridges latched stay latched (a holder that goes releases nothing).
- ``release`` lets go of the e-stop; a bridge obeys only when no other holder is left (the
  console's engaged button holds it): it then names the holders, exit 1.
- ``status`` prints each bridge's e-stop and drive, and the holders alive on the bus.

No command succeeds (exit 1) when more than 16 bridges answer (``crowded``: made-up ones may hide
the robot's) or two runs (epochs) answer under one name (``conflict``); a state whose bridge name
or run id is no instance name is ignored and counted (audit of session 42).
"""

from __future__ import annotations

import contextlib
import faulthandler
import re
import signal
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import typer

from server.cli.options import check_credentials, echo_json, fail, open_bus

#: Where ``xneck up`` puts its hub: the e-stop's default when neither --connect nor the environment names one.
DEFAULT_HUB = "tcp/127.0.0.1:7447"
QUERY_TIMEOUT_S = 1.0  # s: the liveliness query for the holders alive
CLOSE_WAIT_S = 1.0  # s the session's close is waited for (_bus)
SETTLE_S = 0.3  # s an answer listens at least: every bridge on the bus states 150 times meanwhile (send_until)

CONNECT_OPTION = typer.Option(
    None, "--connect", help="Zenoh endpoint of the robot's bridge (best: fewest hops; repeatable). Default: the "
    "bridge of the `xneck up` you run (printed at its start; with several, engage reaches each, release and status "
    f"ask for --connect), else $XNECK_ZENOH_CONNECT, else {DEFAULT_HUB}.")
WAIT_OPTION = typer.Option(3.0, "--wait-s", min=0.1, max=60.0,
                           help="How long to wait for the bridges' answer, in seconds.")
JSON_OPTION = typer.Option(False, "--json", help="Print the outcome as JSON.")

estop_app = typer.Typer(help="The e-stop from a terminal (the console's e-stop): engage, release, status.",
                        no_args_is_help=True, add_completion=False)


@dataclass(frozen=True)
class BridgeWord:
    """What one bridge run's latest ``MotorState`` says of the e-stop, and when it arrived
    (monotonic s). ``conflict``: another run (epoch) answered under the same name in this listen."""

    bridge: str
    engaged: bool
    reason: str
    drive: str
    owner: str
    heard_s: float
    epoch: str = ""
    conflict: bool = False
    first_s: float = 0.0  # when this run was first heard (monotonic s)

    def line(self) -> str:
        estop = f"e-stop engaged ({self.reason})" if self.engaged else "e-stop released"
        return (f"bridge {self.bridge}: {estop}, drives {self.drive}" + (f", obeys {self.owner}" if self.owner else "")
                + (f" [run {self.epoch}: CONFLICT, another run answers under this name]" if self.conflict else ""))

    def to_json(self) -> dict[str, object]:
        return {"bridge": self.bridge, "engaged": self.engaged, "reason": self.reason, "drive": self.drive,
                "owner": self.owner, "epoch": self.epoch, "conflict": self.conflict}


@dataclass(frozen=True)
class Heard:
    """What a listen heard: the words of the bridges kept (:attr:`BridgeWatch.MAX_BRIDGES` names
    at most, every run of each), how many more names were heard (``unlisted``: a flooded or
    hostile bus; ``unlisted_more``: more than counted) and how many states had a name or run id
    no bridge can have (``invalid``)."""

    words: list[BridgeWord]
    listed: int = 0
    unlisted: int = 0
    unlisted_more: bool = False
    invalid: int = 0

    @property
    def conflicts(self) -> list[str]:
        """The names two runs (epochs) answered under in this listen."""
        return sorted({w.bridge for w in self.words if w.conflict})

    @property
    def crowded(self) -> bool:
        return self.unlisted > 0

    def to_json(self) -> dict[str, object]:
        return {"bridges_heard": self.listed + self.unlisted, "unlisted": self.unlisted,
                "unlisted_more": self.unlisted_more, "invalid_states": self.invalid, "conflicts": self.conflicts}


class BridgeWatch:
    """The newest ``MotorState`` of every bridge run on the bus (live ones: a replay's are
    skipped), kept from the Zenoh callback thread, for :attr:`MAX_BRIDGES` names (the first
    heard) and :attr:`MAX_RUNS` runs of each at most; the names past them are counted (up to
    :attr:`MAX_UNLISTED`), and states whose bridge name or run id is no instance name
    (``bridge.safety.INSTANCE_NAME``: a zero-width character made a near twin of the real
    bridge's name) are counted and dropped. Audit of session 42: 16 made-up bridges heard first
    took every place, the real bridge went unheard and a release reported success."""

    MAX_BRIDGES = 16
    MAX_RUNS = 4
    MAX_UNLISTED = 1024

    def __init__(self, session) -> None:
        from bridge import bus

        self._lock = threading.Lock()
        self._runs: dict[str, dict[str, BridgeWord]] = {}  # name -> epoch -> newest word
        self._unlisted: set[str] = set()
        self._unlisted_more = False
        self._invalid = 0
        self._changed = threading.Condition(self._lock)
        self._sub = session.declare_subscriber(bus.MOTOR_STATE, self._on_state)

    def _on_state(self, sample) -> None:
        from bridge import bus
        from bridge.safety import INSTANCE_NAME
        from bridge.session import replayed

        if replayed(sample):
            return
        try:
            msg = bus.decode(bus.MotorState, sample.payload.to_bytes())
        except bus.BusDecodeError:
            return
        if not (INSTANCE_NAME.fullmatch(msg.bridge) and INSTANCE_NAME.fullmatch(msg.epoch)):
            with self._lock:
                self._invalid += 1
            return
        # plain text: a peer's escape sequences must not drive the operator's terminal
        word = BridgeWord(msg.bridge, msg.estop_engaged, bus.plain_text(msg.estop_reason), msg.drive,
                          bus.plain_text(msg.owner, 64), time.monotonic(), msg.epoch)
        with self._lock:
            runs = self._runs.get(word.bridge)
            if runs is None and len(self._runs) >= self.MAX_BRIDGES:
                if word.bridge not in self._unlisted and len(self._unlisted) < self.MAX_UNLISTED:
                    self._unlisted.add(word.bridge)
                    self._changed.notify_all()
                elif word.bridge not in self._unlisted:
                    self._unlisted_more = True
                return
            runs = self._runs.setdefault(word.bridge, {})
            if (old := runs.get(word.epoch)) is not None:
                runs[word.epoch] = replace(word, first_s=old.first_s)
            else:
                if len(runs) >= self.MAX_RUNS:  # a --hold through many restarts: forget the superseded
                    runs = self._runs[word.bridge] = {w.epoch: w for w in self._current(runs)}
                if len(runs) < self.MAX_RUNS:  # past them the name is a conflict anyway
                    runs[word.epoch] = replace(word, first_s=word.heard_s)
            self._changed.notify_all()

    @staticmethod
    def _current(runs: dict[str, BridgeWord]) -> list[BridgeWord]:
        """The runs of one name still answering: a run not heard since a newer one's first state
        was superseded (a bridge restarted: systemd keeps its name), not a second process under
        its name; review of session 42: a restart during ``engage --hold`` ended as a conflict."""
        return [w for w in runs.values() if not any(o.first_s > w.heard_s for o in runs.values())]

    def _heard(self, since_s: float) -> Heard:  # under the lock
        current = [self._current(runs) for runs in self._runs.values()]
        words = [replace(w, conflict=len(ws) > 1) for ws in current for w in ws if w.heard_s > since_s]
        return Heard(sorted(words, key=lambda w: (w.bridge, w.epoch)), len(self._runs), len(self._unlisted),
                     self._unlisted_more, self._invalid)

    def heard(self, since_s: float = -1.0) -> Heard:
        """Every bridge run's newest word heard after ``since_s`` (monotonic s), by name, and the
        listen's counts (the names past the cap, the invalid states, since it began)."""
        with self._lock:
            return self._heard(since_s)

    def words(self, since_s: float = -1.0) -> list[BridgeWord]:
        """Every bridge run's newest word heard after ``since_s`` (monotonic s), by name."""
        return self.heard(since_s).words

    def wait(self, done: Callable[[Heard], bool], since_s: float, timeout_s: float) -> Heard:
        """Wait until ``done(heard)`` holds for what was heard after ``since_s``, at most
        ``timeout_s`` s; returns it (whether or not it held)."""
        end = time.monotonic() + timeout_s
        with self._lock:
            while True:
                heard = self._heard(since_s)
                left = end - time.monotonic()
                if done(heard) or left <= 0:
                    return heard
                self._changed.wait(min(left, 0.1))

    def close(self) -> None:
        self._sub.undeclare()


def send_until(watch: BridgeWatch, send: Callable[[], None], needs: Callable[[BridgeWord], bool], since_s: float,
               timeout_s: float, resend_s: float = 0.1, settle_s: float = SETTLE_S) -> Heard:
    """Call ``send`` now, and again (at most every ``resend_s`` s) while a bridge heard after
    ``since_s`` still ``needs`` it, until none does (one heard, and ``settle_s`` s gone since
    ``since_s``, so that every bridge on the bus has been heard: a second bridge, heard later,
    that did not latch had been left out of a success; review of session 41) or ``timeout_s`` s
    have passed; returns what was heard. A message published before this session has linked
    to the bridge goes nowhere (Zenoh has no route yet; the token, declared, reaches it later):
    the first test of this command had its reason lost so."""
    end = time.monotonic() + timeout_s
    settled = since_s + min(settle_s, timeout_s)
    send()
    sent_s = time.monotonic()

    def done(heard: Heard) -> bool:
        return bool(heard.words) and not any(needs(w) for w in heard.words) and time.monotonic() >= settled

    while True:
        heard = watch.wait(done, since_s, min(resend_s, max(0.0, end - time.monotonic())))
        if done(heard) or time.monotonic() >= end:
            return heard
        if any(needs(w) for w in heard.words) and time.monotonic() - sent_s >= resend_s:
            send()
            sent_s = time.monotonic()


def holders_alive(session) -> list[str]:
    """The e-stop holders whose tokens are alive on the bus (a liveliness query)."""
    from bridge import bus

    found = set()
    for reply in session.liveliness().get(bus.ESTOP_ENGAGED_ALL, timeout=QUERY_TIMEOUT_S):
        if reply.ok is not None:
            try:
                found.add(bus.parse_estop_token_key(str(reply.ok.key_expr))[:64])
            except ValueError:
                continue
    return sorted(found)


def holder_name() -> str:
    """This command's holder name: ``cli-<host>-<6 hex>`` (the host cut to the key's characters)."""
    host = re.sub(r"[^A-Za-z0-9_.\-]", "-", socket.gethostname())[:24] or "host"
    return f"cli-{host}-{uuid.uuid4().hex[:6]}"


def _endpoints(connect: list[str] | None, every_stack: bool = False) -> list[str]:
    """``--connect``, else ``$XNECK_ZENOH_CONNECT``, else the bridge of the one ``xneck up`` this
    user runs (not its hub: the console that hosts it may be what hangs; review of session 41: a
    hung console's hub reached no bridge), else :data:`DEFAULT_HUB`. With several stacks: every
    one's bridge when ``every_stack`` (an engage: reaching too many bridges is the safe side),
    else an error asking for ``--connect``."""
    from bridge.session import ENV_CONNECT, endpoints_from_env
    from server.cli.up import stack_bridge_endpoints

    given = list(connect or endpoints_from_env(ENV_CONNECT) or [])
    if given:
        return given
    stacks = stack_bridge_endpoints()
    if len(stacks) > 1 and every_stack:
        return [stacks[pid] for pid in sorted(stacks)]
    if len(stacks) > 1:
        raise fail(f"{len(stacks)} xneck up stacks run here (pids {', '.join(map(str, sorted(stacks)))}, bridges "
                   f"{', '.join(stacks[pid] for pid in sorted(stacks))}): say which bridge with --connect")
    return list(stacks.values()) or [DEFAULT_HUB]


@contextlib.contextmanager
def _bus(endpoints: list[str]) -> Iterator[Any]:
    """This command's session: it connects to ``endpoints`` and listens on an ephemeral loopback
    port whatever ``XNECK_ZENOH_LISTEN`` says (a shell of the board's, sharing the bridge's
    environment, had it bind the bridge's own port and fail: review of session 41). Its close is
    waited for :data:`CLOSE_WAIT_S` s at most: a hung peer held it 7 s after the answer."""
    session = open_bus(["tcp/127.0.0.1:0"], endpoints)
    try:
        yield session
    finally:
        closer = threading.Thread(target=session.close, daemon=True)
        closer.start()
        closer.join(CLOSE_WAIT_S)


def _report(as_json: bool, ok: bool, outcome: str, heard: Heard, holders: list[str],
            endpoints: list[str], message: str) -> None:
    """Print the outcome (``--json``: one object on stdout; else the bridges' lines, then the
    message, on stderr in red when not ``ok``); the caller exits 1 when not ``ok``. The states
    ignored for their invalid names are counted in the message."""
    if heard.invalid:
        message += f" ({heard.invalid} state(s) with an invalid bridge name or run id ignored)"
    if as_json:
        echo_json({"ok": ok, "outcome": outcome, "message": message, "bridges": [w.to_json() for w in heard.words],
                   "holders": holders, "connect": endpoints, **heard.to_json()})
        return
    for w in heard.words:
        typer.echo(w.line())
    if holders:
        typer.echo(f"e-stop holders on the bus: {', '.join(holders)}")
    typer.secho(message if ok else f"error: {message}", err=not ok, fg=None if ok else "red")


def _doubt(heard: Heard) -> tuple[str, str] | None:
    """``(outcome, why)`` when the bridges heard cannot be taken at their word, whatever each
    says: more names than :attr:`BridgeWatch.MAX_BRIDGES` (``crowded``: the robot's bridge may be
    among those not kept), or two runs under one name (``conflict``: which is the bridge?)."""
    if heard.crowded:
        count = f"{heard.listed + heard.unlisted}{'+' if heard.unlisted_more else ''}"
        return "crowded", (f"more than {BridgeWatch.MAX_BRIDGES} bridges answered ({count} names heard, "
                           f"{heard.unlisted}{'+' if heard.unlisted_more else ''} not listed): a flooded or hostile "
                           "bus, where the robot's bridge cannot be told from made-up ones: ask it on its own "
                           "endpoint (--connect tcp/<board>:7447) and find the peer flooding the bus")
    if heard.conflicts:
        return "conflict", (f"two runs (epochs) answered as bridge {', '.join(heard.conflicts)}: two processes "
                            "claim that name (or it restarted meanwhile), so its word cannot be told: stop the "
                            "impostor, or ask that bridge on its own endpoint (--connect)")
    return None


def _no_bridge(endpoints: list[str], wait_s: float) -> str:
    return (f"no bridge state heard within {wait_s:g} s through {', '.join(endpoints)}: is the bridge (or the "
            "stack) up, and is this its endpoint (--connect)?")


@estop_app.command("engage")
def engage(
    reason: str = typer.Option("", "--reason", help="Why (shown by the console and the bridge's state)."),
    hold: bool = typer.Option(False, "--hold", help="Keep holding the e-stop until Ctrl-C or SIGTERM, so that a "
                              "bridge that starts or links back meanwhile starts latched."),
    connect: list[str] | None = CONNECT_OPTION,
    wait_s: float = WAIT_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Engage the e-stop (every bridge that hears it disables its drives).

    The drives stay disabled, whatever the controller commands, until a release. Exit 0 once
    every bridge heard is latched; 1 if one heard did not latch (partial) or none answers within
    --wait-s."""
    from bridge import bus
    from bridge.estop_holder import EStopHolder
    from bridge.safety import EStopHolders

    check_credentials(acts=True)
    endpoints = _endpoints(connect, every_stack=True)
    name = holder_name()
    why = bus.plain_text(reason.strip()) or f"xneck estop engage ({name})"
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)} if hold else {}
    if hold:  # `kill -USR1 <pid>` writes every thread's stack to stderr, as `xneck up` does: where a
        # hold that does not end waits (fresh-clone CI of a2c45e1: 20 s after its SIGTERM, unexplained)
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    with _bus(endpoints) as session:
        watch, holder = BridgeWatch(session), EStopHolder(session, name)

        def needs(w: BridgeWord) -> bool:  # not latched, or latched by the token alone (no reason yet)
            return not w.engaged or w.reason == EStopHolders.reason(name)

        try:
            sent_s = time.monotonic()
            heard = send_until(watch, lambda: holder.engage(why), needs, sent_s, wait_s)
            confirmed = [w for w in heard.words if w.engaged]
            if hold:
                say = (lambda line: typer.echo(line, err=True)) if as_json else typer.echo  # --json: one object out
                say(f"holding the e-stop as {name} (Ctrl-C to let go: the bridges latched stay latched)")
                for w in confirmed:
                    say(w.line())
                seen = {(w.bridge, w.epoch) for w in confirmed}  # a restarted bridge's new run is said too
                while not stop.wait(0.2):  # the bridges that start or link back meanwhile
                    words = watch.words(sent_s)
                    if any(needs(w) for w in words):
                        holder.engage(why)  # its reason, which the token does not carry
                    for w in words:
                        if w.engaged and (w.bridge, w.epoch) not in seen and not needs(w):
                            seen.add((w.bridge, w.epoch))
                            say(w.line())
                heard = watch.heard(sent_s)  # words are never dropped: every one heard since the send
        finally:
            holder.close()
            watch.close()
            for s, handler in previous.items():
                signal.signal(s, handler)
    words = heard.words
    confirmed = [w for w in words if w.engaged and not w.conflict]
    deaf = [w.bridge for w in words if not w.engaged and not w.conflict]
    doubt = _doubt(heard)
    if doubt:  # more bridges than kept, two runs under one name: no success (audit of session 42)
        _report(as_json, False, doubt[0], heard, [], endpoints, f"e-stop sent by {name}"
                + (f", NOT latched on {', '.join(deaf)}" if deaf else "") + f"; {doubt[1]}")
        raise typer.Exit(1)
    if confirmed and not deaf:
        _report(as_json, True, "engaged", heard, [], endpoints,
                f"e-stop engaged by {name}: {len(confirmed)} bridge(s) confirmed; release with "
                "`xneck estop release` or the console's button")
        return
    if confirmed:  # a bridge heard and not latched must not pass for an e-stop done (review of session 41)
        _report(as_json, False, "partial", heard, [], endpoints,
                f"e-stop engaged on {', '.join(w.bridge for w in confirmed)} but NOT on {', '.join(deaf)} (heard, "
                f"not latched within {wait_s:g} s): cut that bridge's power or stop it")
        raise typer.Exit(1)
    _report(as_json, False, "unconfirmed", heard, [], endpoints,
            f"{_no_bridge(endpoints, wait_s) if not words else 'no bridge confirmed the e-stop'}; it "
            "latches only the bridges that heard it: use --hold to keep it held for a bridge that starts later")
    raise typer.Exit(1)


@estop_app.command("release")
def release(
    reason: str = typer.Option("", "--reason", help="Why (kept in the bridge's log)."),
    connect: list[str] | None = CONNECT_OPTION,
    wait_s: float = WAIT_OPTION,
    as_json: bool = JSON_OPTION,
) -> None:
    """Release the e-stop, unless another holder keeps it engaged.

    The bridges' drives go inactive until the controller's next command (the controller then
    takes the cables up gently). A bridge obeys only when no other holder (the console's engaged
    button, another terminal's --hold) is left. Exit 0 once every bridge heard has released, 1
    otherwise."""
    from bridge import bus
    from bridge.estop_holder import EStopHolder

    check_credentials(acts=True)
    endpoints = _endpoints(connect)
    name = holder_name()
    with _bus(endpoints) as session:
        watch, holder = BridgeWatch(session), EStopHolder(session, name)
        try:
            why = bus.plain_text(reason.strip()) or f"xneck estop release ({name})"
            heard = send_until(watch, lambda: holder.release(why), lambda w: w.engaged, time.monotonic(), wait_s,
                               resend_s=0.25)
            words, doubt = heard.words, _doubt(heard)
            holders = holders_alive(session) if any(w.engaged for w in words) or not words or doubt else []
        finally:
            holder.close()
            watch.close()
    if not words:
        _report(as_json, False, "no bridge", heard, holders, endpoints, _no_bridge(endpoints, wait_s))
        raise typer.Exit(1)
    still = [w.bridge for w in words if w.engaged]
    if doubt:  # more bridges than kept, two runs under one name: no success (audit of session 42)
        _report(as_json, False, doubt[0], heard, holders, endpoints, "release sent"
                + (f", e-stop still engaged on {', '.join(dict.fromkeys(still))}" if still else "") + f"; {doubt[1]}")
        raise typer.Exit(1)
    if still:
        held = (f"held by {', '.join(holders)}: release it there (the console's button, or stop that --hold)"
                if holders else "the bridge did not release it (see its log)")
        _report(as_json, False, "engaged", heard, holders, endpoints, f"e-stop still engaged on {', '.join(still)}: {held}")
        raise typer.Exit(1)
    _report(as_json, True, "released", heard, holders, endpoints,
            "e-stop released: the drives come back with the controller's next command (it takes up the cables' slack first)")


@estop_app.command("status")
def status(
    connect: list[str] | None = CONNECT_OPTION,
    wait_s: float = typer.Option(1.0, "--wait-s", min=0.1, max=60.0, help="How long to listen, in seconds."),
    as_json: bool = JSON_OPTION,
) -> None:
    """Show each bridge's e-stop and drives, and the e-stop holders on the bus.

    Each bridge's newest state heard within --wait-s. Exit 0 when a bridge was heard, 1 when
    none was, or more than 16 bridges answered, or two runs under one name."""
    check_credentials(acts=False)
    endpoints = _endpoints(connect)
    with _bus(endpoints) as session:
        watch = BridgeWatch(session)
        try:
            time.sleep(wait_s)
            heard, holders = watch.heard(), holders_alive(session)
        finally:
            watch.close()
    if not heard.words:
        _report(as_json, False, "no bridge", heard, holders, endpoints, _no_bridge(endpoints, wait_s))
        raise typer.Exit(1)
    engaged = list(dict.fromkeys(w.bridge for w in heard.words if w.engaged))
    doubt = _doubt(heard)
    if doubt:  # more bridges than kept, two runs under one name: their word is no status (audit of session 42)
        _report(as_json, False, doubt[0], heard, holders, endpoints,
                (f"e-stop engaged on {', '.join(engaged)}; " if engaged else "") + doubt[1])
        raise typer.Exit(1)
    _report(as_json, True, "heard", heard, holders, endpoints,
            f"e-stop engaged on {', '.join(engaged)}" if engaged else "e-stop released on every bridge heard")
