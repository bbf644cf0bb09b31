"""Stopping a child process (server/child_processes.py): SIGTERM, a grace period, SIGKILL; never an
exception for a child slow to exit.

Audit of 2026-11-30: under another real-time load, a hung controller that `xneck up` killed stayed
unreaped for more than 16 s (its threads could not run their exit). The supervisor's wait raised
``TimeoutExpired``, its clean-up raised it again, and `xneck up` ended in a traceback, having stopped
neither the bridge nor the console and left its socket folder. The children here are real
processes; only the lateness of a killed one's exit is staged (its ``wait`` says "not yet" a few
times), since a process that outlives SIGKILL for seconds cannot be made on demand.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable, Iterator

import pytest

from server.child_processes import STILL_EXITING, kill_child, stop_child

IGNORES_SIGTERM = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('ready', flush=True); time.sleep(60)"


class SlowToExit(subprocess.Popen):
    """A real child whose exit, once killed, is seen ``late`` waits later than it happens."""

    def __init__(self, late: int) -> None:
        super().__init__([sys.executable, "-c", IGNORES_SIGTERM], stdout=subprocess.PIPE, text=True)
        assert self.stdout is not None and self.stdout.readline().strip() == "ready"  # its handler is set
        self.late, self.killed = late, False

    def kill(self) -> None:
        self.killed = True
        super().kill()

    def wait(self, timeout: float | None = None) -> int:
        if self.killed and self.late > 0:
            self.late -= 1
            raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
        return super().wait(timeout)


@pytest.fixture
def slow_child() -> Iterator[Callable[[int], SlowToExit]]:
    """Makes :class:`SlowToExit` children; each is killed and reaped at the end, whatever happened."""
    made: list[SlowToExit] = []

    def make(late: int) -> SlowToExit:
        made.append(SlowToExit(late))
        return made[-1]

    yield make
    for proc in made:
        proc.late = 0
        proc.kill()
        proc.wait()
        proc.stdout.close()  # type: ignore[union-attr]


def test_a_child_that_ignores_sigterm_is_killed(slow_child) -> None:
    proc = slow_child(0)
    assert stop_child(proc, 0.3) == "killed"
    assert proc.returncode is not None and proc.returncode < 0


def test_a_killed_child_slow_to_exit_is_said_not_raised(slow_child) -> None:
    proc = slow_child(1)
    assert stop_child(proc, 0.3) == STILL_EXITING  # raised TimeoutExpired before
    assert proc.killed and proc.wait(10) < 0  # reaped later, as the caller's next look does
    assert stop_child(proc, 0.3) == ""  # ended: nothing to do


def test_killing_a_hung_child_waits_briefly_and_answers_whether_it_ended(slow_child) -> None:
    proc = slow_child(1)
    assert kill_child(proc, 0.2) is False  # xneck up's supervisor goes on and judges it on a later pass
    assert kill_child(proc, 5.0) is True  # killed again: harmless; now seen ended
    assert proc.returncode is not None and proc.returncode < 0
    assert kill_child(proc, 0.2) is True  # an ended (reaped) child: no error
