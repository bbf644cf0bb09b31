"""Isolation of the loop's processes (issue 21): real-time priority and CPU affinity where the
kernel permits, what each process got read back and reported, refusals named."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from bridge.runtime import LOOP_NICE
from server import child_processes as cp


@pytest.fixture
def child():
    p = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        yield p
    finally:
        p.kill()
        p.wait(5)


def test_a_loop_process_gets_real_time_priority_and_the_loop_cpu_or_says_why_not(child):
    got = cp.isolate(child.pid, "controller")
    loop_cpus, _ = cp.cpu_split()
    assert got["pid"] == child.pid and got["kind"] == "controller"
    assert got["cpus"] == sorted(loop_cpus) or any("affinity" in r for r in got["refused"]), got
    if got["policy"] == "fifo":
        assert got["rt_priority"] == cp.LOOP_PRIORITY["controller"] and not got["refused"]
    else:  # not permitted here: the fallback and the refusal are on record
        assert any("SCHED_FIFO" in r for r in got["refused"]), got
        assert got["nice"] == LOOP_NICE or any("nice" in r for r in got["refused"]), got
    assert cp.scheduling(child.pid, "controller") == got  # read back from the kernel, not remembered


def test_the_console_leaves_the_loop_cpu_and_realtime_can_be_turned_off(child, monkeypatch):
    got = cp.isolate(child.pid, "server")
    loop_cpus, other_cpus = cp.cpu_split()
    assert got["policy"] == "other" and got["rt_priority"] == 0
    if loop_cpus != other_cpus:  # two CPUs or more: the console never shares the loop's
        assert set(got["cpus"]) == other_cpus or got["refused"], got
    monkeypatch.setenv(cp.ENV_REALTIME, "0")
    with subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"]) as other:
        try:
            off = cp.isolate(other.pid, "bridge")
            assert off["policy"] == "other" and off["refused"] == [f"{cp.ENV_REALTIME}=0: scheduling left alone"]
            assert off["cpus"] == sorted(os.sched_getaffinity(other.pid))
        finally:
            other.kill()


def test_cpu_split_keeps_one_cpu_for_the_loop(monkeypatch):
    monkeypatch.delenv(cp.ENV_LOOP_CPUS, raising=False)  # the suite's workers set one each (conftest)
    assert cp.cpu_split({0, 1, 2, 3}) == ({3}, {0, 1, 2})
    assert cp.cpu_split({0}) == ({0}, {0})


def test_local_processes_finds_xneck_processes_by_their_command_line(child):
    assert cp._kind_of([sys.executable, "-m", "server.cli", "controller", "--law", "2"]) == "controller"
    assert cp._kind_of(["/venv/bin/xneck", "bridge", "--driver", "twin"]) == "bridge"
    assert cp._kind_of([sys.executable, "-m", "pytest"]) == ""
    me = [p for p in cp.local_processes() if p["pid"] == os.getpid()]
    assert me and me[0]["kind"] == "server" and "policy" in me[0]


def test_the_split_is_of_the_machine_not_of_the_caller_already_off_the_loop_cpu():
    # The console runs off the loop's CPU and starts campaigns' loop processes itself
    # (campaign_runner): their CPU must still be the loop's, not the console's.
    loop_cpus, other_cpus = cp.cpu_split()
    if loop_cpus == other_cpus:
        pytest.skip("one CPU: nothing to split")
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, other_cpus)
    try:
        assert cp.cpu_split() == (loop_cpus, other_cpus)
    finally:
        os.sched_setaffinity(0, before)


@pytest.mark.parametrize("started_nice", [0, 5], ids=["default", "under-nice-5"])
def test_every_thread_is_isolated_those_started_before_and_after_but_a_niced_one_is_left_alone(started_nice):
    # A slow caller (a loaded machine, or a parent the child starves) isolates a process that
    # has already started threads: they get the loop's priority and CPU too, later ones inherit,
    # and a thread that made itself nicer than its process (the bridge's hold worker) stays so.
    # Started under `nice`, every thread inherits that nice: they are still the process's own
    # threads (this once left all but the main thread unisolated).
    code = ("import os, sys, threading, time\n"
            "def niced():\n"
            "    os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)\n"
            "    time.sleep(30)\n"
            "threading.Thread(target=time.sleep, args=(30,), daemon=True).start()\n"
            "threading.Thread(target=niced, daemon=True).start()\n"
            "time.sleep(0.2)\n"
            "print('started', flush=True)\n"
            "sys.stdin.readline()\n"
            "threading.Thread(target=time.sleep, args=(30,), daemon=True).start()\n"
            "time.sleep(30)\n")
    with subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                          preexec_fn=(lambda: os.nice(started_nice)) if started_nice else None) as p:
        try:
            assert p.stdout is not None and p.stdin is not None
            assert p.stdout.readline().strip() == "started"
            got = cp.isolate(p.pid, "controller")
            p.stdin.write("go\n")
            p.stdin.flush()
            counts: dict[str, int] = {}
            for _ in range(200):
                counts = cp.thread_scheduling(p.pid)
                if sum(counts.values()) == 4:
                    break
                time.sleep(0.05)
            loop_cpus, _ = cp.cpu_split()
            if not got["refused"]:
                assert counts == {f"fifo {cp.LOOP_PRIORITY['controller']}": 3, "other": 1}, counts
                for tid in os.listdir(f"/proc/{p.pid}/task"):
                    assert os.sched_getaffinity(int(tid)) == loop_cpus, tid
            else:
                assert sum(counts.values()) == 4, counts
        finally:
            p.kill()
    assert cp.thread_scheduling(p.pid) == {}  # gone: nothing, no error


def test_the_controllers_own_threads_run_one_below_its_tick_on_zenohs_threads():
    # FIFO does not share a CPU between equals: the loop's housekeeping at the tick's priority
    # kept a state's tick waiting until it blocked. The tick (Zenoh's threads) must preempt it.
    with subprocess.Popen(cp.xneck_argv("controller", "--law", "2", "--listen", "tcp/127.0.0.1:0"),
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as p:
        try:
            got = cp.isolate(p.pid, "controller")
            if got["policy"] != "fifo":
                pytest.skip(f"no real-time priority here: {got['refused']}")
            tick = cp.LOOP_PRIORITY["controller"]
            counts: dict[str, int] = {}
            for _ in range(600):  # imports and the warm-up first, on a loaded machine
                counts = cp.thread_scheduling(p.pid)
                if os.sched_getparam(p.pid).sched_priority == tick - 1:
                    break
                time.sleep(0.1)
            assert os.sched_getparam(p.pid).sched_priority == tick - 1, counts  # the main thread
            assert counts.get(f"fifo {tick}", 0) >= 1, counts  # Zenoh's threads, the tick's
        finally:
            p.kill()


def test_a_loop_process_takes_the_priority_asked_for_at_its_loop_each_thread_at_its_place():
    """``xneck up`` and the campaign runner start a loop process on the loop's CPU only, with
    ``XNECK_LOOP_PRIORITY`` (:func:`server.child_processes.loop_environ`); at its loop's start it
    takes that priority itself (bridge.runtime.take_loop_priority): every thread, but those that
    placed themselves (the bridge's hold worker out of real-time scheduling, the controller's own
    threads one below). Fresh-user audit of 2026-12-01: taken at exec, the imports had starved
    another stack's controller on that CPU."""
    code = ("import os, sys, threading, time\n"
            "from bridge.runtime import arrange_thread, take_loop_priority\n"
            "def placed(offset):\n"
            "    arrange_thread(offset)\n"
            "    time.sleep(30)\n"
            "for offset in (None, -1):\n"
            "    threading.Thread(target=placed, args=(offset,), daemon=True).start()\n"
            "threading.Thread(target=time.sleep, args=(30,), daemon=True).start()\n"
            "time.sleep(0.3)\n"
            "print(os.sched_getscheduler(0), flush=True)\n"
            "print(repr(take_loop_priority()), flush=True)\n"
            "time.sleep(30)\n")
    env = {**os.environ, **cp.loop_environ("controller")}
    if not cp.loop_environ("controller"):
        pytest.skip("XNECK_REALTIME=0: no priority asked for")
    prio = cp.LOOP_PRIORITY["controller"]
    with subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=env) as p:
        try:
            assert p.stdout is not None
            cp.isolate(p.pid, "controller", realtime=False)
            assert p.stdout.readline().strip() == str(os.SCHED_OTHER)  # not at its start
            why = p.stdout.readline().strip()
            counts = cp.thread_scheduling(p.pid)
            if why != "''":
                assert "SCHED_FIFO" in why and counts.get(f"fifo {prio}", 0) == 0, (why, counts)
                pytest.skip(f"no real-time priority here: {why}")
            assert counts == {f"fifo {prio}": 2, f"fifo {prio - 1}": 1, "other": 1}, counts
        finally:
            p.kill()
    assert cp.loop_environ("server") == {} and cp.loop_environ("camera") == {}


