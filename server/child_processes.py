"""Child processes of the console: the `xneck` command lines it starts (campaign runner, `xneck up`),
how they are stopped, and the last lines of their logs for an error message.

One place for what both orchestrators do, so a stop always means SIGTERM, a grace period (the
bridge ramps its forces down and closes its archive in it), then SIGKILL.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path


def xneck_argv(*args: str) -> list[str]:
    """The argv of ``xneck <args>`` run by this very interpreter (the venv's, whatever PATH says)."""
    return [sys.executable, "-m", "server.cli", *args]


def stop_child(proc: subprocess.Popen, grace_s: float) -> bool:
    """SIGTERM, then SIGKILL after ``grace_s`` seconds. Returns True if it had to be killed."""
    if proc.poll() is not None:
        return False
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(grace_s)
        return False
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(grace_s)
        return True


def log_tail(path: Path, lines: int) -> str:
    """The last ``lines`` lines of a child's log ('' if it cannot be read)."""
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""
