"""The test suite's fork server (tests/xneck_forkserver.py) against new interpreters: what a
forked ``xneck`` process saves the suite (README, "The whole suite").

Times, alternately in this one process so that both see the same machine: a short command run to
completion (``xneck kinematics ik``, what the ``xneck`` fixture runs by the hundred) and a twin
bridge that starts, runs 250 ticks (0.5 s at 500 Hz) and exits (what test_stack's ``_procs`` and
the in-process campaigns start), each forked from the server and started as ``python -m
server.cli``. Prints median and p99 wall time of each and the ratio exec/fork, plus the fork
server's own start-up (paid once per pytest worker). Run:
``.venv/bin/python benchmarks/suite_forkserver.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the suite's processes run (tests/conftest.py)
HERE = Path(__file__).resolve().parent
import _repo  # noqa: E402  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing  # noqa: E402  (benchmarks/ is sys.path[0] when run as a script)
import numpy as np  # noqa: E402

sys.path.insert(1, str(_repo.ROOT / "tests"))
import forkserver_client  # noqa: E402  # pyright: ignore[reportMissingImports]  (tests/, put on the path above)

COMMANDS = {
    "kinematics ik (to completion)": ["kinematics", "ik", "--L", "1", "--b", "0.5", "--x", "0", "--y", "1", "--json"],
    "twin bridge, 250 ticks": ["bridge", "--driver", "twin", "--max-ticks", "250", "--listen", "tcp/127.0.0.1:0"],
}


def _exec(args: list[str], log: Path) -> float:
    t0 = time.perf_counter()
    with open(log, "wb") as out:
        code = subprocess.run([*forkserver_client.XNECK, *args], stdout=out, stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL, timeout=120).returncode
    assert code == 0, log.read_text()[-2000:]
    return time.perf_counter() - t0


def _fork(server: forkserver_client.ForkServer, args: list[str], log: Path) -> float:
    t0 = time.perf_counter()
    proc = server.spawn(args, log, dict(os.environ), start_new_session=False)
    assert proc is not None, "the fork server refused"
    code = proc.wait(120)
    assert code == 0, log.read_text()[-2000:]
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7, help="runs of each command each way (default 7)")
    repeats = parser.parse_args().repeats
    with tempfile.TemporaryDirectory(prefix="xneck-forkbench-") as tmp:
        server = forkserver_client.ForkServer(Path(tmp) / "socket")
        t0 = time.perf_counter()
        assert server._start(), "the fork server did not start"
        print(f"fork server start-up (imports, numba kernels; once per worker): {time.perf_counter() - t0:.2f} s")
        log = Path(tmp) / "run.log"
        try:
            for label, args in COMMANDS.items():
                forked, execd = np.empty(repeats), np.empty(repeats)
                for k in range(repeats):  # alternately: the same machine for both
                    forked[k] = _fork(server, args, log)
                    execd[k] = _exec(args, log)
                med_f, _ = _timing.summary(f"{label}: forked", forked, unit=1e-3, unit_name="ms")
                med_e, _ = _timing.summary(f"{label}: new interpreter", execd, unit=1e-3, unit_name="ms")
                print(f"{label}: new interpreter / forked = {med_e / med_f:.2f}x (medians)")
        finally:
            server.stop()


if __name__ == "__main__":
    main()