def test_a_priority_asked_for_that_is_none_is_said_and_nothing_changes(monkeypatch):
    from bridge.runtime import ENV_LOOP_PRIORITY, take_loop_priority

    before = os.sched_getscheduler(0)
    for value in ("high", "0", "99", "-5"):
        monkeypatch.setenv(ENV_LOOP_PRIORITY, value)
        assert "is no real-time priority" in take_loop_priority(), value
    monkeypatch.delenv(ENV_LOOP_PRIORITY)
    assert take_loop_priority() == "" and os.sched_getscheduler(0) == before


def test_where_fifo_is_refused_a_loop_thread_falls_back_to_the_loop_nice_and_says_why():
    """The one fallback both placements use (bridge.runtime.fifo_or_nice: the supervisor's
    isolate and the loop's own take_loop_priority): SCHED_FIFO refused (no CAP_SYS_NICE, no
    RLIMIT_RTPRIO) gives nice LOOP_NICE and the refusal; in a child, whose nice it changes."""
    script = (
        "import errno, os, threading\n"
        "from bridge.runtime import fifo_or_nice\n"
        "def refuse(*_a):\n"
        "    raise PermissionError(errno.EPERM, 'Operation not permitted')\n"
        "os.sched_setscheduler = refuse\n"
        "tid = threading.get_native_id()\n"
        "print(repr(fifo_or_nice(tid, 49)), os.getpriority(os.PRIO_PROCESS, tid), flush=True)\n")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True)
    refused, nice = out.stdout.rsplit(" ", 1)
    assert refused.startswith("['SCHED_FIFO 49: Operation not permitted'"), out.stdout
    # lowering nice needs the right to (CAP_SYS_NICE): without it, the second refusal is said
    assert (int(nice) == LOOP_NICE and "nice" not in refused) or f"nice {LOOP_NICE}: " in refused, out.stdout


