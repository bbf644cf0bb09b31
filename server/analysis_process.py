"""A finished campaign's analysis in a child process, not in the console's.

The identification of a 600 s campaign held the console's interpreter for 29 s and its memory at
944 MB (568 MB kept after: Python keeps what it freed), and ``/api/system/health`` answered in up
to 0.84 s meanwhile: the analysis' pure-Python loops hold the GIL (audit of 2026-11-30,
docs/console.md "Long campaigns"). :func:`run_in_child` runs such a function in a spawned process
(never forked: the console has Zenoh's and uvicorn's threads) and returns its result; the memory
goes with the process. ``benchmarks/analysis_isolation.py`` measures both.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any, TypeVar

T = TypeVar("T")

#: s between two looks at the child while waiting for its result.
POLL_S = 0.2
#: s a child that sent its result is given to exit before it is killed.
EXIT_WAIT_S = 5.0


class AnalysisDied(RuntimeError):
    """The analysis' process ended without a result (killed, out of memory, or a crash)."""


def _child(conn: Connection, fn: Callable[..., Any], args: tuple, kwargs: dict) -> None:
    try:
        result: tuple[bool, Any] = (True, fn(*args, **kwargs))
    except Exception as exc:  # noqa: BLE001 - handed to the parent, which raises it
        result = (False, exc)
    try:
        conn.send(result)
    except Exception as exc:  # noqa: BLE001 - an unpicklable result or exception: its text goes
        conn.send((False, RuntimeError(f"{type(exc).__name__}: {exc} (the analysis' result could not be sent)")))
    finally:
        conn.close()


def run_in_child(fn: Callable[..., T], /, *args: Any, what: str = "analysis", **kwargs: Any) -> T:
    """``fn(*args, **kwargs)`` in a spawned child process (``fn`` a module-level function, its
    arguments and result picklable); its exception is raised here. The child is daemonic: it ends
    with this process. Raises :class:`AnalysisDied` naming ``what`` and the exit code if the child
    ends without a result."""
    ctx = multiprocessing.get_context("spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, fn, args, kwargs), name=f"xneck-{what}", daemon=True)
    started = time.monotonic()
    proc.start()
    send.close()
    try:
        while not recv.poll(POLL_S):
            if not proc.is_alive() and not recv.poll(0):
                raise AnalysisDied(f"the {what} process ended with exit code {proc.exitcode} after "
                                   f"{time.monotonic() - started:.0f} s without a result (killed, or out of memory?)")
        try:
            ok, value = recv.recv()
        except EOFError:
            proc.join(EXIT_WAIT_S)
            raise AnalysisDied(f"the {what} process ended with exit code {proc.exitcode} without a result") from None
    finally:
        recv.close()
        proc.join(EXIT_WAIT_S)
        if proc.is_alive():
            proc.kill()
            proc.join(EXIT_WAIT_S)
    if not ok:
        raise value
    return value
