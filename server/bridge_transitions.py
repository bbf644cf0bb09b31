"""Transitions of the bridges' reported state, for the safety journal (:mod:`server.safety_journal`).

The console takes the newest ``MotorState`` off its bus subscription every
:data:`server.live.STATE_SAMPLE_PERIOD_S` (0.1 s; :class:`server.live.LiveBus`) and hands it to
:meth:`BridgeTransitions.observe`, which compares what the state says of the drives with what the
same bridge run said last: one identity test for a state already seen, one tuple comparison for a
new one, and a line only when something changed. It sees what the console sees: a state that
lasted less than the sampling period may be missed (the bridge's log and a campaign's archive have
every one), and with several bridges on the bus each is seen when its state is the newest.

What is compared, per bridge run (``bridge``, the instance name; ``epoch``, the run's random id,
new at each start): ``estop_engaged`` and ``estop_reason`` (the bridge's latched e-stop and why),
``drive`` (``active``, ``hold``, ``inactive``, ``disabled``: :data:`bridge.bus.DriveState`) and
``hold_reason`` (why it holds; beside ``inactive`` or ``hold``, also the commands it refuses as
answering no recent state, for a second after the last: :class:`bridge.bus.MotorState`). Events handed to ``emit(event, fields)``:

- ``bridge_run``: a run seen for the first time (a bridge started or restarted; ``previous_epoch``
  names the run of the same bridge seen before it, "" if none), with its state;
- ``bridge_state``: a run's state changed; ``changed`` lists what (``estop``, ``estop_reason``,
  ``drive``, ``hold_reason``), ``was`` the state written before.

Every event carries ``bridge``, ``epoch``, the state's four fields, ``bridge_stamp_s`` (the state's
own ``stamp_s``, seconds on the bridge's clock) and ``suppressed``: the transitions of this run
seen since its previous line that this line does not show (0: it shows the one there was; a
``bridge_state`` with ``changed`` empty and ``suppressed`` > 0: the state flapped and came back).

The bus is hostile: any peer may publish states. Text from it is cut and cleaned
(:func:`bridge.bus.plain_text`: bridge and epoch to :data:`NAME_MAX_CHARS`, reasons to
:data:`REASON_MAX_CHARS`); at most :data:`MAX_RUNS` runs are remembered (the least recently seen
is forgotten, counted in :attr:`BridgeTransitions.runs_forgotten`); and lines are rate-limited
per bridge name (:data:`BURST_LINES` at once, then :data:`LINES_PER_S`) and in all
(:data:`ALL_BURST_LINES`, :data:`ALL_LINES_PER_S`: forged names each have a bucket of their own).
A transition over the limit is not written: it is counted, and the run's state as it is then is
written once the limit allows (coalesced), with that count in ``suppressed``; a forged peer
flipping a state at 500 Hz thus writes a few lines a second, not 500.

Lines owed are paid in the order they became owed (the oldest debt first), except that a known
run's e-stop change (``estop_engaged`` or ``estop_reason``) goes before all others: a forger
announcing new runs faster than the limit writes their first lines cannot delay a bridge's
e-stop engage or release by more than a line or two (review of session 43: the runs seen least
recently were paid first, and a live bridge, always the most recent, was starved). A run
forgotten while its line is owed counts that line's transitions, its first line included, in
:attr:`BridgeTransitions.suppressed`; :meth:`BridgeTransitions.status` says how many lines are
owed now and how long the oldest has waited.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from bridge import bus

NAME_MAX_CHARS = 64  # bridge instance names and epochs as journalled
REASON_MAX_CHARS = 200  # e-stop and hold reasons as journalled
MAX_RUNS = 16  # bridge runs remembered (a flood of forged epochs stays bounded)
BURST_LINES = 5.0  # lines one bridge name may write at once (a start: run, active, hold, e-stop...)
LINES_PER_S = 1.0  # then lines per second per bridge name
ALL_BURST_LINES = 20.0  # lines all bridges may write at once
ALL_LINES_PER_S = 4.0  # then lines per second in all

#: What a state says of the drives: (estop_engaged, estop_reason, drive, hold_reason).
Look = tuple[bool, str, str, str]
CHANGES = ("estop", "estop_reason", "drive", "hold_reason")  # the names of Look's fields in ``changed``


def look_of(state: bus.MotorState) -> Look:
    return state.estop_engaged, state.estop_reason, state.drive, state.hold_reason


def look_fields(look: Look) -> dict[str, Any]:
    """A look as journalled, its text cleaned and cut."""
    return {"estop_engaged": look[0], "estop_reason": bus.plain_text(look[1], REASON_MAX_CHARS),
            "drive": bus.plain_text(look[2], NAME_MAX_CHARS), "hold_reason": bus.plain_text(look[3], REASON_MAX_CHARS)}


class Bucket:
    """A token bucket: ``burst`` lines at once, refilled at ``rate`` lines a second (``clock``: s)."""

    def __init__(self, burst: float, rate: float, now: float) -> None:
        self.burst, self.rate = burst, rate
        self.tokens, self.at = burst, now

    def _refill(self, now: float) -> None:
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now

    def ready(self, now: float) -> bool:
        self._refill(now)
        return self.tokens >= 1.0

    def take(self) -> None:
        self.tokens -= 1.0


@dataclass
class _Run:
    look: Look  # as the newest state seen says
    written: Look | None  # as the last line written said (None: the run's first line is owed)
    stamp_s: float  # the newest state's stamp_s (bridge clock, s)
    seen: float  # clock time of the newest state seen (s)
    previous_epoch: str = ""  # the same bridge's run seen before this one ("" if none)
    transitions: int = 0  # transitions seen since the run's last line (its first: before it)
    owed: bool = False  # a line is owed (rate-limited so far)
    owed_since: float = 0.0  # clock time the owed line became owed (s; meaningless unless owed)
    estop_changed: bool = False  # a known run's e-stop changed since its last line: its owed line goes first
    keys: tuple[str, str] = field(default=("", ""))  # (bridge, epoch) as received


class BridgeTransitions:
    """Detects the transitions of each bridge run's state (module docstring) and hands each to
    ``emit(event, fields)`` (:meth:`server.safety_journal.SafetyJournal.record`: it must not
    block). ``clock``: seconds, monotonic. Called from one thread (the state sampler); a lock
    keeps it right if it is not."""

    def __init__(self, emit: Callable[..., None], clock: Callable[[], float] = time.monotonic,
                 max_runs: int = MAX_RUNS) -> None:
        self._emit = emit
        self._clock = clock
        self.max_runs = max_runs
        self._lock = threading.Lock()
        self._last: bus.MotorState | None = None  # the state observed last (the sampler sees it again and again)
        self._runs: dict[tuple[str, str], _Run] = {}
        self._owed: dict[tuple[str, str], None] = {}  # runs owed a line, in the order they became owed
        self._buckets: dict[str, Bucket] = {}  # bridge name -> its bucket (at most max_runs)
        self._all = Bucket(ALL_BURST_LINES, ALL_LINES_PER_S, clock())
        self.suppressed = 0  # transitions no line shows, in all (a forgotten run's owed ones too)
        self.runs_forgotten = 0  # runs forgotten to keep max_runs

    def status(self) -> dict[str, Any]:
        """``suppressed``, ``runs_forgotten`` (since start); ``owed``, the lines owed now (rate-limited
        so far) and ``oldest_owed_s``, how long the oldest of them has waited (s; null if none)."""
        with self._lock:
            oldest = next(iter(self._owed), None)
            waited = None if oldest is None else round(self._clock() - self._runs[oldest].owed_since, 3)
            return {"suppressed": self.suppressed, "runs_forgotten": self.runs_forgotten, "owed": len(self._owed),
                    "oldest_owed_s": waited}

    def observe(self, state: bus.MotorState) -> None:
        """The newest state the console has of a bridge (the same object again while none newer came)."""
        with self._lock:
            if state is self._last:  # the common case, 10 times a second: nothing new
                if self._owed:
                    self._pay(self._clock())
                return
            self._last = state
            key, look, now = (state.bridge, state.epoch), look_of(state), self._clock()
            run = self._runs.get(key)
            if run is not None:
                run.seen, run.stamp_s = now, state.stamp_s
                if look != run.look:
                    if look[:2] != run.look[:2] and run.written is not None:
                        run.estop_changed = True
                    run.look = look
                    run.transitions += 1
                    self._owe(key, run, now)
            else:
                self._runs[key] = run = _Run(look, None, state.stamp_s, now, self._previous_epoch(state.bridge),
                                             keys=key)
                self._forget_beyond(key)
                self._owe(key, run, now)
            if self._owed:
                self._pay(now)

    def _previous_epoch(self, bridge: str) -> str:
        runs = [r for r in self._runs.values() if r.keys[0] == bridge]
        return max(runs, key=lambda r: r.seen).keys[1] if runs else ""

    def _owe(self, key: tuple[str, str], run: _Run, now: float) -> None:
        if not run.owed:  # a line still owed keeps its place: this transition is folded into it
            run.owed, run.owed_since = True, now
            self._owed[key] = None

    @staticmethod
    def _suppressed(run: _Run) -> int:
        """The run's transitions since its last line that the line owed does not show: all but
        the one from the state written last to the state now, if they differ."""
        shown = 1 if run.written is not None and run.written != run.look else 0
        return run.transitions - shown

    def _forget_beyond(self, keep: tuple[str, str]) -> None:
        while len(self._runs) > self.max_runs:
            oldest = min((k for k in self._runs if k != keep), key=lambda k: self._runs[k].seen)
            gone = self._runs.pop(oldest)
            if gone.owed:  # its owed line is never written: all its transitions since are lost,
                # its first appearance too if that line was the one owed
                self.suppressed += gone.transitions + (gone.written is None)
            self._owed.pop(oldest, None)
            self.runs_forgotten += 1
        names = {k[0] for k in self._runs}
        for name in [n for n in self._buckets if n not in names]:
            del self._buckets[name]

    def _pay(self, now: float) -> None:
        """Write the lines owed that the buckets allow: the known runs' e-stop changes first, then
        the oldest debt first (module docstring)."""
        urgent = [k for k in self._owed if self._runs[k].estop_changed]
        for key in [*urgent, *(k for k in self._owed if not self._runs[k].estop_changed)]:
            if not self._all.ready(now):
                return
            run = self._runs[key]
            bucket = self._buckets.get(key[0])
            if bucket is None:
                bucket = self._buckets[key[0]] = Bucket(BURST_LINES, LINES_PER_S, now)
            if not bucket.ready(now):
                continue
            bucket.take()
            self._all.take()
            suppressed = self._suppressed(run)
            self.suppressed += suppressed
            self._line(run, suppressed)
            run.written, run.transitions, run.owed, run.estop_changed = run.look, 0, False, False
            del self._owed[key]

    def _line(self, run: _Run, suppressed: int) -> None:
        fields: dict[str, Any] = {"bridge": bus.plain_text(run.keys[0], NAME_MAX_CHARS),
                                  "epoch": bus.plain_text(run.keys[1], NAME_MAX_CHARS), **look_fields(run.look),
                                  "bridge_stamp_s": run.stamp_s if math.isfinite(run.stamp_s) else None,
                                  "suppressed": suppressed}
        if run.written is None:
            self._emit("bridge_run", previous_epoch=bus.plain_text(run.previous_epoch, NAME_MAX_CHARS), **fields)
            return
        was = run.written
        changed = [name for name, a, b in zip(CHANGES, was, run.look, strict=True) if a != b]
        self._emit("bridge_state", changed=changed, was=look_fields(was), **fields)
