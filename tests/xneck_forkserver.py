"""A fork server for the suite's ``xneck`` processes (tests/forkserver_client.py is its client).

The suite starts ``python -m server.cli`` some hundreds of times: commands run to completion (the
``xneck`` fixture) and the stacks' processes (tests/test_stack.py's ``_procs``). Each read and
initialised numpy, typer, pydantic and the project again, and a bridge or a controller loaded its
numba kernels from the cache (0.4-2 s of CPU apiece, on a VM whose page cache is emptied all the
time). This server imports them and loads the kernels once, then forks a child per process: the
child takes the asking test's working directory, environment, nice and CPUs, its output files,
``/dev/null`` as stdin and, if asked, a session of its own (``start_new_session``), and runs
``server.cli`` as ``python -m`` does (``runpy``, ``sys.path[0]`` the working directory). It exits as
the interpreter would (non-daemon threads joined, cycles collected, ``atexit`` handlers run, output
flushed, the code of ``SystemExit``) but without finalising the modules it was forked with.

Protocol, over a Unix socket, one process per connection: the client sends one JSON line (``argv``,
``cwd``, ``env``, ``nice``, ``cpus``, ``session``, ``stdout``, ``stderr``: paths of files the child
writes, the same path for both as ``stderr=STDOUT``, ``append``), the server answers the child's pid on one
line, then its exit code (``subprocess`` convention: -N for a signal) on another when it has ended.
The server stops when its parent (the pytest worker) is gone or on SIGTERM.

Run as ``python tests/xneck_forkserver.py SOCKET PADDING`` (PADDING: :data:`CMDLINE_ROOM` characters,
the room the children's command lines are written in); it binds SOCKET once its imports are done.
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

# What `xneck`'s processes import beyond `server.cli` itself (their heavier dependencies are
# imported inside the commands): imported here once, shared copy-on-write by every child. A list,
# not what the children were seen to import: importing those here (anyio's and asyncio's modules
# among them, after an `xneck up` had run) left the next forked console's threadpool without its
# asyncio task (anyio: "cannot create weak reference to 'NoneType' object").
PRELOAD = ("server.cli", "server.cli.identify", "server.cli.camera", "server.cli.campaign", "server.cli.study",
           "server.cli.excitation", "server.cli.kinematics", "server.cli.model", "server.cli.estop",
           "server.cli.processes", "server.cli.up", "server.cli.serve", "server.cli.bus", "server.cli.calibrate",
           "typer._adapters", "typer.rich_utils", "rich.markdown", "rich.traceback", "rich.syntax", "pydantic",
           "twin.jsonout", "importlib.metadata", "zoneinfo", "csv", "secrets",
           "scipy.signal", "scipy.optimize", "mcap.reader", "mcap.writer", "zenoh", "matplotlib.pyplot",
           "bridge.node", "twin.sim.driver", "controller.process", "server.app")


def _preload() -> None:
    import importlib

    os.environ.setdefault("MPLBACKEND", "Agg")
    for name in PRELOAD:
        with contextlib.suppress(ImportError):  # a module this checkout lacks: its commands say so themselves
            importlib.import_module(name)
    with contextlib.suppress(Exception):  # best effort: a child loads what is missing itself
        _load_kernels()


def _load_kernels() -> None:
    """The numba kernels of the twin and of the three laws, loaded from numba's cache (or compiled)
    here once: about 1 s of every bridge's and controller's start-up."""
    from controller.laws import ComputedTorque, LawConfig
    from twin.model.params import load_params
    from twin.sim.simulator import Twin

    Twin()
    for law in (1, 2, 3):
        ComputedTorque(load_params(), LawConfig(law=law))


def _threads() -> int:
    return len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else 1


def serve(path: str) -> dict[str, Any]:
    """Accepts runs until the parent is gone; returns only in a forked child, with its request."""
    me, parent = os.getpid(), os.getppid()
    start, end = cmdline_area()
    room = end - start
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path + ".binding")
    listener.listen(64)
    os.rename(path + ".binding", path)  # the path appears once connections are accepted
    waiting: dict[int, socket.socket] = {}  # child pid -> the connection that waits for its exit code
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
                if len(child_cmdline(request["argv"])) > room:  # this one only: a process of its own
                    conn.sendall(b"too long\n")
                    conn.close()
                    continue
                sys.stdout.flush()
                sys.stderr.flush()
                gc.freeze()  # what the server imported since, out of the child's collections too
                ready_r, ready_w = os.pipe()
                pid = os.fork()
                if pid == 0:
                    os.close(ready_r)
                    listener.close()
                    for other in waiting.values():
                        other.close()
                    conn.close()
                    signal.signal(signal.SIGTERM, signal.SIG_DFL)
                    request["ready_fd"] = ready_w
                    return request
                os.close(ready_w)
                os.read(ready_r, 1)  # the child is set up (run_child), or dead: then b""
                os.close(ready_r)
                conn.sendall(f"{pid}\n".encode())
                waiting[pid] = conn
            while waiting:
                pid, status = os.waitpid(-1, os.WNOHANG)
                if pid == 0:
                    break
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


#: Bytes the server's own command line is padded with: room for its children's (:func:`set_cmdline`).
CMDLINE_ROOM = 8192
PR_SET_MM, PR_SET_MM_ARG_END = 35, 9  # prctl(2)


def cmdline_area() -> tuple[int, int]:
    """(start, end) addresses of this process's command line (proc(5): /proc/self/stat fields 48-49)."""
    with open("/proc/self/stat") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return int(fields[45]), int(fields[46])  # fields 48 and 49, counted from field 3 after the ")"


