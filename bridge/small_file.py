"""Reading the bus's small secret files (credentials, TLS keys and certificates) with every check
a user needs an answer for: missing, not a file, readable by others, oversized, not ASCII."""

from __future__ import annotations

import stat
from pathlib import Path


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
