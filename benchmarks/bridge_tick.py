"""Bridge speed and memory without numba, as on the robot's BeagleBone Blue (issue 20).

1. In process, the model as plain Python (numba off, as ``xneck bridge --driver beaglebone|replay``
   runs it): one ``BridgeNode.tick`` (e-stop check, command in, safety rules with clamping and the
   watchdog, driver write/step/read, ``MotorState`` published on a real Zenoh session) with a fresh
   command every tick (one force below f_min, so every tick clamps), then ticks in hold after the
   commands stop (the command's decoding and validation run on Zenoh's thread, not counted).
   Ticks are timed back to back (the tick's own cost), and once more one every 2 ms as the real
   loop runs them: on a machine busy with other work each tick then starts with cold caches.
   Median and p99; target p99 <= 50 µs on x86_64, so a Cortex-A8 (roughly 10-20x
   slower) keeps its 2 ms period. Also the tick that starts a hold (its hold forces are ready:
   the node's worker thread computes them off the tick) and the cost of the hold forces
   themselves (eq. 33 + eqs. 63-65 in plain Python), which that worker pays.
   The process runs as the robot's systemd unit runs the bridge (docs/bridge.md): SCHED_FIFO 50
   where permitted (``--no-realtime``: normal priority) and the bridge loop's GIL switch interval.
   The machine is shared: each timed tick is followed by a fixed reference workload of the same
   kind (small Python lists, a 4-element numpy array, a msgspec encoding), timed the same way,
   and the ratio tick / reference is printed too, a figure that load affects far less.
2. The BeagleBone driver's own part of a tick on the robot (``write`` + ``read``, rcpy faked),
   which the replay driver of 1. does not have.
3. The resident memory of a real ``xneck bridge --driver replay`` process after a few seconds
   on the bus (VmHWM, the peak); target <= 80 MB on x86_64.
4. How often the machine interrupts a busy Python thread for more than 10 µs, and for how long
   (``_timing.interruptions``): a tick of median d loses the CPU in about rate x d of its runs,
   a floor under its p99 that no change to the tick removes (cold caches after other work add more).
Run: ``.venv/bin/python benchmarks/bridge_tick.py [--ticks 5000]``.
``--write-replay PATH`` only writes a replay MCAP file (used by benchmarks/armhf_bridge.sh).
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
import _repo  # noqa: E402, F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing  # noqa: E402  (benchmarks/ is sys.path[0] when run as a script)

from twin.model import compiled  # noqa: E402

compiled.prefer_plain_python()  # before any model import: the robot's path

from bridge import bus  # noqa: E402

TARGET_TICK_P99_US = 50.0
TARGET_RSS_MB = 80.0


def write_replay(path: Path, n: int = 1000) -> Path:
    """A campaign MCAP file of ``n`` recorded states (2 s of a slow nod) for the replay driver."""
    from bridge.archive import write_campaign

    # The identity fields exist from MotorState v2 on.
    identity: dict[str, Any] = {"epoch": "recorded", "bridge": "bridge-bench"} if "epoch" in bus.MotorState.__struct_fields__ else {}
    states = [bus.MotorState(seq=k, stamp_s=0.002 * k, drive="active", force_applied_N=[10.0] * 4,
                             theta_rad=[0.05 * np.sin(k / 80), 0.0, -0.05 * np.sin(k / 80), 0.0], **identity)
              for k in range(n)]
    return write_campaign(path, [(bus.MOTOR_STATE, k * 2_000_000, s) for k, s in enumerate(states)],
                          {"campaign_id": "bench", "kind": "control"})


def _command(node, seq: int, force_N: list[float]) -> bus.ForceCommand:
    # From ForceCommand v2 on, a command names its sender and answers the bridge's epoch.
    extra: dict[str, Any] = {"sender": "bench", "epoch": node.epoch} if "epoch" in bus.ForceCommand.__struct_fields__ else {}
    # It answers the node's newest state (a bridge that checks it refuses others; older ones have none).
    stamp = getattr(node, "last_state_stamp_s", None)
    if stamp is not None and math.isnan(stamp):
        node.publish_state()
        stamp = node.last_state_stamp_s
    return bus.ForceCommand(seq=seq, stamp_s=time.time() if stamp is None else stamp, force_N=force_N,
                            source="benchmark", **extra)


_REF_STATE = {"v": 2, "seq": 1, "stamp_s": 0.0, "theta_rad": [0.1, 0.2, 0.3, 0.4], "drive": "active",
              "force_applied_N": [10.0, 11.0, 12.0, 13.0], "epoch": "e", "bridge": "b"}
_REF_ENCODER = msgspec.json.Encoder()


def reference() -> object:
    """A fixed workload of the kind a tick does, to time beside it on a loaded machine; it uses
    nothing of this project, so a faster bridge does not make it faster too."""
    f = [min(max(x * 1.5, 2.0), 100.0) for x in _REF_STATE["force_applied_N"]]
    a = np.array(f)
    return _REF_ENCODER.encode(_REF_STATE), a.tolist(), sum(f)


def _ratio(label: str, ticks: np.ndarray, refs: np.ndarray) -> tuple[float, float]:
    """Print and return the (median, p99) of the ticks over those of the reference workload."""
    med, p99 = float(np.median(ticks) / np.median(refs)), float(np.percentile(ticks, 99) / np.percentile(refs, 99))
    print(f"{'  over the reference workload (' + label + ')':<58s} median {med:10.2f} x    p99 {p99:10.2f} x")
    return med, p99


def ticks_in_process(replay: Path, n_ticks: int) -> dict[str, float]:
    from bridge.drivers.replay import ReplayConfig, ReplayDriver
    from bridge.node import SWITCH_INTERVAL_S, BridgeConfig
    from bridge.session import free_tcp_port, liveliness_token, open_session, publisher
    from controller.laws import encoder_hold_forces
    from server.cli.processes import bridge_node
    from twin.model.params import load_params

    assert not compiled.numba_enabled() and "numba" not in sys.modules
    params = load_params()
    hub = f"tcp/127.0.0.1:{free_tcp_port()}"
    out: dict[str, float] = {}
    with open_session(listen=[hub], connect=[]) as bridge_session, \
            open_session(listen=["tcp/127.0.0.1:0"], connect=[hub]) as controller_session:
        driver = ReplayDriver(ReplayConfig(path=str(replay), loop=True, n_motors=params.n_cables))
        node = bridge_node(bridge_session, driver, params, BridgeConfig(command_timeout_s=0.010))
        token = liveliness_token(controller_session, "controller", "bench")
        commands = publisher(controller_session, bus.MOTOR_COMMAND)
        time.sleep(0.5)  # peers and liveliness settle
        f_low = max(params.limits.f_min - 0.5, 0.0)  # valid (>= 0) but below f_min: clamped
        active, active_ref = np.empty(n_ticks), np.empty(n_ticks)
        switch = sys.getswitchinterval()
        # The GIL switch interval the bridge's real-time loop runs with (run_realtime): the tick
        # is timed as the robot runs it, Zenoh's callback thread included.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        k = 0
        try:
            while k < n_ticks:
                before = node.commands.latest_with_time()[1]
                commands.put(_command(node, k + 1, [f_low, 12.0, 12.0, 12.0]))
                deadline = time.perf_counter() + 0.05
                while node.commands.latest_with_time()[1] == before and time.perf_counter() < deadline:
                    pass  # spin: a sleep would hand the core to other work and time a cold tick
                t0 = time.perf_counter()
                node.tick()
                t1 = time.perf_counter()
                reference()
                active[k], active_ref[k] = t1 - t0, time.perf_counter() - t1
                k += 1
            sys.setswitchinterval(switch)
            assert node.mode == "active" and node.clamped > 0, (node.mode, node.clamped, node.commands.stats)
            out["active_median_us"], out["active_p99_us"] = _timing.summary(
                "tick, fresh command, clamped, published", active[100:])
            _timing.summary("  reference workload beside it", active_ref[100:])
            out["active_ratio_median"], out["active_ratio_p99"] = _ratio("fresh command", active[100:], active_ref[100:])
            # Past the 10 ms command timeout, with the states a controller would have answered
            # meanwhile (the watchdog's second condition, bridge/safety.py) gone out unanswered.
            unanswered = node.safety.config.command_timeout_states
            time.sleep(0.02)
            for _ in range(unanswered):
                node.tick()
            assert node.mode == "hold", node.mode
            held, held_ref = np.empty(n_ticks), np.empty(n_ticks)
            for k in range(n_ticks):
                t0 = time.perf_counter()
                node.tick()
                t1 = time.perf_counter()
                reference()
                held[k], held_ref[k] = t1 - t0, time.perf_counter() - t1
            out["hold_median_us"], out["hold_p99_us"] = _timing.summary("tick in hold (watchdog, ramp, published)", held)
            _timing.summary("  reference workload beside it", held_ref)
            out["hold_ratio_median"], out["hold_ratio_p99"] = _ratio("hold", held, held_ref)
            paced = np.empty(min(n_ticks, 2000))
            for k in range(len(paced)):
                time.sleep(node.dt)  # as run_realtime does: a period of other work between ticks
                t0 = time.perf_counter()
                node.tick()
                paced[k] = time.perf_counter() - t0
            out["paced_median_us"], out["paced_p99_us"] = _timing.summary(
                "tick in hold, one every 2 ms (caches cooled by other work)", paced)
            # A command, then 20 ms without: the tick that starts a hold; 20 ms later, for
            # comparison, a tick in that hold after as long a pause (caches as cold).
            starts, later = np.empty(50), np.empty(50)
            for k in range(len(starts)):
                before = node.commands.latest_with_time()[1]
                commands.put(_command(node, n_ticks + k + 1, [12.0] * 4))
                deadline = time.perf_counter() + 1.0
                while node.commands.latest_with_time()[1] == before and time.perf_counter() < deadline:
                    time.sleep(0.001)
                for _ in range(unanswered):  # the command's tick, then states unanswered
                    node.tick()
                for out_s in (starts, later):
                    time.sleep(0.02)
                    t0 = time.perf_counter()
                    node.tick()
                    out_s[k] = time.perf_counter() - t0
                assert node.mode == "hold", node.mode
            for label, x in (("tick that starts a hold (after 20 ms idle, 50 holds)", starts),
                             ("tick in that hold 20 ms later (as cold, no hold start)", later)):
                print(f"{label:<58s} median {np.median(x) * 1e6:10.2f} µs   max {x.max() * 1e6:10.2f} µs")
            out["hold_start_median_us"], out["hold_start_max_us"] = float(np.median(starts) * 1e6), float(starts.max() * 1e6)
            hold = encoder_hold_forces(params)
            thetas = np.random.default_rng(1).uniform(-2, 2, size=(200, params.n_cables))
            it = iter(np.vstack([thetas] * 2))
            _timing.summary("hold forces alone, plain Python (eq. 33 + 63-65), off the tick",
                            _timing.time_calls(lambda: hold(next(it)), repeats=200, warmup=20), unit=1e-3, unit_name="ms")
        finally:
            node.shutdown()
            commands.close()
            token.undeclare()
    return out


def beaglebone_driver_io(n_calls: int) -> dict[str, float]:
    """The robot's driver in a tick: ``write`` (force → ESCON set value → force) then ``read``
    (encoder counts → θ), back to back, with rcpy faked at the library boundary as the tests and
    benchmarks/armhf_bridge.sh do (tests/fake_rcpy: the fake's calls cost next to nothing)."""
    sys.path.insert(0, str(ROOT / "tests" / "fake_rcpy"))
    from bridge.drivers.beaglebone import BeagleBoneConfig, BeagleBoneDriver
    from twin.model.params import load_params

    params = load_params()
    driver = BeagleBoneDriver.from_params(BeagleBoneConfig(n_motors=params.n_cables), params)
    driver.configure()
    driver.activate()
    force = np.array([10.0, 12.0, 14.0, 16.0][: params.n_cables])
    io, io_ref = np.empty(n_calls), np.empty(n_calls)
    try:
        for k in range(n_calls):
            t0 = time.perf_counter()
            driver.write(force)
            driver.read()
            t1 = time.perf_counter()
            reference()
            io[k], io_ref[k] = t1 - t0, time.perf_counter() - t1
    finally:
        driver.close()
    out: dict[str, float] = {}
    out["bb_median_us"], out["bb_p99_us"] = _timing.summary("BeagleBone driver write + read (fake rcpy)", io)
    out["bb_ratio_median"], out["bb_ratio_p99"] = _ratio("BeagleBone driver", io, io_ref)
    return out


def bridge_process_rss(replay: Path, seconds: float) -> dict[str, float]:
    """VmHWM and VmRSS (MB) of a real `xneck bridge --driver replay` after ``seconds``."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "server.cli", "bridge", "--driver", "replay", "--replay", str(replay),
                             "--loop"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(seconds)
        if proc.poll() is not None:
            raise RuntimeError(f"the bridge exited early: {proc.stderr.read() if proc.stderr else ''}")
        status = Path(f"/proc/{proc.pid}/status").read_text()
        mods = {k: float(v.split()[0]) / 1024 for k, v in (line.split(":", 1) for line in status.splitlines())
                if k in ("VmHWM", "VmRSS")}
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    print(f"{'xneck bridge --driver replay: resident memory':<58s} peak {mods['VmHWM']:8.1f} MB   now {mods['VmRSS']:8.1f} MB")
    return {"rss_peak_mb": mods["VmHWM"], "rss_mb": mods["VmRSS"]}


def realtime_priority(wanted: bool) -> str:
    """Run this process as docs/bridge.md's systemd unit runs the bridge on the robot: SCHED_FIFO
    at priority 50 (Zenoh's threads, started later, inherit it; the hold worker demotes itself).
    On a machine shared with other work this is also what keeps their load out of the figures.
    Returns what was got."""
    if not wanted:
        return "normal priority (--no-realtime)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
    except (AttributeError, OSError) as exc:
        return f"normal priority (SCHED_FIFO refused: {exc})"
    return "SCHED_FIFO 50, as the robot's systemd unit (docs/bridge.md)"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--ticks", type=int, default=5000)
    ap.add_argument("--seconds", type=float, default=5.0, help="how long the bridge process runs before its RSS is read")
    ap.add_argument("--write-replay", type=Path, default=None, help="only write a replay MCAP file there")
    ap.add_argument("--no-realtime", action="store_true",
                    help="time at normal priority, not SCHED_FIFO 50 as the robot's systemd unit runs the bridge")
    args = ap.parse_args()
    if args.write_replay is not None:
        print(write_replay(args.write_replay))
        return
    print(f"scheduling: {realtime_priority(not args.no_realtime)}; load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        replay = write_replay(Path(tmp) / "replay.mcap")
        print(f"bridge tick without numba ({args.ticks} ticks), {os.cpu_count()} cores")
        ticks = ticks_in_process(replay, args.ticks)
        rate, gap_s = _timing.interruptions()
        hit = rate * ticks["active_median_us"] * 1e-6
        print(f"{'machine: a busy Python thread loses the CPU for > 10 µs':<58s} {rate:6.0f} times/s, median gap"
              f" {gap_s * 1e6:.1f} µs: about {hit * 100:.2f} % of fresh-command ticks (at their median) lose it once")
        beaglebone_driver_io(args.ticks)
        rss = bridge_process_rss(replay, args.seconds)
    ok_tick = ticks["active_p99_us"] <= TARGET_TICK_P99_US and ticks["hold_p99_us"] <= TARGET_TICK_P99_US
    ok_rss = rss["rss_peak_mb"] <= TARGET_RSS_MB
    print(f"target tick p99 <= {TARGET_TICK_P99_US:.0f} µs: {'met' if ok_tick else 'NOT met'};"
          f" target RSS <= {TARGET_RSS_MB:.0f} MB: {'met' if ok_rss else 'NOT met'}")


if __name__ == "__main__":
    main()