def child_cmdline(argv: list[str]) -> bytes:
    """What /proc/PID/cmdline shows for ``python -m server.cli <argv>``."""
    return b"".join(a.encode() + b"\0" for a in [sys.executable, "-m", "server.cli", *argv])


def set_cmdline(title: bytes) -> None:
    """This process's /proc/PID/cmdline becomes ``title`` (NUL-separated, as the kernel keeps argv):
    a forked child is then the `python -m server.cli ...` it runs for everything that finds xneck
    processes by their command line (``server.child_processes.local_processes``, ``ps``, tests).
    Written over the server's own (padded) argv; its end moved to the title's where the kernel lets
    this process (CAP_SYS_RESOURCE), else the rest stays NUL bytes (empty trailing arguments)."""
    import ctypes

    start, end = cmdline_area()
    ctypes.memmove(start, title + b"\0" * (end - start - len(title)), end - start)
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_MM, PR_SET_MM_ARG_END, ctypes.c_ulong(start + len(title)), 0, 0)


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

    # What the asker may act on as soon as it has the pid (a killpg, an isolate() that sets the
    # CPUs and nice, a look at /proc/PID/cmdline) is done before the server answers it.
    set_cmdline(child_cmdline(request["argv"]))
    if request.get("session"):
        os.setsid()
    with contextlib.suppress(OSError):  # lowering a nice needs the right to: the server's then
        os.setpriority(os.PRIO_PROCESS, 0, int(request["nice"]))
    if request.get("cpus"):
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setaffinity(0, request["cpus"])
    os.write(request["ready_fd"], b"1")
    os.close(request["ready_fd"])
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.close(null)
    out = os.open(request["stdout"], os.O_WRONLY | (os.O_APPEND if request.get("append") else os.O_TRUNC))
    os.dup2(out, 1)
    if request["stderr"] == request["stdout"]:
        os.dup2(out, 2)
    else:
        err = os.open(request["stderr"], os.O_WRONLY | os.O_TRUNC)
        os.dup2(err, 2)
        os.close(err)
    os.close(out)
    os.chdir(request["cwd"])
    os.environ.clear()
    os.environ.update(request["env"])
    if os.environ.get("PYTHONUNBUFFERED"):  # as `python -u` makes them: every write reaches the file
        import io

        sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding=sys.stdout.encoding,
                                      errors=sys.stdout.errors, write_through=True)
        sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding=sys.stderr.encoding,
                                      errors=sys.stderr.errors, write_through=True)
    sys.argv = ["-m", *request["argv"]]  # runpy sets argv[0] to the module's file, as `python -m` does
    sys.path[0] = request["cwd"]
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
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        os._exit(code)


if __name__ == "__main__":
    sys.path[0] = os.getcwd()  # as `python -m` would have it: the project, not tests/
    _preload()
    run_child(serve(sys.argv[1]))
