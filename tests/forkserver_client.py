"""The client of tests/xneck_forkserver.py: ``xneck`` runs and the stacks' processes forked from a
server that imported the command line and loaded the numba kernels once (its module docstring).

One server per test process (each xdist worker), started at the first use and stopped when the
process exits. ``XNECK_TEST_FORKSERVER=0`` makes every process one of its own (``subprocess``), as
does a server that cannot start or refuses (a warning says so).
"""

from __future__ import annotations

import atexit
import contextlib
import json
import locale
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path
from typing import Any

XNECK = [sys.executable, "-m", "server.cli"]  # `xneck` with this interpreter (tests/conftest.py uses it too)
START_TIMEOUT_S = 120.0
CMDLINE_ROOM = 8192  # xneck_forkserver.CMDLINE_ROOM: its children's command lines are written over it


class ForkedProcess(subprocess.Popen):
    """A process the fork server started, with the ``Popen`` calls the tests make (``pid``,
    ``poll``, ``wait``, ``send_signal``, ``terminate``, ``kill``, ``returncode``). It is the
    server's child, so its exit code comes from the server, over the connection it was asked on."""

    def __init__(self, conn: socket.socket, pid: int, args: list[str]) -> None:  # no Popen.__init__: no exec
        self._conn, self._answers = conn, conn.makefile("rb")
        self.pid, self.args, self.returncode = pid, args, None
        self.stdin = self.stdout = self.stderr = None
        self._child_created = False  # Popen.__del__ has nothing to reap

    def _read_code(self) -> None:
        line = self._answers.readline().strip()
        self.returncode = int(line) if line.lstrip(b"-").isdigit() else -signal.SIGKILL  # the server died
        self._answers.close()
        self._conn.close()

    def poll(self) -> int | None:
        if self.returncode is None and select.select([self._conn], [], [], 0)[0]:
            self._read_code()
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            if not select.select([self._conn], [], [], timeout)[0]:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
            self._read_code()
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def communicate(self, *args: Any, **kwargs: Any) -> Any:
        raise NotImplementedError("a forked process writes to files, not pipes")

    def __del__(self) -> None:
        pass


class ForkServer:
    """The client of one fork server (module docstring)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.proc: subprocess.Popen | None = None
        self.broken = os.environ.get("XNECK_TEST_FORKSERVER", "1") == "0"
        self._lock = threading.Lock()

    def _start(self) -> bool:
        with self._lock:  # the in-process consoles' campaign threads ask too
            return self._start_locked()

    def _start_locked(self) -> bool:
        if self.proc is None and not self.broken:
            self.proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name("xneck_forkserver.py")),
                                          str(self.path), "-" * CMDLINE_ROOM], cwd=Path(__file__).parent.parent,
                                         stdin=subprocess.DEVNULL)
            deadline = time.monotonic() + START_TIMEOUT_S
            while not self.path.exists() and self.proc.poll() is None and time.monotonic() < deadline:
                time.sleep(0.02)
            if not self.path.exists():
                warnings.warn("the xneck fork server did not start: each process is one of its own", stacklevel=3)
                self.stop()
                self.broken = True
        return not self.broken

    def _ask(self, args: list[str], cwd: Path | None, env: dict[str, str], stdout: Path, stderr: Path,
             session: bool, append: bool = False) -> tuple[socket.socket, int] | None:
        """Asks for a process; its connection and pid, or None if the server cannot take it."""
        if not self._start():
            return None
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
        request = {"argv": args, "cwd": str(Path(cwd or os.getcwd()).absolute()), "env": env, "session": session,
                   "nice": os.getpriority(os.PRIO_PROCESS, 0), "cpus": cpus, "stdout": str(stdout),
                   "stderr": str(stderr), "append": append}
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            conn.connect(str(self.path))
            conn.sendall(json.dumps(request).encode() + b"\n")
            first = b""
            while not first.endswith(b"\n"):  # one byte at a time: the exit code's line is the caller's
                byte = conn.recv(1)
                if not byte:
                    break
                first += byte
        except OSError as exc:
            first = f"{type(exc).__name__}: {exc}".encode()
        answer = first.decode(errors="replace").strip()
        if answer == "too long":  # a command line longer than the server's room: this one a process of its own
            conn.close()
            return None
        if not answer.isdigit():
            conn.close()
            warnings.warn(f"the xneck fork server refused a process ({answer or 'no answer'}): "
                          "each process is one of its own from now on", stacklevel=4)
            self.broken = True
            return None
        return conn, int(answer)

    def run(self, args: list[str], timeout: float, cwd: Path | None) -> subprocess.CompletedProcess | None:
        """``xneck <args>`` run to completion, as ``subprocess.run(capture_output=True, text=True)``
        returns it; None if the server could not take it (then the caller starts a process)."""
        with tempfile.TemporaryDirectory(prefix="xneck-run-") as tmp:
            out, err = Path(tmp) / "stdout", Path(tmp) / "stderr"
            out.touch()
            err.touch()
            asked = self._ask(args, cwd, dict(os.environ), out, err, session=False)
            if asked is None:
                return None
            proc = ForkedProcess(asked[0], asked[1], [*XNECK, *args])
            try:
                code = proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(30)
                raise subprocess.TimeoutExpired(proc.args, timeout, _text(out), _text(err)) from None
            return subprocess.CompletedProcess(proc.args, code, _text(out), _text(err))

    def spawn(self, args: list[str], log: Path, env: dict[str, str], cwd: Path | None = None,
              start_new_session: bool = True, append: bool = False) -> ForkedProcess | None:
        """``xneck <args>`` started, stdout and stderr to ``log`` (truncated, or appended to), stdin
        ``/dev/null``: ``Popen(..., stdout=open(log, "wb"), stderr=STDOUT, start_new_session=...)``;
        None if the server could not take it."""
        log.touch()
        asked = self._ask(args, cwd, env, log, log, session=start_new_session, append=append)
        return None if asked is None else ForkedProcess(asked[0], asked[1], [*XNECK, *args])

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


def _text(path: Path) -> str:
    """A file's bytes as ``subprocess.run(text=True)`` decodes a pipe's (locale encoding, universal newlines)."""
    data = path.read_bytes().decode(locale.getpreferredencoding(False))
    return data.replace("\r\n", "\n").replace("\r", "\n")


_shared: ForkServer | None = None


def shared() -> ForkServer:
    """This process's fork server (started at its first use, stopped at this process's exit)."""
    global _shared
    if _shared is None:
        _shared = ForkServer(Path(tempfile.mkdtemp(prefix="xneck-forkserver-")) / "socket")
        atexit.register(_shared.stop)
    return _shared


def parent_pids() -> set[int]:
    """The pids a process this test process started may have as its parent: this process's own,
    and its fork server's (whose children the forked processes are)."""
    server = _shared.proc if _shared is not None else None
    return {os.getpid()} | ({server.pid} if server is not None else set())
