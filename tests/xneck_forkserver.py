"""A fork server for the suite's ``xneck`` runs (tests/conftest.py's ``xneck`` fixture).

The suite runs ``xneck`` to completion some hundreds of times; each ``python -m server.cli`` read
and initialised numpy, typer, pydantic and the project again (0.4-1 s of CPU apiece, on a VM whose
page cache is emptied all the time). This server imports them once, then forks a child per run:
the child takes the asking test's working directory, environment and nice, its output files and
``/dev/null`` as stdin, and runs ``server.cli`` as ``python -m`` does (``runpy``, ``sys.path[0]``
the working directory), then exits through the interpreter's normal shutdown (threads joined,
``atexit`` handlers run, objects finalised), as the real process would.

Protocol, over a Unix socket, one run per connection: the client sends one JSON line (``argv``,
``cwd``, ``env``, ``nice``, ``stdout``, ``stderr``: paths of files the child writes), the server
answers the child's pid on one line, then its exit code (``subprocess`` convention: -N for a
signal) on another. The server stops when its parent (the pytest worker) is gone or on SIGTERM.

Run as ``python tests/xneck_forkserver.py SOCKET``; it binds SOCKET once its imports are done.
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import select
import signal
import socket
import sys
from typing import Any

# What `xneck`'s commands import beyond `server.cli` itself (their heavier dependencies are
# imported inside the commands): imported here once, shared copy-on-write by every child.
PRELOAD = ("server.cli", "server.cli.identify", "server.cli.camera", "server.cli.campaign", "server.cli.study",
           "server.cli.excitation", "server.cli.kinematics", "server.cli.model", "server.cli.estop",
           "scipy.signal", "scipy.optimize", "mcap.reader", "mcap.writer", "zenoh", "matplotlib.pyplot")


def _preload() -> None:
    import importlib

    os.environ.setdefault("MPLBACKEND", "Agg")
    for name in PRELOAD:
        with contextlib.suppress(ImportError):  # a module this checkout lacks: its commands say so themselves
            importlib.import_module(name)


def _threads() -> int:
    return len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else 1


def serve(path: str) -> dict[str, Any]:
    """Accepts runs until the parent is gone; returns only in a forked child, with its request."""
    me, parent = os.getpid(), os.getppid()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path + ".binding")
    listener.listen(64)
    os.rename(path + ".binding", path)  # the path appears once connections are accepted
    waiting: dict[int, socket.socket] = {}  # child pid -> the connection that waits for its exit code
    children_modules: dict[int, str] = {}  # child pid -> the file it names its new modules in
    stopping = False

    def _stop(*_: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, _stop)
    try:
        while not stopping and os.getppid() == parent:
            ready, _, _ = select.select([listener], [], [], 0.05)
            if ready:
                conn, _ = listener.accept()
                with conn.makefile("rb") as lines:
                    request = json.loads(lines.readline())
                if _threads() != 1:  # a fork would copy locks held by threads that do not follow
                    conn.sendall(b"refused: the fork server has threads\n")
                    conn.close()
                    continue
                sys.stdout.flush()
                sys.stderr.flush()
                gc.freeze()  # what the server imported since, out of the child's collections too
                pid = os.fork()
                if pid == 0:
                    listener.close()
                    for other in waiting.values():
                        other.close()
                    conn.close()
                    signal.signal(signal.SIGTERM, signal.SIG_DFL)
                    request["modules"] = f"{path}.{os.getpid()}.modules"
                    return request
                conn.sendall(f"{pid}\n".encode())
                waiting[pid] = conn
                children_modules[pid] = f"{path}.{pid}.modules"
            while waiting:
                pid, status = os.waitpid(-1, os.WNOHANG)
                if pid == 0:
                    break
                if (modules := children_modules.pop(pid, None)) is not None:
                    import_what_children_did(modules)
                if (conn := waiting.pop(pid, None)) is not None:
                    with contextlib.suppress(OSError):  # the client is gone (its test timed out and left)
                        conn.sendall(f"{os.waitstatus_to_exitcode(status)}\n".encode())
                    conn.close()
    finally:
        if os.getpid() == me:
            listener.close()
            for pid in waiting:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
    sys.exit(0)


def run_child(request: dict[str, Any]) -> None:
    """In the forked child: become the asking test's ``python -m server.cli <argv>``, run it and exit
    as the interpreter would (non-daemon threads joined, cycles collected, ``atexit`` handlers run,
    output flushed, the exit code of ``SystemExit``), but without finalising the modules it was
    forked with: that touched every preloaded object and copied the server's whole heap."""
    import atexit
    import gc
    import runpy
    import threading
    import traceback

    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    for fd, key in ((1, "stdout"), (2, "stderr")):
        out = os.open(request[key], os.O_WRONLY | os.O_TRUNC)
        os.dup2(out, fd)
        os.close(out)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    with contextlib.suppress(OSError):  # lowering a nice needs the right to: the server's then
        os.setpriority(os.PRIO_PROCESS, 0, int(request["nice"]))
    sys.argv = ["-m", *request["argv"]]  # runpy sets argv[0] to the module's file, as `python -m` does
    sys.path[0] = request["cwd"]
    before = set(sys.modules)
    code = 0
    try:
        runpy.run_module("server.cli", run_name="__main__", alter_sys=True)
    except SystemExit as stop:
        if stop.code is None:
            code = 0
        elif isinstance(stop.code, int):
            code = stop.code
        else:
            print(stop.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001 - what the interpreter does with an uncaught exception
        traceback.print_exc()
        code = 1
    try:
        threading._shutdown()  # type: ignore[attr-defined]  # as at a normal exit
        gc.collect()
        atexit._run_exitfuncs()
        with open(request["modules"], "w") as imported:  # for the server to import before the next runs
            imported.write("\n".join(sorted(set(sys.modules) - before)))
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        os._exit(code)


def import_what_children_did(path: str) -> None:
    """Imports the modules a child imported (a file of names), so that later children have them."""
    import importlib

    try:
        with open(path) as names:
            wanted = [name for name in names.read().splitlines() if name not in sys.modules and name != "__main__"]
        os.unlink(path)
    except OSError:
        return
    for name in wanted:
        with contextlib.suppress(BaseException):  # a module that needs its own process stays the child's
            importlib.import_module(name)


if __name__ == "__main__":
    sys.path[0] = os.getcwd()  # as `python -m` would have it: the project, not tests/
    _preload()
    run_child(serve(sys.argv[1]))
