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

Viewers. A user named ``viewer`` or ``viewer-<name>`` (also ``viewer_``/``viewer.``) may watch and
may not act: every xneck process whose file lists such a user drops, at the link, whatever that
user's sessions publish (samples, deletions, queries and replies, liveliness tokens) with Zenoh's
access control (:func:`viewer_access_control`), so a viewer receives the robot's states but its
commands, e-stops, campaign requests and presence reach no one. The viewer's machine holds a file
with its own entry alone (``xneck bus credentials LAB-FILE --export viewer-NAME OUT``): it connects
to the stack and cannot present any other user, since it knows no other password. xneck's command
line refuses to start a process that would act (a stack, a bridge, a controller, a campaign) as a
viewer; ``xneck server`` as a viewer is a read-only console.
"""

from __future__ import annotations

import os
import re
import secrets
from dataclasses import dataclass
from pathlib import Path

from bridge.small_file import read_checked

__all__ = [
    "ENV_CREDENTIALS",
    "ENV_USER",
    "Credentials",
    "CredentialsError",
    "add_entry",
    "export_entry",
    "from_env",
    "is_viewer",
    "load",
    "remove_entry",
    "viewer_access_control",
    "write_new",
]

ENV_CREDENTIALS = "XNECK_ZENOH_CREDENTIALS"
ENV_USER = "XNECK_ZENOH_USER"
MAX_FILE_BYTES = 64 * 1024
MIN_PASSWORD_CHARS = 16
VIEWER = "viewer"
#: What a viewer's sessions may not do, in Zenoh's access-control message names: everything that
#: reaches another process as an action or a presence. Subscribing and liveliness queries (reading
#: who is alive) stay allowed.
VIEWER_DENIED_MESSAGES = ("put", "delete", "query", "declare_queryable", "reply", "liveliness_token")
_USER = re.compile(r"[A-Za-z0-9_.-]{1,64}")
_PASSWORD = re.compile(rf"[!-~]{{{MIN_PASSWORD_CHARS},256}}")  # printable ASCII, no spaces


class CredentialsError(ValueError):
    """A credentials file that cannot be used, with the reason and the fix."""


def is_viewer(user: str) -> bool:
    """Whether ``user`` names a viewer: ``viewer``, or ``viewer`` then ``-``, ``_`` or ``.`` and a name."""
    return user == VIEWER or (user.startswith(VIEWER) and user[len(VIEWER):len(VIEWER) + 1] in ("-", "_", "."))


@dataclass(frozen=True)
class Credentials:
    """What a process presents (``user``, ``password``) and the file of what it accepts."""

    path: Path
    user: str
    password: str = ""  # not in repr: logs and tracebacks must not show it
    users: tuple[str, ...] = ()

    def __repr__(self) -> str:
        return f"Credentials(path={str(self.path)!r}, user={self.user!r}, users={self.users!r})"

    @property
    def role(self) -> str:
        """``viewer`` if the user presented is one (:func:`is_viewer`), else ``operator``."""
        return VIEWER if is_viewer(self.user) else "operator"

    @property
    def viewers(self) -> tuple[str, ...]:
        """The viewers the file lists: this process drops what their sessions publish."""
        return tuple(u for u in self.users if is_viewer(u))


def viewer_access_control(viewers: tuple[str, ...] | list[str]) -> dict | None:
    """Zenoh's ``access_control`` section that drops, on the way in, what the sessions of
    ``viewers`` publish (:data:`VIEWER_DENIED_MESSAGES`, on every key); None without viewers (no
    interceptor at all). Zenoh matches the user a link authenticated with (transport/auth/usrpwd),
    so a viewer cannot pass for another user without that user's password. Everything else is
    allowed as before: the rule is a deny, and Zenoh's denies win over allows."""
    if not viewers:
        return None
    return {
        "enabled": True,
        "default_permission": "allow",
        "rules": [{"id": "viewers-publish-nothing", "permission": "deny", "flows": ["ingress"],
                   "messages": list(VIEWER_DENIED_MESSAGES), "key_exprs": ["**"]}],
        "subjects": [{"id": "viewers", "usernames": list(viewers)}],
        "policies": [{"rules": ["viewers-publish-nothing"], "subjects": ["viewers"]}],
    }