@pytest.mark.parametrize(("value", "loop", "refused"), [
    ("", {3}, ""), ("1", {1}, ""), ("1-2", {1, 2}, ""), ("0,3", {0, 3}, ""),
    ("0-3", {3}, "leaves no CPU"), ("7", {3}, "leaves no CPU"), ("x", {3}, "is no CPU list"),
    ("-1", {3}, "is no CPU list"), ("3-1", {3}, "is no CPU list"),
    ("0-100000000000", {3}, "is no CPU list")])  # a typo's range is not enumerated (it was, for minutes)
def test_xneck_loop_cpus_names_the_loops_cpus_or_is_refused_for_the_last_one(monkeypatch, value, loop, refused):
    monkeypatch.setenv(cp.ENV_LOOP_CPUS, value)
    assert cp.cpu_split({0, 1, 2, 3}) == (loop, {0, 1, 2, 3} - loop)
    why = cp.loop_cpus_refusal({0, 1, 2, 3})
    assert (refused in why and why) if refused else why == "", why


def test_a_loop_process_goes_to_the_cpu_xneck_loop_cpus_names(child, monkeypatch):
    cpus = cp.machine_cpus()
    if len(cpus) < 2:
        pytest.skip("one CPU: shared by all")
    monkeypatch.setenv(cp.ENV_LOOP_CPUS, str(min(cpus)))
    got = cp.isolate(child.pid, "controller", realtime=False)
    assert got["cpus"] == [min(cpus)] or any("affinity" in r for r in got["refused"]), got
