"""An e-stop holder: the sending side of the e-stop contract (docs/safety.md, "E-stop").

Whoever engages the e-stop (the console's button, ``xneck estop engage``) publishes an ``EStop``
on ``xneck/estop`` naming itself (:data:`bridge.session.ESTOP_HOLDER`) and holds a liveliness token
``xneck/estop/engaged/<holder>`` until it releases: a message reaches only the bridges linked when
it goes out, the token also those that start or link back later (they start latched). A release
drops the token first, then publishes; a bridge obeys it only when no other holder is left
(:class:`bridge.safety.EStopHolders`). A holder that goes away without releasing (a crash, Ctrl-C)
drops its token and releases nothing: the bridges latched stay latched.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time

import zenoh

from bridge import bus
from bridge.session import estop_holder_attachment, publisher

log = logging.getLogger("xneck.estop")

REASON_MAX_CHARS = 200  # what a bridge keeps of a reason (bridge.node)


class EStopHolder:
    """Engage and release the e-stop on ``session`` as holder ``name`` (letters, digits, ``._-``).

    Thread-safe: two calls at once go out one after the other, so the last one sent is the last
    one asked for. A token that cannot be declared or dropped is logged, never raised: the
    message goes out (or went out) whatever becomes of the token.
    """

    def __init__(self, session: zenoh.Session, name: str) -> None:
        self.name = name
        self._key = bus.estop_token_key(name)  # checks the name before anything is declared
        self._session = session
        self._pub = publisher(session, bus.ESTOP)
        self._attachment = estop_holder_attachment(name)
        self._lock = threading.Lock()
        self._seq = 0
        self._token: zenoh.LivelinessToken | None = None

    @property
    def holds(self) -> bool:
        """Whether this holder's token is declared (from an engage to the next release)."""
        return self._token is not None

    def engage(self, reason: str) -> None:
        """Publish an engaged ``EStop``, then hold the token (the bridges up now latch at once on
        the message and need not wait for the token's propagation). The token is held even if the
        publication fails: an engage must not be lost whole to one error (review of session 41:
        a reason that did not encode had sent neither)."""
        with self._lock:
            try:
                self._put(True, reason)
            finally:
                self._hold(True)

    def release(self, reason: str) -> None:
        """Drop the token, then publish the release (a bridge obeys it once no other holder is
        left: the two travel apart and may arrive in either order)."""
        with self._lock:
            self._hold(False)
            self._put(False, reason)

    def close(self) -> None:
        """Drop the token (the bridges latched stay latched: a vanished holder releases nothing)
        and the publisher."""
        with self._lock:
            self._hold(False)
            with contextlib.suppress(Exception):  # a closed session: nothing left to close
                self._pub.close()

    def _put(self, engaged: bool, reason: str) -> None:
        self._seq += 1
        self._pub.put(bus.EStop(seq=self._seq, stamp_s=time.time(), engaged=engaged,
                                reason=bus.plain_text(reason, REASON_MAX_CHARS)), attachment=self._attachment)

    def _hold(self, hold: bool) -> None:
        try:
            if hold and self._token is None:
                self._token = self._session.liveliness().declare_token(self._key)
            elif not hold and self._token is not None:
                token, self._token = self._token, None
                token.undeclare()
        except Exception as exc:  # noqa: BLE001 - see the class docstring
            log.error("e-stop token %s could not be %s (%s: %s)", self._key, "declared" if hold else "dropped",
                      type(exc).__name__, exc)


__all__ = ["EStopHolder"]
