"""The bridge's loop watchdog (docs/bridge.md, "The loop watchdog"): what it costs per tick, and
how soon a hung loop has every drive off.

1. Per-tick cost: the real-time loop's bookkeeping (``bridge.node.run_realtime``: clock read,
   due time, the watchdog's two stores) with and without the stores, 10^6 iterations, best of 7.
2. Hang → drives off: a real ``xneck bridge --driver beaglebone`` on the fake board
   (tests/fake_rcpy: rcpy cannot exist here; it logs every enable level across processes), this
   script as its controller on a loopback bus; once the drives are enabled the loop is hung in an
   encoder read (``FAKE_RCPY_BLOCK``: ``sleep`` = a call that releases the GIL, ``spin`` = an
   endless Python loop, ``convoy`` = short GIL-releasing calls in a loop) and the time from the
   hang to every enable line off, set by the bridge's own process, is measured, and the trip's
   own part as the bridge logs it (``drives disabled in … ms``); ``slow`` (a tick every 0.48 s)
   is the rare-tick rule's case.

Run: ``.venv/bin/python benchmarks/loop_watchdog.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # the fake board's log reader (tests/fake_board_log.py)

import _repo  # noqa: E402, F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
from fake_board_log import board_log, levels  # noqa: E402  # pyright: ignore[reportMissingImports]  (tests/ on sys.path above)

from bridge import bus  # noqa: E402
from bridge.drivers.beaglebone import BLUE_GP0_PINS  # noqa: E402
from bridge.session import free_tcp_port, liveliness_token, open_session, publisher  # noqa: E402


def per_tick_ns(iterations: int = 1_000_000, best_of: int = 7) -> tuple[float, float]:
    """ns per iteration of the loop's bookkeeping without and with the watchdog's two stores."""

    class _Watchdog:
        __slots__ = ("last_tick_s", "ticks")

    def bare() -> float:
        clock, start, dt, k = time.perf_counter, time.perf_counter(), 0.002, 0
        t0 = clock()
        for k in range(iterations):
            now = clock()
            due = start + k * dt
            if now > due:
                pass
        return (clock() - t0) / iterations

    def watched() -> float:
        wd = _Watchdog()
        clock, start, dt, k = time.perf_counter, time.perf_counter(), 0.002, 0
        t0 = clock()
        for k in range(iterations):
            now = clock()
            wd.last_tick_s = now
            wd.ticks = k
            due = start + k * dt
            if now > due:
                pass
        return (clock() - t0) / iterations

    return min(bare() for _ in range(best_of)) * 1e9, min(watched() for _ in range(best_of)) * 1e9


def hang_to_off_s(mode: str, workdir: Path) -> tuple[float, str]:
    """Seconds from the loop's hang to every enable line off (by the bridge itself), and its log line."""
    board, block, log = workdir / f"{mode}.rcpy.log", workdir / f"{mode}.block", workdir / f"{mode}.bridge.log"
    for f in (board, block):
        with contextlib.suppress(FileNotFoundError):
            f.unlink()
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "FAKE_RCPY_LOG": str(board), "FAKE_RCPY_BLOCK": str(block),
           "PYTHONPATH": os.pathsep.join([str(ROOT / "tests" / "fake_rcpy"), os.environ.get("PYTHONPATH", "")])}
    states: list[bus.MotorState] = []
    with open_session(listen=[hub], connect=[]) as session:
        sub = session.declare_subscriber(
            bus.MOTOR_STATE, lambda s: states.append(bus.decode(bus.MotorState, s.payload.to_bytes())))
        token = liveliness_token(session, "controller", "wd-bench")
        pub = publisher(session, bus.MOTOR_COMMAND)
        with open(log, "wb") as out:
            proc = subprocess.Popen([sys.executable, "-m", "server.cli", "bridge", "--driver", "beaglebone", "--listen",
                                     "tcp/127.0.0.1:0", "--connect", hub], stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, env=env)
        try:
            deadline = time.monotonic() + 60
            while not states and time.monotonic() < deadline:
                time.sleep(0.01)
            k = 0
            while not any(s.drive == "active" for s in states[-5:]):
                k += 1
                pub.put(bus.ForceCommand(seq=k, stamp_s=states[-1].stamp_s, force_N=[20.0] * 4, source="bench",
                                         sender="wd-bench", epoch=states[-1].epoch))  # answers the newest state
                time.sleep(0.002)
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise RuntimeError(f"the bridge did not enable its drives: {log.read_text()[-2000:]}")
            time.sleep(0.5)  # commands stop: the bridge holds, drives still enabled
            block.write_text(mode)
            hung = off = None
            n_seen = 0
            while off is None and time.monotonic() < deadline + 30:
                lines = board_log(board)
                if hung is None and any(w == "hang" for _, w, _, _ in lines[n_seen:]):
                    hung, n_seen = time.perf_counter(), len(lines)
                if hung is not None and levels(lines[n_seen:], {proc.pid}) == dict.fromkeys(BLUE_GP0_PINS, 0):
                    off = time.perf_counter()
                time.sleep(0.001)
            proc.wait(10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
            with contextlib.suppress(FileNotFoundError):
                block.unlink()
            sub.undeclare()
            pub.close()
            token.undeclare()
    said = next((line for line in log.read_text().splitlines() if "loop watchdog:" in line), "")
    if hung is None or off is None:
        raise RuntimeError(f"{mode}: no hang or no drives off seen; {said}")
    return off - hung, said


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="bridges hung per mode")
    a = ap.parse_args()
    bare, watched = per_tick_ns()
    print(f"per tick: bookkeeping {bare:.1f} ns bare, {watched:.1f} ns with the watchdog's stores: "
          f"+{watched - bare:.1f} ns ({watched / bare:.2f}x)")
    print(f"hang → every enable line off, by the bridge's own process (load average {os.getloadavg()[0]:.1f} "
          f"on {os.cpu_count()} CPUs; limit 0.5 s, looks every 50 ms):")
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("sleep", "spin", "convoy", "slow"):
            times, trips, said = [], [], ""
            for _ in range(a.repeats):
                t, said = hang_to_off_s(mode, Path(tmp))
                times.append(t)
                trips.append(float(said.split("drives disabled in ")[1].split(" ms")[0]))
            print(f"  {mode:7s} median {statistics.median(times) * 1e3:6.0f} ms   max {max(times) * 1e3:6.0f} ms   "
                  f"of which the trip (the bridge's figure) median {statistics.median(trips):6.2f} ms   max "
                  f"{max(trips):6.2f} ms   ({len(times)} bridges; the bridge said: "
                  f"{said.split('loop watchdog: ')[-1][:70]}…)")


if __name__ == "__main__":
    main()
