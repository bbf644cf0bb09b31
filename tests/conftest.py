from __future__ import annotations

import os

# One BLAS thread per process, set before numpy loads (here, and in every process a test starts):
# two workers on two CPUs already fill the machine, and OpenBLAS's second thread spins while it
# waits. test_identification_loadfriction alone took 36.7 s of CPU with two threads, 30.3 s with
# one; the whole suite's modules 1448 s with two, 1373 s with one (tests/conftest.py's timeline).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import contextlib
import fcntl
import functools
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import forkserver_client
import numpy as np
import pytest
import zenoh

from bridge.session import ENV_ZENOH_RUNTIME, free_tcp_port, open_session, zenoh_runtime_environment
from twin.model.numeric import build
from twin.model.params import load_params

# xneck reads its settings from XNECK_* variables (server/settings.py, bridge/session.py): a lab
# shell's XNECK_CONNECT, XNECK_ZENOH_CONNECT or XNECK_MODE=robot would point the suite's consoles,
# controllers and campaigns at that lab's bridge, and XNECK_ZENOH_LISTEN or XNECK_HOST open them
# to its network (audit of session 48). The suite runs on its own settings: every XNECK_* variable
# but its own switches (XNECK_TEST_*, XNECK_NO_NUMBA, XNECK_REALTIME) is dropped here, before any
# test reads it (no module reads them on import), for this process and those it starts; the
# header names them.
KEPT_XNECK_VARIABLES = ("XNECK_TEST_", "XNECK_NO_NUMBA", "XNECK_REALTIME")  # the suite's switches (README)
IGNORED_XNECK_VARIABLES = sorted(k for k in os.environ  # the settings read them in any case (pydantic)
                                 if k.upper().startswith("XNECK_") and not k.upper().startswith(KEPT_XNECK_VARIABLES))
for _name in IGNORED_XNECK_VARIABLES:
    del os.environ[_name]
# Likewise Zenoh's runtime, which xneck sets unless the shell did (bridge.session, imported above):
# a lab's ZENOH_RUNTIME decided whether tests/test_bus_dead_peers.py passed (review of session 48).
if os.environ.get(ENV_ZENOH_RUNTIME) != (_XNECK_RUNTIME := zenoh_runtime_environment({})):
    IGNORED_XNECK_VARIABLES.append(ENV_ZENOH_RUNTIME)
    os.environ[ENV_ZENOH_RUNTIME] = _XNECK_RUNTIME

XNECK = forkserver_client.XNECK  # `xneck` with this interpreter, whatever PATH says (what a forked run stands for)

