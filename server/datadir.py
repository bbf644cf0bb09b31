"""The console's data directory: one owner at a time, and the storage checks before a campaign.

One owner: ``<data_dir>/server.lock`` holds an exclusive ``flock`` for the life of the server and
says who holds it (pid, host, start time). A second server on the same directory is refused with
one line naming the owner (two servers would each "recover" the other's live campaign, issue 14
finding 1). The kernel drops the lock when its owner dies, however it dies, so a dead owner's lock
is taken over without any staleness rule. (``flock`` is local: a data directory shared over NFS
between machines is not protected.)

Storage: a campaign starts only where it can be written and where ``min_free_bytes`` are free
besides the room its archive will take (:func:`archive_room_bytes`; :func:`storage_problem`); the
reason, with the figures, is the 507 a client sees.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
from pathlib import Path

from bridge.archive import iso_time, storage_reason

LOCK_FILE = "server.lock"


class DataDirError(Exception):
    """The data directory cannot be used; the message is the one line ``xneck server`` prints."""


class DataDirInUse(DataDirError):
    """Another live process owns the data directory (its lock)."""


class DataDirLock:
    """Exclusive ownership of a data directory by this process; :meth:`release` gives it back."""

    def __init__(self, data_dir: Path) -> None:
        self.dir = Path(data_dir)
        self.path = self.dir / LOCK_FILE
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise DataDirError(f"cannot use the data directory {self.dir}: {storage_reason(exc)}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _read_owner(fd)
            os.close(fd)
            raise DataDirInUse(
                f"the data directory {self.dir} is in use by another xneck server (pid {owner.get('pid', '?')} on "
                f"{owner.get('host', '?')}, since {owner.get('started_at', '?')}): stop it or choose another "
                f"--data-dir") from None
        self._fd: int | None = fd
        self.owner = {"pid": os.getpid(), "host": socket.gethostname(), "started_at": iso_time()}
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(self.owner).encode() + b"\n", 0)
            os.fsync(fd)
        except OSError as exc:
            self.release()
            raise DataDirError(f"cannot use the data directory {self.dir}: {storage_reason(exc)}") from None

    def release(self) -> None:
        """Unlock (the file stays: removing it would race with a server opening it right now)."""
        if self._fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._fd, fcntl.LOCK_UN)
                os.close(self._fd)
            self._fd = None


def _read_owner(fd: int) -> dict:
    try:
        return json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return {}


def free_bytes(directory: Path) -> int:
    st = os.statvfs(directory)
    return st.f_bavail * st.f_frsize


#: Archive bytes per second of a campaign: 0.46 MB/s measured with the twin's noise α_IP, 0.66 MB/s
#: with the rendered camera (audit of 2026-11-30, 600 s and 97 s campaigns on `xneck up`), and margin.
#: The Foxglove scene the console adds afterwards goes through a whole copy of the archive
#: (server.foxglove_scene): not counted, it is given up, the archive kept, where it does not fit.
ARCHIVE_BYTES_PER_S = 0.8e6


def archive_room_bytes(duration_s: float) -> int:
    """Room (bytes) a campaign of ``duration_s`` seconds needs for its archive: a fixed 64 MB had let
    a 600 s campaign, whose archive takes ~0.3-0.4 GB, start on a disk that would fill part-way
    through (audit of 2026-11-30)."""
    return int(max(0.0, duration_s) * ARCHIVE_BYTES_PER_S)


def storage_problem(directory: Path, min_free_bytes: int, duration_s: float = 0.0) -> str:
    """Why a campaign of ``duration_s`` seconds cannot be recorded in ``directory`` now ('' if it
    can): not writable, or less than ``min_free_bytes`` free besides its archive's room
    (:func:`archive_room_bytes`; the figures in MB)."""
    probe = Path(directory) / f".probe-{os.getpid()}"
    try:
        with open(probe, "wb") as f:
            f.write(b"\0")
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        return f"the archive directory {directory} is not writable: {storage_reason(exc)}"
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()
    free, room = free_bytes(directory), archive_room_bytes(duration_s)
    if free < min_free_bytes + room:
        archive = f" ({room / 1e6:.0f} MB for the archive of {duration_s:.0f} s, " \
                  f"{min_free_bytes / 1e6:.1f} MB besides)" if room else ""
        return (f"{free / 1e6:.1f} MB free in {directory}, a campaign needs at least "
                f"{(min_free_bytes + room) / 1e6:.1f} MB{archive}: free some space (delete or move archives)")
    return ""
