"""A console that stops answering under ``xneck up`` must not disturb the control path.

Found 2026-11-27 (docs/safety.md, "Peers that stop reading"): with the console (the hub) stopped
(SIGSTOP: a hung process, a suspended machine) past Zenoh's lease, the bridge and the controller,
which connected to the hub, retried it every 11-14 s; each attempt's socket, accepted by the
stopped hub's kernel but never answered, is closed after Zenoh's 10 s open timeout, and that close
(SO_LINGER, hard-coded in Zenoh) blocks the thread that polls every socket of the process for about
40 ms (``strace -T``: ``close`` 42 ms on ``net-0``, in both processes at once). So the commands
stopped for 40 ms and the bridge held, once per attempt (3-4 holds in 45 s). The control path now
connects to the bridge, and the console connects to it and the controller: neither reconnects to
a console.

Real processes, real Zenoh on 127.0.0.1; every process is stopped within bounded time.
"""

from __future__ import annotations

import os
import re
import signal
import time
from datetime import datetime
from pathlib import Path

import httpx
import pytest
from server_harness import wait_until
from test_up_child_death import _child, _xneck_up

# No hold for 34 s is a deadline (10 ms): alone on the machine (tests/conftest.py, _cpu_turn).
pytestmark = [pytest.mark.e2e, pytest.mark.realtime]

# The first reconnect attempt closed ~19 s after the stop (lease 10 s, open timeout 10 s), the
# next ones 11-14 s apart: 34 s covers two.
STOP_S = 34.0
LEASE_S = 10.0  # Zenoh's transport lease: the stopped console's links close after it
LOG_TIME = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")


def _holds_between(log: Path, since: float, until: float = float("inf")) -> list[str]:
    """The bridge's hold lines logged in the wall-clock interval [``since``, ``until``)."""
    lines = []
    for line in log.read_text(errors="replace").splitlines():
        m = LOG_TIME.match(line)
        if m and " hold: " in line and since <= datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp() < until:
            lines.append(line)
    return lines


def _bridge_state_age_s(url: str) -> float:
    """How old the console's latest bridge state is (s); inf when it has none or does not answer."""
    try:
        age = httpx.get(url + "/api/system/health", timeout=5).json()["bridge"]["state_age_s"]
    except (httpx.HTTPError, ValueError, KeyError, TypeError):
        return float("inf")
    return float("inf") if age is None else float(age)


def test_a_console_stopped_past_zenohs_timeouts_does_not_make_the_bridge_hold(tmp_path: Path) -> None:
    with _xneck_up(tmp_path) as (url, data, up):
        bridge_log = data / "logs" / "bridge.log"
        assert wait_until(lambda: bridge_log.exists() and "bumpless ramp done" in bridge_log.read_text(), 120, 0.3), \
            (tmp_path / "up.log").read_text()
        time.sleep(2.0)  # past the start-up: any hold from here on is the stop's
        server = _child(up.pid, "server")
        assert server is not None
        stopped_at = time.time()
        os.kill(server, signal.SIGSTOP)
        try:
            time.sleep(STOP_S)
        finally:
            os.kill(server, signal.SIGCONT)
            resumed_at = time.time()
        # Counted from the lease's end (10 s), when the links to the stopped console close and the
        # reconnect retries this test is about begin (the first at ~19 s). A hold or two at the stop's
        # very start (two of 11 ms, 0.1-0.6 s in, in one CI run of ef29ae4) is another effect, open:
        # docs/safety.md, "Peers that stop reading". Counted until the console resumes: its links
        # coming back are a peer joining (benchmarks/peer_churn.py), not this test's subject; one CI
        # run (499017b) had holds at and after the SIGCONT, printed here when the test fails.
        holds = _holds_between(bridge_log, stopped_at + LEASE_S, resumed_at)
        early = _holds_between(bridge_log, stopped_at, stopped_at + LEASE_S)
        assert up.poll() is None, (tmp_path / "up.log").read_text()
        # The console comes back and sees the bridge's states again (its links were closed meanwhile).
        assert wait_until(lambda: _bridge_state_age_s(url) < 0.5, 60, 0.5)
        # The hub layout held at every retry, two or more in 34 s in every run seen (3 here before the
        # change); one hold is allowed, for a scheduling hiccup of this shared 2-CPU machine (CI of
        # 622a523: one hold, 11 ms, 30 s into the stop, no retry in the strace of a rerun).
        late = _holds_between(bridge_log, resumed_at)
        assert len(holds) <= 1, "\n".join(holds + ["(before the lease's end:)", *early, "(after the resume:)", *late])

