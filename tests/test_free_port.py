"""bridge.session.free_tcp_port: a port for a listener started next (hubs, viser, test consoles)."""

from __future__ import annotations

import socket

from bridge.session import LISTEN_PORTS_FROM, _ephemeral_start, free_tcp_port


def test_free_ports_are_bindable_distinct_and_outside_the_kernels_ephemeral_range() -> None:
    """The kernel's choice for port 0 is also what it gives outgoing connections as their local
    port: on a busy machine one took a console's port between the pick and the bind (a fresh-clone
    CI run, 2026-11-28, "address already in use"). Ports are drawn below that range, and one
    process never gets the same port twice in a row of calls."""
    top = _ephemeral_start()
    ports = [free_tcp_port() for _ in range(200)]
    assert len(set(ports)) == len(ports)
    assert all(LISTEN_PORTS_FROM <= p < top for p in ports), (top, sorted(ports)[-5:])
    for p in ports[:20]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", p))


def test_a_port_taken_meanwhile_is_not_handed_out() -> None:
    """Ports bound by someone else are skipped: hold many, ask again, never get one of them."""
    held: list[socket.socket] = []
    try:
        for _ in range(50):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", free_tcp_port()))
            s.listen()
            held.append(s)
        taken = {s.getsockname()[1] for s in held}
        assert not taken & {free_tcp_port() for _ in range(200)}
    finally:
        for s in held:
            s.close()
