"""Which controller service a console's request goes to, when more than one is on the bus.

Every campaign service takes the bare ``xneck/campaign/request``: with a second one on the bus
(a lab's ``xneck controller`` left running beside ``xneck up``), both took the console's campaign,
and the one the bridge does not obey aborted it at once ("the bridge obeys controller …, not this
one"), naming the wrong controller (audit of 2026-11-28). The console therefore addresses each
request to one service (:func:`bridge.bus.campaign_request_key`), chosen here from what the bus
says: the service the bridge obeys, else the only one, else none, with the reason.
"""

from __future__ import annotations

from collections.abc import Iterable

import zenoh

from bridge import bus

#: s: how long a liveliness query waits for the services' tokens
QUERY_TIMEOUT_S = 0.5
SERVICES_KEY = f"{bus.PREFIX}/alive/campaign-service/*"


def choose_service(services: Iterable[str], owners: Iterable[str]) -> tuple[str, str]:
    """``(instance, "")`` of the campaign service a request goes to, or ``("", reason)`` when the
    console cannot tell which one drives the robot. ``services``: the instances of the campaign
    services alive on the bus; ``owners``: the controllers the bridges on the bus obey (their
    states' ``owner``; none if unknown). With no service at all: ``("", "")`` (the request goes out
    bare, and the caller's wait for an answer says that nobody answered)."""
    alive = sorted(set(services))
    obeyed = sorted(set(owners) & set(alive))
    if len(obeyed) == 1:
        return obeyed[0], ""
    if len(alive) == 1:
        return alive[0], ""
    if not alive:
        return "", ""
    others = sorted(set(owners) - set(alive))
    obeys = (f"the bridges obey {', '.join(obeyed)}" if obeyed else
             f"the bridge obeys {', '.join(others)}, not one of them" if others else "the bridge obeys none of them")
    return "", (f"{len(alive)} controller services are on the bus ({', '.join(alive)}) and {obeys}: the console "
                f"cannot tell which one drives the robot; stop the one that is not this stack's")


def alive_services(session: zenoh.Session, timeout_s: float = QUERY_TIMEOUT_S) -> list[str]:
    """The instances of the campaign services alive on the bus (a liveliness query)."""
    found = set()
    for reply in session.liveliness().get(SERVICES_KEY, timeout=timeout_s):
        if reply.ok is None:
            continue
        try:
            kind, instance = bus.parse_liveliness_key(str(reply.ok.key_expr))
        except ValueError:
            continue
        if kind == "campaign-service":
            found.add(instance)
    return sorted(found)