# The suite starts some hundreds of Python processes (stacks, campaigns, CLI runs); with
# PYTHONDONTWRITEBYTECODE set (this machine's default environment does) each one compiled the
# project's modules again, about 0.2 s of CPU apiece. Their bytecode is cached like any checkout's.
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
sys.dont_write_bytecode = False


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (pyproject's addopts): the whole suite, or a folder of it, runs on two workers, one
    module per unit (``--dist loadfile``: a module's fixtures, a stack, a console, recorded campaigns,
    are set up once); named files or tests run in this one process, as a developer checking one thing
    on a shared machine wants. More than two workers would only add load beside the real-time tests."""
    whole = all(Path(str(arg).split("::")[0]).is_dir() for arg in config.args)
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 2 if whole and cpus >= 2 else 0


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Module order, which is xdist's dispatch order: the first ``background`` module, then the
    ``realtime`` modules (one unit of work, :func:`pytest_xdist_make_scheduler`), then the other
    background modules, then the rest, each group in file order (a stable sort). So one worker runs
    the realtime chain while the other runs the background modules beside it, at nice 19 in the
    CPU the chain leaves idle (about one of two), then both share the rest. Scattered through the
    suite, the realtime modules waited 204 s in all for their turns (2026-11-26) with one CPU idle."""
    renice = _may_renice()  # else a background module is an ordinary one (``_cpu_turn``)
    background = sorted({str(item.path) for item in items if item.get_closest_marker("background") is not None})

    def rank(item: pytest.Item) -> int:
        if renice and item.get_closest_marker("background") is not None:
            return 0 if str(item.path) == background[0] else 2
        return 1 if item.get_closest_marker("realtime") is not None else 3

    items.sort(key=rank)


REALTIME_UNIT = "realtime modules"
_REALTIME_MARK = re.compile(r"^pytestmark\s*=.*\bmark\.realtime\b", re.MULTILINE)


@functools.cache
def _is_realtime_file(path: Path) -> bool:
    """Whether the test module at ``path`` is marked ``realtime`` (its ``pytestmark`` line): xdist's
    controller does not collect, so it cannot see the marker itself."""
    try:
        return bool(_REALTIME_MARK.search(path.read_text(errors="replace")))
    except OSError:
        return False


def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadfile`` with every ``realtime`` module in one unit of work: they run one after
    the other on one worker (they take turns anyway), so the other worker is free for the
    background modules beside them instead of waiting for its next realtime module's turn."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class RealtimeTogether(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            scope = super()._split_scope(nodeid)
            return REALTIME_UNIT if _is_realtime_file(config.rootpath / scope) else scope

    return RealtimeTogether(config, log)


#: How long a module waits for its turn on the CPUs before it runs anyway (a stuck peer worker
#: must not hang CI): longer than any one module takes.
TURN_TIMEOUT_S = 600.0


def _flock(f, mode: int, deadline: float) -> bool:
    """``fcntl.flock`` polled until ``deadline`` (monotonic s); False if it timed out."""
    while True:
        try:
            fcntl.flock(f, mode | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.05)


@pytest.fixture(autouse=True)
def _own_state_home(monkeypatch: pytest.MonkeyPatch, tmp_path_factory: pytest.TempPathFactory) -> None:
    """Each test's processes keep their state (the board bridge's e-stop latch file,
    ``bridge.estop_latch``) in a folder of its own, not in the user's ``~/.local/state``: a robot
    bridge that a test stopped under an engaged e-stop had left its latch there, and every later
    robot bridge of the suite (and of the user) started latched (session 53)."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path_factory.mktemp("xdg-state")))


@pytest.fixture(scope="module", autouse=True)
def _cpu_turn(request: pytest.FixtureRequest) -> Iterator[None]:
    """A module marked ``realtime`` (its assertions are about deadlines, ticks and lost messages)
    runs with no other module beside it, of this suite or of another one running on the machine
    at the same time (issue 21: the suite stays green with a second copy beside it); other modules
    share the machine. A readers-writer lock on files in ``XNECK_TEST_TURNS_DIR`` (default: a
    directory under the system's temporary directory), writer first: a realtime module takes the
    gate, waits until the running modules end, and every other worker's next module waits for it.
    On a 2-CPU machine a second worker's stacks and campaigns were what made those tests miss
    (CI: a hold 1 ms late, 27 states lost on the bus); the rest still runs two at a time."""
    exclusive = request.node.get_closest_marker("realtime") is not None
    if request.node.get_closest_marker("background") is not None and _may_renice():
        # The whole worker at nice 19 (every thread, so its subprocesses too): beside a realtime
        # module it gets only the CPU that module leaves idle, so it takes no turn and waits for none.
        asked, started, cpu = time.monotonic(), time.time(), _cpu_s()
        saved = _renice_worker(BACKGROUND_NICE)
        group = _own_autogroup()
        _set_group_nice(group, BACKGROUND_NICE)
        try:
            yield
        finally:
            _set_group_nice(group, 0)
            _restore_nice(saved)
            _timeline(request, False, asked, started, cpu)
        return
    root = Path(os.environ.get("XNECK_TEST_TURNS_DIR") or Path(tempfile.gettempdir()) / "xneck-test-turns")
    root.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + TURN_TIMEOUT_S
    with open(root / "cpu-gate.lock", "a+") as gate, open(root / "cpu-turn.lock", "a+") as turn:
        got = _flock(gate, fcntl.LOCK_EX, deadline)
        try:
            got = _flock(turn, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH, deadline) and got
        finally:
            fcntl.flock(gate, fcntl.LOCK_UN)
        if not got:
            warnings.warn(f"{request.node.name}: no turn on the CPUs after {TURN_TIMEOUT_S:.0f} s, running anyway",
                          stacklevel=1)
        started, cpu = time.time(), _cpu_s()
        try:
            yield
        finally:
            fcntl.flock(turn, fcntl.LOCK_UN)
            _timeline(request, exclusive, deadline - TURN_TIMEOUT_S, started, cpu)


BACKGROUND_NICE = 19


def _may_renice() -> bool:
    """Whether this worker may take its nice back down after a background module (root, or an
    RLIMIT_NICE that allows it); else background modules are ordinary ones, in order and turns:
    slower, but a realtime module still runs alone. ``XNECK_TEST_RENICE=0`` asks for that anywhere
    (and is how tests/test_suite_turns.py checks it as root)."""
    if os.environ.get("XNECK_TEST_RENICE", "1") == "0":
        return False
    if os.geteuid() == 0:
        return True
    soft, _hard = resource.getrlimit(resource.RLIMIT_NICE)
    return soft == resource.RLIM_INFINITY or 20 - soft <= os.getpriority(os.PRIO_PROCESS, 0)


AUTOGROUP = Path("/proc/self/autogroup")


def _own_autogroup() -> Path | None:
    """This worker in a session of its own, so in a scheduler autogroup of its own; the file that
    sets that group's nice, or None where the kernel has none.

    Linux with ``sched_autogroup_enabled`` (this VM, most desktops) shares the CPUs between
    sessions first and applies a thread's nice only inside its session: a stack started with
    ``start_new_session`` (every ``xneck up`` of the realtime modules) got as much CPU as the whole
    pytest session, background modules at nice 19 included (two loops at nice 19 took 35 % of the
    CPU beside two in a new session, 2026-11-28; realtime modules missed deadlines beside pyright).
    A session is for good: the worker stays a leader of its own session afterwards."""
    if not AUTOGROUP.exists():
        return None
    if os.getsid(0) != os.getpid():
        try:
            os.setsid()
        except OSError:  # a process group leader cannot: thread nices only
            return None
    return AUTOGROUP


def _set_group_nice(group: Path | None, nice: int) -> None:
    """The autogroup's nice (any user may raise it; lowering it back to 0 needs no privilege either,
    only to go below 0); nothing where there is no autogroup."""
    if group is None:
        return
    for _ in range(3):
        try:
            group.write_text(f"{nice}\n")
            return
        except BlockingIOError:  # without CAP_SYS_ADMIN, one change per 100 ms
            time.sleep(0.11)
        except OSError:
            return


def _threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [threading.get_native_id()]


def _renice_worker(nice: int) -> dict[int, int]:
    """Every thread of this process at ``nice`` (Linux nices threads, not processes); returns the
    nice each had, for :func:`_restore_nice`."""
    saved = {}
    for tid in _threads():
        with contextlib.suppress(OSError):
            saved[tid] = os.getpriority(os.PRIO_PROCESS, tid)
            os.setpriority(os.PRIO_PROCESS, tid, nice)
    return saved


def _restore_nice(saved: dict[int, int]) -> None:
    """Threads back to their nice before :func:`_renice_worker`; those started meanwhile (which
    inherited the background nice) to the main thread's."""
    base = saved.get(os.getpid(), 0)
    for tid in _threads():
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, saved.get(tid, base))


