"""A finished campaign's analysis in a child process, not in the console's.

The identification of a 600 s campaign held the console's interpreter for 29 s and its memory at
944 MB (568 MB kept after: Python keeps what it freed), and ``/api/system/health`` answered in up
to 0.84 s meanwhile: the analysis' pure-Python loops hold the GIL (audit of 2026-11-30,
docs/console.md "Long campaigns"). :func:`run_in_child` runs such a function in a spawned process
(never forked: the console has Zenoh's and uvicorn's threads) and returns its result; the memory
goes with the process. ``benchmarks/analysis_isolation.py`` measures both.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import threading
import time
import traceback
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, TypeVar

from server.child_processes import die_with_parent

T = TypeVar("T")

#: s between two looks at the child while waiting for its result.
POLL_S = 0.2
#: s a child that sent its result is given to exit before it is killed.
EXIT_WAIT_S = 5.0


class AnalysisDied(RuntimeError):
    """The analysis' process ended without a result (killed, out of memory, or a crash)."""


class AnalysisStopped(RuntimeError):
    """The caller's stop was set (the campaign aborted, the console closing): the child was killed."""


def _sendable(exc: Exception) -> Exception:
    """``exc`` with the child's traceback as a note, if it survives pickling both ways (ArchiveError's
    did not: its two-argument constructor came back as a TypeError), else a RuntimeError with its text."""
    exc.add_note("in the analysis' process:\n" + "".join(traceback.format_exception(exc)).rstrip())
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - whatever pickle raises, the text goes
        return RuntimeError(f"{type(exc).__name__}: {exc}")


def _child(conn: Connection, parent_pid: int, fn: Callable[..., Any], args: tuple, kwargs: dict) -> None:
    # The parent decides when this ends: a Ctrl-C to the terminal's process group is the parent's to
    # handle (it had ended the analysis as "killed, or out of memory?"), and its death ends this one
    # (a console killed by `xneck up` had left it running under init).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    die_with_parent(parent_pid)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s [analysis]: %(message)s")
    try:
        result: tuple[bool, Any] = (True, fn(*args, **kwargs))
    except Exception as exc:  # noqa: BLE001 - handed to the parent, which raises it
        result = (False, _sendable(exc))
    try:
        conn.send(result)
    except Exception as exc:  # noqa: BLE001 - an unpicklable result: its text goes
        conn.send((False, RuntimeError(f"{type(exc).__name__}: {exc} (the analysis' result could not be sent)")))
    finally:
        conn.close()


def run_in_child(fn: Callable[..., T], /, *args: Any, what: str = "analysis", stop: threading.Event | None = None,
                 **kwargs: Any) -> T:
    """``fn(*args, **kwargs)`` in a spawned child process (``fn`` a module-level function, its
    arguments and result picklable); its exception is raised here, with the child's traceback as a
    note. The child ignores SIGINT and ends with this process. ``stop`` set while it runs: the child
    is killed and :class:`AnalysisStopped` raised. Raises :class:`AnalysisDied` naming ``what`` and
    the exit code if the child ends without a result."""
    ctx = multiprocessing.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, os.getpid(), fn, args, kwargs), name=f"xneck-{what}", daemon=True)
    started = time.monotonic()

    def stopped() -> bool:
        return stop is not None and stop.is_set()

    try:
        try:
            proc.start()
        finally:
            send.close()
        while not recv.poll(POLL_S):
            if stopped() and not recv.poll(0):
                proc.kill()
                raise AnalysisStopped(f"the {what} was stopped after {time.monotonic() - started:.0f} s")
            if not proc.is_alive() and not recv.poll(0):
                if stopped():  # a Ctrl-C reached it before it could ignore it: the caller's stop
                    raise AnalysisStopped(f"the {what} was stopped after {time.monotonic() - started:.0f} s")
                raise AnalysisDied(f"the {what} process ended with exit code {proc.exitcode} after "
                                   f"{time.monotonic() - started:.0f} s without a result (killed, or out of memory?)")
        try:
            ok, value = recv.recv()
        except EOFError:
            proc.join(EXIT_WAIT_S)
            raise AnalysisDied(f"the {what} process ended with exit code {proc.exitcode} without a result") from None
    finally:
        recv.close()
        if proc.pid is not None:
            proc.join(EXIT_WAIT_S)
            if proc.is_alive():
                proc.kill()
                proc.join(EXIT_WAIT_S)
    if not ok:
        raise value
    return value
