from __future__ import annotations

import fcntl
import os
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from bridge.session import free_tcp_port, open_session
from twin.model.numeric import build
from twin.model.params import load_params

XNECK = [sys.executable, "-m", "server.cli"]  # `xneck` with this interpreter, whatever PATH says

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
    """The ``background`` modules first (they start beside the first realtime one and use the CPU it
    leaves), then the ``realtime`` modules, in file order, then the rest in file order (a stable sort).
    Each realtime module waits for the other worker's running module to end before it starts
    (``_cpu_turn``); scattered through the suite, the seven of them waited 204 s in all on
    2026-11-26 (pytest --durations' setup times) with one CPU idle. Together, they wait for each
    other only, which they would anyway."""
    items.sort(key=lambda item: (item.get_closest_marker("background") is None,
                                 item.get_closest_marker("realtime") is None))


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
    if request.node.get_closest_marker("background") is not None:
        # Its heavy work runs at nice 19 (tests/test_architecture.py): beside a realtime module it
        # gets only the CPU that module leaves idle, so it takes no turn and waits for none.
        asked, started = time.monotonic(), time.time()
        yield
        _timeline(request, False, asked, started)
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
        started = time.time()
        try:
            yield
        finally:
            fcntl.flock(turn, fcntl.LOCK_UN)
            _timeline(request, exclusive, deadline - TURN_TIMEOUT_S, started)


def _timeline(request: pytest.FixtureRequest, exclusive: bool, asked_monotonic: float, started: float) -> None:
    """With ``XNECK_TEST_TIMELINE=FILE``, one line per module appended to FILE: worker, realtime or
    not, seconds waited for its turn, wall-clock start and end (s since the epoch), module. The suite's
    critical path, read with ``sort -k4 -n FILE``, is what to cut when CI's time grows."""
    path = os.environ.get("XNECK_TEST_TIMELINE")
    if not path:
        return
    waited = time.monotonic() - asked_monotonic - (time.time() - started)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    with open(path, "a") as f:
        f.write(f"{worker} {'rt' if exclusive else '--'} {waited:7.1f} {started:.1f} {time.time():.1f} "
                f"{request.node.nodeid}\n")


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
    to this process's environment)."""

    def run(*args: str, timeout: float = 180, cwd: Path | None = None,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
        return subprocess.run([*XNECK, *args], capture_output=True, text=True, timeout=timeout, cwd=cwd,
                              env={**os.environ, **(env or {})})

    return run
