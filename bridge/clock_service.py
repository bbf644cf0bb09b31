"""The bridge's stamp clock on the bus: the queryable the bridge serves, and one query of it.

:class:`ClockService` (the bridge): a Zenoh queryable on :data:`bridge.bus.BRIDGE_CLOCK` that
answers each query with a :class:`bridge.bus.ClockReading`: ``stamp_s`` the driver's
``stamp_s()`` at the reply, the clock of every ``MotorState.stamp_s`` (the board's wall clock for
hardware; for the twin the simulated time of its last tick, which moves only as the loop ticks).
The handler runs on a Zenoh thread beside the real-time loop: it reads the stamp (one call, no
lock), encodes one small message and replies; it reads nothing else of the loop's state. A token
bucket (:data:`RATE_PER_S` replies a second, bursts of :data:`BURST`) bounds the *replies* a peer
flooding queries gets (their encoding and sending); queries beyond it get no reply and are counted
(``refused``). It does not bound the callbacks: every query of a flood still runs :meth:`_on_query`
(the bucket's arithmetic under its lock, in Python, under the GIL of the process whose 500 Hz loop
it shares), so a flood still costs the bridge CPU and GIL time per query, refused or not (audit of
2026-11-29, its g_flood.py). Keep the bus of the robot closed to peers you do not trust.

:func:`query_clock` (the querier, a camera): one query, each reply stamped on the querier's clock
when it left (``t0``) and came back (``t1``). Replies are untrusted (any peer may declare a
queryable on the key): a payload too large, undecodable or of another version is counted with its
reason and never used; so are error replies, replies of one peer beyond :data:`MAX_PER_REPLIER`
(its Zenoh id, ``reply.replier_id``: a bridge answers once) and valid replies beyond
:data:`MAX_REPLIES`. Refused replies never use up the valid ones' room: one peer answering each
query with 16 junk replies had the bridge's reply behind them refused (audit of 2026-11-29). Each
valid reply names its replier (``ClockReply.replier``), so a run claimed by two peers is told.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh

from bridge import bus
from bridge.clock_sync import ClockSample

log = logging.getLogger("xneck.bridge")

RATE_PER_S = 200.0  # replies a second, sustained (a camera's burst of 8 every 10 s is 0.8)
BURST = 64  # replies at once
MAX_REPLIES = 16  # valid replies of one query taken (one per bridge on the bus; more is a flood)
MAX_PER_REPLIER = 2  # replies of one peer to one query looked at (a bridge sends one)
MAX_REASONS = 16  # refusal reasons kept per query (all are counted)


class ClockService:
    """Serves ``stamp()`` (s) on :data:`bridge.bus.BRIDGE_CLOCK` for bridge run ``epoch`` of
    instance ``bridge`` (module docstring). :meth:`close` undeclares it."""

    def __init__(self, session: zenoh.Session, stamp: Callable[[], float], epoch: str, bridge: str,
                 rate_per_s: float = RATE_PER_S, burst: int = BURST) -> None:
        self._stamp, self.epoch, self.bridge = stamp, epoch, bridge
        self.rate_per_s, self.burst = float(rate_per_s), float(burst)
        self._tokens, self._refill_at = self.burst, time.monotonic()
        self._lock = threading.Lock()  # the bucket: Zenoh may run two queries' callbacks at once
        self._seq = itertools.count(1)
        self.answered = self.refused = self.failed = 0
        self._queryable = session.declare_queryable(bus.BRIDGE_CLOCK, self._on_query)

    def _on_query(self, query: zenoh.Query) -> None:
        # Zenoh thread: a few µs, never the loop's state beyond the stamp (module docstring).
        now = time.monotonic()
        with self._lock:
            self._tokens = min(self.burst, self._tokens + (now - self._refill_at) * self.rate_per_s)
            self._refill_at = now
            if self._tokens < 1.0:
                self.refused += 1
                return
            self._tokens -= 1.0
        try:
            reading = bus.ClockReading(seq=next(self._seq), stamp_s=float(self._stamp()), epoch=self.epoch, bridge=self.bridge)
            query.reply(bus.BRIDGE_CLOCK, bus.encode(reading))
            self.answered += 1
        except Exception:  # noqa: BLE001 - a query must never take the bridge down (a stamp not yet finite, a closing session)
            self.failed += 1

    def close(self) -> None:
        with contextlib.suppress(Exception):  # the session may be closed already
            self._queryable.undeclare()


@dataclass
class ClockReply:
    """A valid reply of one query: the reading, its round trip on the querier's clock, and the
    Zenoh id of the session that sent it ('' if Zenoh does not say)."""

    reading: bus.ClockReading
    sample: ClockSample
    replier: str = ""


@dataclass
class QueryResult:
    """What one query got: ``replies`` (valid), ``refused`` (replies refused) and the ``rejected``
    reasons (the first :data:`MAX_REASONS` of them)."""

    replies: list[ClockReply] = field(default_factory=list)
    rejected: list[str] = field(default_factory=list)
    refused: int = 0

    def refuse(self, reason: str) -> None:
        self.refused += 1
        if len(self.rejected) < MAX_REASONS:
            self.rejected.append(reason)


def _reply_text(err: object) -> str:
    payload = getattr(err, "payload", None)
    try:
        text = payload.to_bytes()[:200].decode("utf-8", "replace") if payload is not None else str(err)
    except Exception:  # noqa: BLE001 - an error reply is untrusted too
        text = "?"
    return text[:200]


def _replier(reply: zenoh.Reply) -> str:
    """The Zenoh id of the session that sent ``reply`` ('' if unknown)."""
    try:
        rid = reply.replier_id
        return "" if rid is None else str(rid.zid)
    except Exception:  # noqa: BLE001 - an older Zenoh: no id, the run key is the reading's alone
        return ""


def query_clock(session: zenoh.Session, timeout_s: float = 0.5, clock: Callable[[], float] = time.time) -> QueryResult:
    """Query :data:`bridge.bus.BRIDGE_CLOCK` once; every reply stamped on ``clock`` (s) when the
    query left and when the reply was taken (module docstring). Returns within ``timeout_s`` (an
    empty result when no bridge answers)."""
    result = QueryResult()
    t0 = clock()
    # Every bridge's reply: not the "best matching" queryable's alone, and not consolidated into one
    # (Zenoh's default keeps one reply per key: of two bridges on one hub the querier saw one).
    replies = session.get(bus.BRIDGE_CLOCK, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                          timeout=timeout_s)
    per_replier: dict[str, int] = {}
    for reply in replies:
        t1 = clock()
        replier = _replier(reply)
        seen = per_replier[replier] = per_replier.get(replier, 0) + 1
        if seen > MAX_PER_REPLIER:
            result.refuse(f"peer {replier or '?'}: more than {MAX_PER_REPLIER} replies to one query")
            continue
        if len(result.replies) >= MAX_REPLIES:
            result.refuse(f"more than {MAX_REPLIES} valid replies to one query")
            continue
        ok = reply.ok
        if ok is None:
            result.refuse(f"error reply: {_reply_text(reply.err)}")
            continue
        try:
            if str(ok.key_expr) != bus.BRIDGE_CLOCK:
                raise bus.BusDecodeError(f"reply on {str(ok.key_expr)[:100]!r}, not {bus.BRIDGE_CLOCK}")
            bus.check_payload_size(bus.ClockReading, len(ok.payload))
            reading = bus.decode(bus.ClockReading, ok.payload.to_bytes())
        except bus.BusDecodeError as exc:
            result.refuse(exc.reason)
            continue
        result.replies.append(ClockReply(reading, ClockSample(t0, reading.stamp_s, t1), replier))
    return result


__all__ = ["BURST", "MAX_PER_REPLIER", "MAX_REPLIES", "RATE_PER_S", "ClockReply", "ClockService", "QueryResult", "query_clock"]
