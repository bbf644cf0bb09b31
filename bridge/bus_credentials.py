"""Bus credentials: who may open a Zenoh session with an xneck process.

The bridge that drives the robot listens on the lab network (docs/bridge.md, deployment), and a
Zenoh peer that links to it may publish motor commands and e-stops and subscribe to everything.
The bridge's ownership rule and message checks stop mistakes (a second stack, a malformed
message), not a stranger on the network. A credentials file set in ``XNECK_ZENOH_CREDENTIALS``
turns on Zenoh's user/password authentication (``transport/auth/usrpwd``) in every process that
reads it: a session is opened only between two processes that both present a user and password
the other's file lists, in both directions, so a peer without the file (or with another lab's)
gets no link at all, neither to send nor to receive.

The file is Zenoh's dictionary format, one ``user:password`` per line (blank lines allowed; Zenoh
refuses comments). A process presents the entry named by ``XNECK_ZENOH_USER``, the first entry by
default, and accepts every entry: one file copied to every machine of the lab (``xneck bus
credentials FILE`` writes one), or one line per machine so that a machine's entry can be removed.
Like an SSH key, the file must be readable by its owner alone.
"""

from __future__ import annotations

import os
import re
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path

__all__ = ["ENV_CREDENTIALS", "ENV_USER", "Credentials", "CredentialsError", "from_env", "load", "write_new"]

ENV_CREDENTIALS = "XNECK_ZENOH_CREDENTIALS"
ENV_USER = "XNECK_ZENOH_USER"
MAX_FILE_BYTES = 64 * 1024
MIN_PASSWORD_CHARS = 16
_USER = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_PASSWORD = re.compile(rf"[!-~]{{{MIN_PASSWORD_CHARS},256}}")  # printable ASCII, no spaces


class CredentialsError(ValueError):
    """A credentials file that cannot be used, with the reason and the fix."""


@dataclass(frozen=True)
class Credentials:
    """What a process presents (``user``, ``password``) and the file of what it accepts."""

    path: Path
    user: str
    password: str = ""  # not in repr: logs and tracebacks must not show it
    users: tuple[str, ...] = ()

    def __repr__(self) -> str:
        return f"Credentials(path={str(self.path)!r}, user={self.user!r}, users={self.users!r})"


def load(path: str | os.PathLike[str], user: str | None = None) -> Credentials:
    """The credentials of ``path``, presenting ``user`` (None: the first entry). Raises
    :class:`CredentialsError` naming the file and the line for a missing, unreadable, too open,
    oversized or malformed file, a duplicate or unknown user or a short password."""
    p = Path(path).expanduser()
    where = f"{ENV_CREDENTIALS} {p}"
    try:
        st = p.stat()
    except OSError as exc:
        raise CredentialsError(f"{where}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise CredentialsError(f"{where} is not a regular file")
    if st.st_mode & 0o077:
        raise CredentialsError(f"{where} is readable or writable by others (mode {stat.S_IMODE(st.st_mode):04o}): "
                               f"chmod 600 {p}")
    if st.st_size > MAX_FILE_BYTES:
        raise CredentialsError(f"{where} is {st.st_size} bytes, more than {MAX_FILE_BYTES}: not a credentials file")
    try:
        text = p.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as exc:
        raise CredentialsError(f"{where} cannot be read as ASCII text: {exc}") from None
    entries: dict[str, str] = {}
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        name, sep, password = line.partition(":")
        if not sep:
            raise CredentialsError(f"{where}, line {n}: not of the form user:password (Zenoh allows no comments)")
        if not _USER.fullmatch(name):
            raise CredentialsError(f"{where}, line {n}: user {name!r} is not 1-64 letters, digits or _.-")
        if not _PASSWORD.fullmatch(password):
            raise CredentialsError(f"{where}, line {n}: the password of {name!r} must be {MIN_PASSWORD_CHARS}-256 "
                                   "printable ASCII characters without spaces (xneck bus credentials makes one)")
        if name in entries:
            raise CredentialsError(f"{where}, line {n}: user {name!r} listed twice")
        entries[name] = password
    if not entries:
        raise CredentialsError(f"{where} lists no user:password")
    chosen = next(iter(entries)) if user is None else user
    if chosen not in entries:
        raise CredentialsError(f"{ENV_USER}={chosen!r} is not listed in {p} (users: {', '.join(entries)})")
    return Credentials(path=p, user=chosen, password=entries[chosen], users=tuple(entries))


def from_env(environ: os._Environ[str] | dict[str, str] = os.environ) -> Credentials | None:
    """The credentials ``XNECK_ZENOH_CREDENTIALS`` names (None if unset or empty), presenting
    ``XNECK_ZENOH_USER`` when set."""
    path = environ.get(ENV_CREDENTIALS, "").strip()
    if not path:
        return None
    return load(path, environ.get(ENV_USER, "").strip() or None)


def write_new(path: str | os.PathLike[str], user: str = "xneck") -> Credentials:
    """A new credentials file at ``path`` with one entry, ``user`` and a random password (256 bits),
    created readable by its owner alone; an existing file is never replaced (FileExistsError)."""
    if not _USER.fullmatch(user):
        raise CredentialsError(f"user {user!r} is not 1-64 letters, digits or _.-")
    p = Path(path).expanduser()
    password = secrets.token_urlsafe(32)
    # O_EXCL: never truncate someone's file; 0o600 from the start, no window where it is open.
    fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(f"{user}:{password}\n")
    return load(p, user)