def _cpu_s() -> tuple[float, float]:
    """CPU seconds (user and system): of this worker and of the children it has waited for; of
    this worker alone (its tests' own work: in-process consoles, recorders, analyses)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    mine = own.ru_utime + own.ru_stime
    return mine + children.ru_utime + children.ru_stime, mine


def _timeline(request: pytest.FixtureRequest, exclusive: bool, asked_monotonic: float, started: float,
              cpu_s: tuple[float, float]) -> None:
    """With ``XNECK_TEST_TIMELINE=FILE``, one line per module appended to FILE: worker, realtime or
    not, seconds waited for its turn, wall-clock start and end (s since the epoch), CPU seconds
    (the worker's and its waited-for children's: a process a test leaves unwaited is not counted),
    CPU seconds of the worker alone, module. The suite's critical path, read with ``sort -k4 -n
    FILE``, and its CPU, ``sort -k6 -n`` (``-k7``: the tests' in-process work), are what to cut when
    CI's time grows: two workers on two CPUs make the suite CPU-bound."""
    path = os.environ.get("XNECK_TEST_TIMELINE")
    if not path:
        return
    waited = time.monotonic() - asked_monotonic - (time.time() - started)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    with open(path, "a") as f:
        total, own = _cpu_s()
        f.write(f"{worker} {'rt' if exclusive else '--'} {waited:7.1f} {started:.1f} {time.time():.1f} "
                f"{total - cpu_s[0]:7.1f} {own - cpu_s[1]:7.1f} {request.node.nodeid}\n")


@pytest.fixture(scope="module")
def dask_client():
    """A local Dask cluster of two worker processes for a module's studies (server/studies)."""
    from distributed import Client

    from server.studies.execute import loopback_cluster

    cluster = loopback_cluster(2)
    try:
        c = Client(cluster)
    except BaseException:
        cluster.close()
        raise
    try:
        yield c
    finally:
        c.close()
        cluster.close()


@pytest.fixture(scope="session")
def params():
    return load_params()


@pytest.fixture(scope="session")
def model(params):
    return build(params)


@pytest.fixture
def rng():
    return np.random.default_rng(20261123)


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """Two real Zenoh peers: ``a`` listens on a free loopback port, ``b`` connects to it."""
    port = free_tcp_port()
    with (open_session(listen=[f"tcp/127.0.0.1:{port}"], connect=[]) as a,
          open_session(listen=["tcp/127.0.0.1:0"], connect=[f"tcp/127.0.0.1:{port}"]) as b):
        yield a, b


XneckRunner = Callable[..., subprocess.CompletedProcess]


@pytest.fixture(scope="session")
def xneck() -> XneckRunner:
    """Runs ``xneck <args>`` (``python -m server.cli``) to completion and returns the finished
    process (text stdout/stderr). Keywords: ``timeout`` (s, default 180), ``cwd``, ``env`` (added
    to this process's environment).

    Runs are forked from tests/xneck_forkserver.py, which has imported the command line's modules
    once (a ``python -m server.cli`` start-up is 0.4-1 s of CPU, and the suite runs some hundreds;
    test_cli_usage took 70 s instead of 258 s); a run with ``env``, or ``XNECK_TEST_FORKSERVER=0``,
    is a process of its own, as is every run if the fork server cannot start.
    (``XNECK_TEST_TIMELINE`` counts the forked runs' CPU when the worker ends, not in their module.)"""

    def run(*args: str, timeout: float = 180, cwd: Path | None = None,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
        if env is None and (done := forkserver_client.shared().run(list(args), timeout, cwd)) is not None:
            return done
        return subprocess.run([*XNECK, *args], capture_output=True, text=True, timeout=timeout, cwd=cwd,
                              env={**os.environ, **(env or {})})

    return run


@pytest.fixture(autouse=True, scope="session")
def _forked_campaign_children() -> Iterator[None]:
    """The campaigns this process runs (``run_campaign``, the in-process consoles) start their twin,
    controller and camera forked from the suite's fork server (tests/forkserver_client.py), not as
    new interpreters: each was 1.5-2 s of CPU of imports and numba kernel loads before its first
    tick. Same command lines, same environment, same logs; ``XNECK_TEST_FORKSERVER=0`` turns it off."""
    import server.campaign_runner
    from server.child_processes import start_xneck

    def start(args: list[str], log: Path, env: dict[str, str], *, append: bool = False,
              start_new_session: bool = False) -> subprocess.Popen:
        forked = forkserver_client.shared().spawn(list(args), log, env, start_new_session=start_new_session,
                                                  append=append)
        return forked or start_xneck(args, log, env, append=append, start_new_session=start_new_session)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(server.campaign_runner, "start_xneck", start)
        yield


@pytest.fixture(autouse=True)
def _board_lock(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Each test its own board lock (bridge/drivers/board_lock.py): the fake boards of tests that
    xdist runs at once are not one board. Subprocesses inherit it with the environment."""
    monkeypatch.setenv("XNECK_BOARD_LOCK", str(tmp_path_factory.mktemp("board") / "board.lock"))


@pytest.fixture
def board(monkeypatch: pytest.MonkeyPatch) -> Any:
    """The BeagleBone's hardware library (rcpy) faked at its lowest layer and installed in
    ``sys.modules`` for the test: tests/test_bridge_driver.py's ``FakeBoard``."""
    from test_bridge_driver import FakeBoard

    b = FakeBoard()
    for name, module in b.modules().items():
        monkeypatch.setitem(sys.modules, name, module)
    return b


def _ignored_line() -> str | None:
    if IGNORED_XNECK_VARIABLES:
        return "xneck: ignored from the environment (the suite runs on its own settings): " + \
            ", ".join(IGNORED_XNECK_VARIABLES)
    return None


def pytest_report_header(config) -> str | None:
    return _ignored_line()


def pytest_terminal_summary(terminalreporter, exitstatus, config) -> None:
    """The ignored variables again at the end: ``-q`` (.ci/run, the README) shows no header."""
    if (line := _ignored_line()) is not None:
        terminalreporter.write_line(line)
