"""What running a campaign's identification in a child process (``server.analysis_process``) buys
the console: its other threads keep answering, and its memory comes back.

Writes an identification campaign's archive (the twin's §5.2.2 campaign,
``controller.identification_loop.simulate_campaign``, 97 s, motor states and camera frames) unless
a file is given, then runs the console's analysis of it (``server.results.analyse_archive``) twice
in this process: in a thread, as the console did until 2026-11-30 (the baseline), and through
``run_in_child``. Meanwhile a thread sleeps 10 ms at a time, as the console's health route waits
for its turn; printed: median, p99 and worst of how late it woke, their ratio child / thread, and
this process's resident memory (VmRSS) before and after each (the thread's run first, so that the
child's is not flattered by memory the thread's left).
Run: ``.venv/bin/python benchmarks/analysis_isolation.py [FILE.mcap]``.
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import numpy as np

from bridge import bus
from bridge.archive import write_campaign
from controller.identification_loop import simulate_campaign
from controller.trajectory import identification_trajectory
from server.analysis_process import run_in_child
from server.results import analyse_archive

SLEEP_S = 0.01


def campaign(path: Path) -> Path:
    """The twin's identification campaign as an archive (the messages ``xneck identify`` reads)."""
    data = simulate_campaign(0)[0]
    msgs = [(bus.MOTOR_STATE, int(t * 1e9), bus.MotorState(seq=k, stamp_s=float(t), theta_rad=list(th),
                                                          force_applied_N=list(f), drive="active", epoch="e",
                                                          bridge="b"))
            for k, (t, th, f) in enumerate(zip(data.t_s, data.theta_rad, data.force_N, strict=True))]
    msgs += [(bus.CAMERA_ALPHA, int(t * 1e9) + 1, bus.CameraAlpha(seq=k, stamp_s=float(t), alpha_ip_rad=list(a),
                                                                 capture_stamp_s=float(t)))
             for k, (t, a) in enumerate(zip(data.t_ip_s, data.alpha_ip_rad, strict=True))]
    msgs.sort(key=lambda m: m[1])
    return write_campaign(path, msgs, {"campaign_id": "bench", "kind": "identification",
                                       "trajectory": identification_trajectory().to_json()})


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def lateness(work: Callable[[], object]) -> tuple[np.ndarray, float]:
    """How late (s) a 10 ms sleeper woke while ``work`` ran, and how long ``work`` took (s)."""
    late: list[float] = []
    done = threading.Event()

    def sleeper() -> None:
        while not done.is_set():
            t = time.perf_counter()
            time.sleep(SLEEP_S)
            late.append(time.perf_counter() - t - SLEEP_S)

    thread = threading.Thread(target=sleeper)
    thread.start()
    t0 = time.perf_counter()
    try:
        work()
    finally:
        took = time.perf_counter() - t0
        done.set()
        thread.join()
    return np.array(late), took


def in_thread(path: Path) -> None:
    out: list[object] = []
    worker = threading.Thread(target=lambda: out.append(analyse_archive(path, None)))
    worker.start()
    worker.join()
    if not out or out[0][0] is None:  # type: ignore[index]
        raise SystemExit(f"the analysis failed: {out}")


def in_child(path: Path) -> None:
    report, text, _ = run_in_child(analyse_archive, path, None, what="identification")
    if report is None:
        raise SystemExit(f"the analysis failed: {text}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("file", nargs="?", type=Path, help="an identification campaign's MCAP file")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.file or campaign(Path(tmp) / "bench.mcap")
        print(f"{path.name}: {path.stat().st_size / 1e6:.1f} MB")
        rows = {}
        for label, run in (("analysis in a thread (baseline)", in_thread), ("analysis in a child process", in_child)):
            before = rss_mb()
            late, took = lateness(lambda run=run: run(path))
            after = rss_mb()
            med, p99, worst = (float(np.percentile(late, q)) * 1e3 for q in (50, 99, 100))
            rows[label] = (med, p99, worst)
            print(f"{label:<34s} {took:6.1f} s; the sleeper late: median {med:7.2f} ms  p99 {p99:7.2f} ms  "
                  f"worst {worst:7.2f} ms; this process {before:6.0f} -> {after:6.0f} MB")
        (m0, p0, w0), (m1, p1, w1) = rows.values()
        print(f"ratio child / thread: median {m1 / m0:.2f}, p99 {p1 / p0:.2f}, worst {w1 / w0:.2f}")


if __name__ == "__main__":
    main()
