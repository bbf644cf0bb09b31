"""A second machine on this one, for benchmarks: a network namespace (its own TCP stack and routes,
as the BeagleBone's) joined to this one by a veth pair. Needs root (``ip netns``, ``ip link``).

    with board_namespace() as board:
        subprocess.Popen([*board.exec_prefix, "python", ...])   # listens on tcp/{board.board_ip}:PORT

Everything is removed on exit, also after an error.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass

SUBNET = "10.213.47"  # a /30 of private space no lab routes to a benchmark machine


@dataclass(frozen=True)
class Board:
    name: str
    board_ip: str
    pc_ip: str

    @property
    def exec_prefix(self) -> list[str]:
        return ["ip", "netns", "exec", self.name]


def _ip(*args: str, ns: str | None = None) -> None:
    cmd = ["ip", *(["-n", ns] if ns else []), *args]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: {r.stderr.strip()}")


def quickack_state(address: str) -> bool:
    """Whether this machine's route to ``address`` acknowledges at once (``ip route … quickack 1``)
    instead of delaying ACKs up to 40 ms."""
    try:
        out = subprocess.run(["ip", "route", "get", address], capture_output=True, text=True, timeout=10).stdout
    except OSError:  # no iproute2 here: the header says "off", the local runs need no ip command
        return False
    return "quickack 1" in out


@contextlib.contextmanager
def board_namespace() -> Iterator[Board]:
    """The namespace and its link (module docstring); removed on exit."""
    if os.geteuid() != 0:
        raise PermissionError("a network namespace needs root (ip netns add)")
    tag = os.getpid() % 100000
    b = Board(f"xneck-board-{tag}", f"{SUBNET}.2", f"{SUBNET}.1")
    pc_if, board_if = f"xnp{tag}", f"xnb{tag}"
    try:
        _ip("netns", "add", b.name)
        _ip("link", "add", pc_if, "type", "veth", "peer", "name", board_if)
        _ip("link", "set", board_if, "netns", b.name)
        _ip("addr", "add", f"{b.pc_ip}/30", "dev", pc_if)
        _ip("addr", "add", f"{b.board_ip}/30", "dev", board_if, ns=b.name)
        _ip("link", "set", pc_if, "up")
        _ip("link", "set", board_if, "up", ns=b.name)
        _ip("link", "set", "lo", "up", ns=b.name)
        yield b
    finally:
        with contextlib.suppress(RuntimeError):
            _ip("link", "del", pc_if)  # deletes its peer in the namespace too
        with contextlib.suppress(RuntimeError):
            _ip("netns", "del", b.name)
