"""A campaign's analysis runs in a child process (server/analysis_process.py): its result and its
exceptions come back, and a child that dies is a clear error, not a hang. What it buys the console
(its interpreter free, its memory back) is measured by benchmarks/analysis_isolation.py."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from bridge.archive import ArchiveError
from server.analysis_process import AnalysisDied, AnalysisStopped, run_in_child


def _answer(x: int, *, y: int = 0) -> dict:
    return {"sum": x + y, "pid": os.getpid()}


def _fails(message: str) -> None:
    raise ValueError(message)


def _dies() -> None:
    os.kill(os.getpid(), signal.SIGKILL)  # what the kernel's OOM killer does


def _unpicklable() -> object:
    return threading.Lock()


def _archive_error(path: str) -> None:
    raise ArchiveError(path, "damaged MCAP file (truncated)")


def _sleeps(seconds: float) -> float:
    time.sleep(seconds)
    return seconds


def _sleeps_after_sigint(seconds: float) -> float:
    """Sends itself a SIGINT (a Ctrl-C to the terminal's process group), then works on."""
    os.kill(os.getpid(), signal.SIGINT)
    return _sleeps(seconds)


class _Unreadable(Exception):
    def __init__(self, a: int, b: int) -> None:  # pickled by its message only: cannot be rebuilt
        super().__init__(f"{a}/{b}")


def _raises_unreadable() -> None:
    raise _Unreadable(1, 2)


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


def test_an_archive_error_comes_back_as_itself_with_the_childs_traceback() -> None:
    """Review of session 51: ArchiveError(path, reason) came back as "TypeError: __init__() missing
    1 required positional argument", its reason lost."""
    with pytest.raises(ArchiveError, match="damaged MCAP file") as err:
        run_in_child(_archive_error, "/data/x.mcap")
    assert err.value.reason == "damaged MCAP file (truncated)"
    assert any("_archive_error" in note for note in err.value.__notes__)


def test_an_exception_that_cannot_be_rebuilt_comes_back_as_its_text() -> None:
    with pytest.raises(RuntimeError, match="_Unreadable: 1/2"):
        run_in_child(_raises_unreadable)


def test_a_stop_kills_the_child_and_says_so() -> None:
    stop = threading.Event()
    threading.Timer(1.0, stop.set).start()
    with pytest.raises(AnalysisStopped, match="the identification was stopped"):
        run_in_child(_sleeps, 60.0, what="identification", stop=stop)


def test_a_ctrl_c_to_the_process_group_is_the_callers_to_handle_not_the_childs() -> None:
    """Review of session 51: the child shared the console's process group and died of a Ctrl-C with
    a KeyboardInterrupt; the analysis was then recorded failed ("killed, or out of memory?")."""
    assert run_in_child(_sleeps_after_sigint, 0.5) == 0.5


PARENT = r"""
import sys, time
sys.path[:0] = sys.argv[2:]
from test_analysis_process import _sleeps_and_says
from server.analysis_process import run_in_child
run_in_child(_sleeps_and_says, sys.argv[1])
"""


def _sleeps_and_says(pid_file: str) -> None:
    Path(pid_file).write_text(str(os.getpid()))
    _sleeps(90.0)  # longer than the test waits for it to end


def test_the_child_ends_with_its_parent(tmp_path) -> None:
    """Review of session 51: `xneck up` kills a console slow to stop; its analysis' child then ran on
    under init, holding its memory."""
    pid_file = tmp_path / "child.pid"
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(pid_file), os.path.dirname(__file__), *sys.path])
    try:
        deadline = 30.0
        start = time.monotonic()
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() - start < deadline and parent.poll() is None
            time.sleep(0.05)
        child = int(pid_file.read_text())
        parent.kill()
        parent.wait(10)
        start = time.monotonic()
        while _alive(child):
            assert time.monotonic() - start < deadline, "the child outlived its parent"
            time.sleep(0.05)
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait(10)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as f:
            return not any(line.startswith("State:") and "Z" in line.split()[1] for line in f)
    except FileNotFoundError:
        return False


def test_an_identification_stopped_during_its_analysis_keeps_its_outcome_and_archive(tmp_path) -> None:
    """An abort (or the console closing) during the analysis kills its process: the recording stays
    ``finished``, the archive is not amended to ``analysis_failed``, the message says what to run."""
    from bridge import bus
    from bridge.archive import write_campaign
    from bridge.archive_read import read_campaign_info
    from server.campaign_runner import CampaignResult, analyse_identification

    state = bus.MotorState(seq=1, stamp_s=0.0, theta_rad=[0.0] * 4, force_applied_N=[5.0] * 4, drive="active",
                           epoch="e", bridge="b")
    path = write_campaign(tmp_path / "c.mcap", [(bus.MOTOR_STATE, 1, state)],
                          {"campaign_id": "c", "kind": "identification", "outcome": "finished"})
    stop = threading.Event()
    stop.set()
    result = CampaignResult("c", path, "finished", "")
    analyse_identification(result, None, stop=stop)
    assert result.outcome == "finished" and result.identification is None
    assert result.analysis.startswith("identification not done: the identification was stopped")
    assert f"xneck identify {path}` does it" in result.message
    assert read_campaign_info(path).get("outcome") == "finished"
    # not stopped, the same archive's analysis fails (one state is no campaign) and says so
    failed = CampaignResult("c", path, "finished", "")
    analyse_identification(failed, None, stop=threading.Event())
    assert failed.outcome == "analysis_failed" and failed.analysis.startswith("identification failed")
