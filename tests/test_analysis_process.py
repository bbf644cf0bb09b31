"""A campaign's analysis runs in a child process (server/analysis_process.py): its result and its
exceptions come back, and a child that dies is a clear error, not a hang. What it buys the console
(its interpreter free, its memory back) is measured by benchmarks/analysis_isolation.py."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from server.analysis_process import AnalysisDied, run_in_child


def _answer(x: int, *, y: int = 0) -> dict:
    return {"sum": x + y, "pid": os.getpid()}


def _fails(message: str) -> None:
    raise ValueError(message)


def _dies() -> None:
    os.kill(os.getpid(), signal.SIGKILL)  # what the kernel's OOM killer does


def _unpicklable() -> object:
    return threading.Lock()


def test_the_result_comes_back_from_another_process() -> None:
    out = run_in_child(_answer, 2, y=3)
    assert out["sum"] == 5 and out["pid"] != os.getpid()


def test_the_childs_exception_is_raised_here_with_its_type_and_message() -> None:
    with pytest.raises(ValueError, match="no controller status recorded"):
        run_in_child(_fails, "no controller status recorded")


def test_a_child_killed_is_a_clear_error_not_a_hang() -> None:
    with pytest.raises(AnalysisDied, match=r"the identification process ended with exit code -9 .*without a result"):
        run_in_child(_dies, what="identification")


def test_an_unpicklable_result_is_an_error_naming_it() -> None:
    with pytest.raises(RuntimeError, match="could not be sent"):
        run_in_child(_unpicklable)
