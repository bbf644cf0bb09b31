"""The bridge's e-stop latch kept on disk, so that a bridge restarted under an engaged e-stop
starts latched even when nobody holds it on the bus any more.

An engaged e-stop reaches a bridge that starts later through its holder's liveliness token
(``xneck/estop/engaged/<holder>``, docs/safety.md rule 4). Not when the holder is gone first: a
console that crashed (or was stopped) while engaged, then the bridge restarted (a power cycle of
the board, systemd), and the new bridge came up ``inactive`` and obeyed the controller's commands
(session 40). The latch file closes that: the bridge writes it when its e-stop engages and removes
it when the e-stop is released, and a bridge that finds it at start is latched (``disabled``)
until a release. A file that cannot be read counts as engaged (fail safe, as a malformed e-stop
message does).

The writes happen on a thread of their own (an SD card's write may take tens of ms, a tick has
2 ms): the tick only hands over the newest state. Each write is a new file renamed over the old
one and synced with its folder, so a power cut leaves the old latch or the new one, never half.
A write that fails is logged (the latch in memory still holds; the next change tries again).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from pathlib import Path

log = logging.getLogger("xneck.bridge")

LATCH_MAX_BYTES = 4096  # a latch file is one line: larger is not one


def default_latch_path() -> Path:
    """Where the board's bridge keeps its latch: ``$XDG_STATE_HOME/xneck/estop-board``
    (``~/.local/state`` when unset). One per board, whatever the bridge's name: a board runs one
    bridge (its lock), and ``xneck up --robot`` names its bridge anew at each start (a latch per
    name was never read again; review of session 40)."""
    state = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(state) / "xneck" / "estop-board"


def read_latch(path: Path) -> str | None:
    """The reason of the e-stop latched in ``path``, None if there is no latch file. A file that
    cannot be read, or is not a latch, is a latch whose reason says so."""
    try:
        with path.open("rb") as f:
            data = f.read(LATCH_MAX_BYTES + 1)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"the latch file cannot be read ({exc.strerror or exc}): taken as engaged"
    if len(data) > LATCH_MAX_BYTES:
        return f"the latch file is over {LATCH_MAX_BYTES} bytes: taken as engaged"
    return data.decode("utf-8", "replace").strip() or "e-stop"


class LatchFile:
    """The e-stop latch at ``path``, written off the tick (module docstring). :meth:`set` hands
    over the newest state (engaged, reason); :meth:`close` writes what is pending (bounded)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.failures = 0
        self._wanted: tuple[bool, str] | None = None
        self._cond = threading.Condition()
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="xneck-estop-latch", daemon=True)
        self._thread.start()

    def set(self, engaged: bool, reason: str) -> None:
        """Keep the e-stop ``engaged`` (with ``reason``) on disk, or remove the latch. Never blocks
        on the disk: the tick calls it."""
        with self._cond:
            self._wanted = (engaged, reason)
            self._cond.notify()

    def close(self, timeout_s: float = 2.0) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._wanted is None and not self._closing:
                    self._cond.wait()
                wanted, self._wanted = self._wanted, None
                closing = self._closing
            if wanted is not None:
                self._write(*wanted)
            if closing and wanted is None:
                return

    def _write(self, engaged: bool, reason: str) -> None:
        try:
            if engaged:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                tmp = self.path.with_name(self.path.name + ".tmp")
                with tmp.open("wb") as f:
                    f.write(reason.encode("utf-8", "replace")[:LATCH_MAX_BYTES - 1] + b"\n")
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, self.path)
            else:
                self.path.unlink(missing_ok=True)
            self._sync_folder()
        except OSError as exc:
            self.failures += 1
            log.error("e-stop latch file %s could not be %s (%s): a bridge restarted now would not know of "
                      "this e-stop's state", self.path, "written" if engaged else "removed", exc.strerror or exc)

    def _sync_folder(self) -> None:
        with contextlib.suppress(OSError):  # not every file system syncs a folder
            fd = os.open(self.path.parent, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)


__all__ = ["LATCH_MAX_BYTES", "LatchFile", "default_latch_path", "read_latch"]
