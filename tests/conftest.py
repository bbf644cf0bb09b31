from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from bridge.session import free_tcp_port, open_session
from twin.model.numeric import build
from twin.model.params import load_params

XNECK = [sys.executable, "-m", "server.cli"]  # `xneck` with this interpreter, whatever PATH says


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (pyproject's addopts): the whole suite, or a folder of it, runs on two workers, one
    module per unit (``--dist loadfile``: a module's fixtures, a stack, a console, recorded campaigns,
    are set up once); named files or tests run in this one process, as a developer checking one thing
    on a shared machine wants. More than two workers would only add load beside the real-time tests."""
    whole = all(Path(str(arg).split("::")[0]).is_dir() for arg in config.args)
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 2 if whole and cpus >= 2 else 0


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
