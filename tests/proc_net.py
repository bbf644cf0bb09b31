"""The TCP sockets a process holds, read from /proc (Linux): which listeners and links it has."""

from __future__ import annotations

import os
from dataclasses import dataclass

LISTEN, ESTABLISHED = "0A", "01"  # /proc/net/tcp's state column


@dataclass(frozen=True)
class TcpSocket:
    """One TCP socket: ``state`` (/proc/net/tcp's hex code), ``local`` and ``remote`` as
    (hex address, port)."""

    pid: int
    state: str
    local: tuple[str, int]
    remote: tuple[str, int]


def _inodes(pid: int) -> set[str]:
    inodes = set()
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except (FileNotFoundError, ProcessLookupError):  # the process ended meanwhile: it holds nothing
        return inodes
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    return inodes


def tcp_sockets(pids: list[int]) -> list[TcpSocket]:
    """The TCP sockets (IPv4 and IPv6, any state) that the processes ``pids`` hold."""
    owner = {inode: pid for pid in pids for inode in _inodes(pid)}
    found = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for line in f.readlines()[1:]:
                cols = line.split()
                if cols[9] in owner:
                    local, remote = (cols[i].rsplit(":", 1) for i in (1, 2))
                    found.append(TcpSocket(owner[cols[9]], cols[3], (local[0], int(local[1], 16)),
                                           (remote[0], int(remote[1], 16))))
    return found