def load(path: str | os.PathLike[str], user: str | None = None) -> Credentials:
    """The credentials of ``path``, presenting ``user`` (None: the first entry). Raises
    :class:`CredentialsError` naming the file and the line for a missing, unreadable, too open,
    oversized or malformed file, a duplicate or unknown user or a short password."""
    p = Path(path).expanduser()
    entries = _entries(p)
    chosen = next(iter(entries)) if user is None else user
    if chosen not in entries:
        raise CredentialsError(f"{ENV_USER}={chosen!r} is not listed in {p} (users: {', '.join(entries)})")
    return Credentials(path=p, user=chosen, password=entries[chosen], users=tuple(entries))


def _entries(p: Path, where: str | None = None) -> dict[str, str]:
    """The ``user: password`` entries of the file ``p``, in file order, checked (see :func:`load`);
    ``where`` names it in the errors (default: as :data:`ENV_CREDENTIALS` names it)."""
    where = where or f"{ENV_CREDENTIALS} {p}"
    text = read_checked(p, where, CredentialsError, kind="credentials file", max_bytes=MAX_FILE_BYTES)
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
    return entries


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



def _argument(p: Path) -> str:
    """How the errors name a file the caller was given (``xneck bus add-user FILE``), not read from
    :data:`ENV_CREDENTIALS`: the variable named a file the user never set it to (audit of 2026-11-29)."""
    return f"credentials file {p}"


def add_entry(path: str | os.PathLike[str], user: str) -> Credentials:
    """Add ``user`` with a new random password (256 bits) to the credentials file ``path`` (which
    must be usable, :func:`load`), replacing it at once (never half-written, mode 600 kept). Raises
    CredentialsError for an unusable file, a malformed or existing user."""
    if not _USER.fullmatch(user):
        raise CredentialsError(f"user {user!r} is not 1-64 letters, digits or _.-")
    p = Path(path).expanduser()
    entries = _entries(p, _argument(p))
    if user in entries:
        raise CredentialsError(f"{_argument(p)} already lists {user!r}")
    entries[user] = secrets.token_urlsafe(32)
    _replace(p, entries)
    return load(p, user)


def remove_entry(path: str | os.PathLike[str], user: str) -> Credentials:
    """Remove ``user`` from the credentials file ``path`` (a lost laptop, a viewer who left),
    replacing it at once (mode 600 kept); returns the file's credentials, presenting its first
    remaining entry. Raises CredentialsError for an unusable file, an unknown user or the last entry."""
    p = Path(path).expanduser()
    entries = _entries(p, _argument(p))
    if user not in entries:
        raise CredentialsError(f"{_argument(p)} does not list {user!r} (users: {', '.join(entries)})")
    if len(entries) == 1:
        raise CredentialsError(f"{user!r} is the last entry of {p}: remove the file instead")
    del entries[user]
    _replace(p, entries)
    return load(p)


def _replace(p: Path, entries: dict[str, str]) -> None:
    # Beside it, private from creation, then renamed over it: the old file or the new one, never a
    # mix, and never a moment when the passwords are readable by others (bridge.archive.atomic_write
    # creates with the umask's mode).
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write("".join(f"{u}:{pw}\n" for u, pw in entries.items()))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def export_entry(path: str | os.PathLike[str], user: str, out: str | os.PathLike[str]) -> Credentials:
    """Write ``out`` (created, never replaced: FileExistsError; mode 600) with ``user``'s entry of
    the credentials file ``path`` alone: the file for a machine that presents ``user`` and must not
    learn the other passwords (a viewer's). Raises CredentialsError for an unusable file or an
    unknown user."""
    p = Path(path).expanduser()
    entries = _entries(p, _argument(p))
    if user not in entries:
        raise CredentialsError(f"{_argument(p)} does not list {user!r} (users: {', '.join(entries)})")
    o = Path(out).expanduser()
    fd = os.open(o, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(f"{user}:{entries[user]}\n")
    return load(o, user)
