"""One bridge per board: an exclusive lock taken before a driver touches a pin.

A second ``xneck bridge --driver beaglebone`` on the board a bridge already drives (one started
by hand beside the systemd unit) turned every drive off and zeroed its encoders in its
``configure`` while the first bridge went on publishing ``active``; once commanded, both wrote
the same pins (session 37: reproduced on the fake board). The bus's ownership rules cannot see it:
the second bridge acts before it joins the bus, and both now take the same default name.

:func:`claim` takes an exclusive, non-blocking ``flock`` on a lock file (``XNECK_BOARD_LOCK``, else
``/run/lock/xneck-beaglebone.lock``, else the temporary directory's) and writes the holder's pid
in it; a second claim fails with that pid and what to do. The kernel drops the lock with the
process, however it ends (a SIGKILL included), so a stale file never blocks a restart.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
from pathlib import Path

from bridge.driver import DriverError

ENV = "XNECK_BOARD_LOCK"
NAME = "xneck-beaglebone.lock"


def lock_path() -> Path:
    """Where the board's lock lives (module docstring)."""
    if os.environ.get(ENV):
        return Path(os.environ[ENV])
    run_lock = Path("/run/lock")
    return run_lock / NAME if run_lock.is_dir() and os.access(run_lock, os.W_OK) else Path(tempfile.gettempdir()) / NAME


def claim(path: Path | None = None) -> int:
    """Take the board: the lock's file descriptor, held until :func:`release` or the process ends.
    Raises :class:`DriverError` naming the holder when another process has it."""
    where = path or lock_path()
    try:
        fd = os.open(where, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise DriverError(f"beaglebone: cannot open the board's lock {where} ({exc.strerror}); set {ENV} to a "
                          f"writable path") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = ""
        with contextlib.suppress(OSError, ValueError):
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        os.close(fd)
        raise DriverError(f"beaglebone: another xneck bridge drives this board (pid {holder or '?'}, lock {where}): "
                          "stop it first (systemctl stop xneck-bridge); nothing was written to the board") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def release(fd: int | None) -> None:
    """Give the board back (closing the descriptor drops the lock)."""
    if fd is not None:
        with contextlib.suppress(OSError):
            os.close(fd)
