"""``xneck up --robot``: a hung bridge that cannot exit has its drives disabled at once.

A process killed while another real-time task holds its CPU cannot run its exit: the robot's
bridge runs at SCHED_FIFO 50 on the loop's CPU, and a task above it there (another lab program at
real-time priority, a kernel thread) keeps the killed bridge alive, unreaped, for as long as it
runs (a FIFO 60 task spinning 4 s kept one 3.6 s). `xneck up` judged the bridge hung, killed it and
set its drives off only once it had exited: the ESCONs drove the last currents all that time, and
the log said nothing (a fresh-clone CI run of session 52 waited 150 s on a silent log). Now the
supervisor says so at once and runs `xneck bridge --drives-off` beside the dying bridge, and
again after its exit.

Staged for real: the bridge SIGSTOPped (hung), then a FIFO 60 process spinning on the loop's CPU
for :data:`SPIN_S` (bounded, killed at the end whatever happens). It takes the loop's CPU, so the
module is ``realtime`` (alone on the machine). The board is tests/fake_rcpy.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fake_board_log import board_log, levels
from server_harness import wait_until
from test_up_robot import _stuck_report, _up_robot

from bridge.drivers.beaglebone import BLUE_GP0_PINS

pytestmark = [pytest.mark.e2e, pytest.mark.realtime]  # it holds the loop's CPU for SPIN_S

SPIN_S = 30.0  # the judgement (1 s), the kill's wait (1 s), `--drives-off` (a process start); killed once seen
SPINNER = """\
import os, sys, time
os.sched_setaffinity(0, {{{cpu}}})
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(60))
except PermissionError:
    print("refused", flush=True)
    sys.exit(0)
print("spinning", flush=True)
end = time.monotonic() + {spin_s}
while time.monotonic() < end:
    pass
"""


@contextlib.contextmanager
def _spinner(cpu: int):
    """A FIFO 60 process spinning on ``cpu`` for :data:`SPIN_S`, killed at the end if still there."""
    proc = subprocess.Popen([sys.executable, "-c", SPINNER.format(cpu=cpu, spin_s=SPIN_S)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        said = proc.stdout.readline().strip()
        if said == "refused":
            pytest.skip("SCHED_FIFO 60 is not permitted here (RLIMIT_RTPRIO): no task above the bridge to stage")
        assert said == "spinning", proc.stderr.read() if proc.stderr is not None else said
        yield proc
    finally:
        proc.kill()
        proc.wait(30)


def test_a_hung_robot_bridge_that_cannot_exit_has_its_drives_disabled_beside_it(tmp_path: Path) -> None:
    board = tmp_path / "rcpy.log"
    log = tmp_path / "up.log"
    with _up_robot(tmp_path, exit_after_s=300) as (_base, _hub, up, bridge):
        if os.sched_getscheduler(bridge) != os.SCHED_FIFO:
            pytest.skip("the bridge did not get SCHED_FIFO here (not permitted, or XNECK_REALTIME=0)")
        if os.sched_getaffinity(bridge) == os.sched_getaffinity(up.pid):
            pytest.skip("one CPU for everyone: a spinner on the loop's would starve xneck up too")
        assert set(levels(board_log(board), {bridge}).values()) == {1}  # every drive enabled
        (cpu,) = os.sched_getaffinity(bridge)
        os.kill(bridge, signal.SIGSTOP)  # hung
        with _spinner(cpu) as spin:
            said = "its drives were disabled by `xneck bridge --drives-off`"
            assert wait_until(lambda: said in log.read_text() or spin.poll() is not None, SPIN_S + 5, 0.1)
            assert spin.poll() is None, ("the drives were not set off while the bridge could not exit",
                                         _stuck_report(up, bridge, log))
            # the drives are off while the killed bridge is still there, not even a zombie
            assert Path(f"/proc/{bridge}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
            lines = board_log(board)
            assert levels(lines, {pid for pid, *_ in lines} - {bridge}) == dict.fromkeys(BLUE_GP0_PINS, 0)
            assert levels(lines) == dict.fromkeys(BLUE_GP0_PINS, 0)
            printed = log.read_text()
            assert "warning: the bridge hung (its loop silent for" in printed and "killed, not exited after 1 s (state" \
                in printed, printed[-3000:]
        try:  # the spinner gone, the bridge exits and the stack stops as for any hung bridge
            rc = up.wait(120)
        except subprocess.TimeoutExpired:
            rc = None
        assert rc == 1, (rc, _stuck_report(up, bridge, log))
    printed = log.read_text()
    # The controller (FIFO 49, same CPU) was starved too: it may be judged and reaped first, the
    # stack then stopped for it and the bridge's exit seen at the stop.
    error = next((line for line in printed.splitlines() if line.startswith("error: the ")), "")
    assert error.startswith(("error: the bridge hung (its loop silent for", "error: the controller hung")), printed[-3000:]
    # beside the dying bridge, then again after its exit (a thread preempted in a GPIO write ends it
    # first): before the error when its death is handled, at the stack's stop when the controller's is
    assert printed.count(said) == 2, printed[-3000:]
    assert printed.index(said) < printed.index(error), printed[-3000:]
    time.sleep(0.1)
    assert levels(board_log(board)) == dict.fromkeys(BLUE_GP0_PINS, 0)  # and they stay off
