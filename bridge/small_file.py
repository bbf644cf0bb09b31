"""Reading the bus's small secret files (credentials, TLS keys and certificates) with every check
a user needs an answer for: missing, not a file, readable by others, oversized, not ASCII; and
reading a user's input file (a trajectory, a parameter set, a truth, a study) whole, once it is
known to be a regular file of a bounded size (:func:`read_input_file`)."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

#: The most bytes :func:`read_input_file` reads. The largest trajectory a campaign takes (2000
#: waypoints with a pretension schedule, pretty-printed as `xneck excitation design` writes it) is
#: under 0.2 MB and a parameter or truth file under 10 kB: 1 MiB leaves room for comments and
#: spacing, yet a device (/dev/zero) or a wrong file costs no more than that (a MemoryError
#: traceback before, input audit).
INPUT_FILE_MAX_BYTES = 1024 * 1024

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _regular(st: os.stat_result, max_bytes: int) -> None:
    if stat.S_ISDIR(st.st_mode):  # the message open() gives for a directory, as the loaders said before
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR))
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _KINDS if test(st.st_mode)), "a special file")
        raise OSError(errno.EINVAL, f"not a regular file but {kind}")
    if st.st_size > max_bytes:
        raise OSError(errno.EFBIG, f"{st.st_size} bytes, more than the {max_bytes} an input file may have")


def read_input_file(path: str | os.PathLike[str], max_bytes: int = INPUT_FILE_MAX_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (symbolic links followed), at most ``max_bytes``.

    Raises OSError, its ``strerror`` the reason a user reads: missing or unreadable (the system's
    word), a directory ("Is a directory"), not a regular file (a FIFO blocked the command for ever,
    a device never ends), or larger than ``max_bytes``. The path is checked before it is opened
    (opening a FIFO blocks; opening a device may act on it), and the file opened is checked again
    (non-blocking, so one swapped in meanwhile neither blocks nor is read past ``max_bytes``)."""
    _regular(os.stat(path), max_bytes)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    with os.fdopen(fd, "rb") as f:
        _regular(os.fstat(fd), max_bytes)
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:  # it grew since the check
        raise OSError(errno.EFBIG, f"more than the {max_bytes} bytes an input file may have")
    return data


def read_checked(path: Path, label: str, error: type[ValueError], *, kind: str, max_bytes: int,
                 private: bool = True, hint: str = "") -> str:
    """The ASCII text of ``path``, or ``error`` with ``label`` (what names the file in the
    message) and the reason: missing (then ``hint``), not a regular file, readable or writable by
    others when ``private`` (with the chmod that fixes it), over ``max_bytes`` (not a ``kind``),
    not ASCII."""
    try:
        st = path.stat()
    except OSError as exc:
        raise error(f"{label}: {exc.strerror or exc}{hint}") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{label} is not a regular file")
    if private and st.st_mode & 0o077:
        raise error(f"{label} is readable or writable by others (mode {stat.S_IMODE(st.st_mode):04o}): chmod 600 {path}")
    if st.st_size > max_bytes:
        raise error(f"{label} is {st.st_size} bytes, more than {max_bytes}: not a {kind}")
    try:
        return path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{label} cannot be read as ASCII text: {exc}") from None


def stamps(paths: list[Path]) -> dict[str, tuple[int, int] | None]:
    """Each file's (modification time in ns, size in bytes), None if it cannot be read now: what
    :func:`changed` compares, to tell that a file a process read at start was replaced since."""
    out: dict[str, tuple[int, int] | None] = {}
    for p in paths:
        try:
            st = p.stat()
            out[str(p)] = (st.st_mtime_ns, st.st_size)
        except OSError:
            out[str(p)] = None
    return out


def changed(before: dict[str, tuple[int, int] | None]) -> list[str]:
    """The files of ``before`` (:func:`stamps`) replaced, changed or removed since."""
    now = stamps([Path(p) for p in before])
    return [p for p in before if now[p] != before[p]]
