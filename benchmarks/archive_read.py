"""Reading a campaign archive back (``bridge.archive_read.read_campaign``): what every campaign's
metrics, the console's results page and ``xneck identify`` pay before they compute anything.

Writes a synthetic campaign of the §7 control test's size (14 s at 500 Hz: motor states, commands,
controller statuses and the twin's truth, the camera at 30 Hz, and the Foxglove scene the console
adds at 20 Hz; ~28,000 messages) unless a file is given, then times ``read_campaign`` against a
baseline in the same process: the same read with mcap's own log-time ordering
(``iter_messages(log_time_order=True)``, what read_campaign used until 2026-11-28), which orders
the messages through a Python heap. Prints median and p99 of each and the ratio.

Then the memory the decoded campaign holds (tracemalloc's peak during the read, against the
file's size): whole, with the keys ``xneck identify`` read until it folded its motor states
(``keys=``, 2026-11-30), and as ``xneck identify`` reads it now
(``twin.identification.record.campaign_data_from_mcap``: motor states and commands folded into
columns, ``fold=``), per second of record as well, since a campaign may last 600 s; and the
console's campaign metrics, as they read the archive until 2026-11-30 (controller statuses and
commands decoded and kept) and folded (``server.archive_metrics.metrics_from_archive``).
Run: ``.venv/bin/python benchmarks/archive_read.py [FILE.mcap] [--repeats N]``.
"""

from __future__ import annotations

import argparse
import gc
import sys
import tempfile
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing  # (benchmarks/ is sys.path[0] when run as a script)

from bridge import bus
from bridge.archive import write_campaign
from bridge.archive_read import decode_archived, read_campaign
from server.archive_metrics import metrics_from_archive
from server.foxglove_scene import add_scene_channel
from twin.identification.record import CAMERA_TOPIC, MOTOR_COMMAND_TOPIC, MOTOR_TOPIC, campaign_data_from_mcap
from twin.model.params import load_params

#: What ``xneck identify`` reads (twin.identification.record.campaign_data_from_mcap).
IDENTIFY_KEYS = (MOTOR_TOPIC, MOTOR_COMMAND_TOPIC, CAMERA_TOPIC)
#: What the console's campaign metrics read, decoded and kept, until they were folded (2026-11-30).
METRICS_KEYS = (bus.CONTROLLER_STATUS, bus.MOTOR_COMMAND, bus.CAMERA_ALPHA)


def synthetic(path: Path, seconds: float = 14.0) -> Path:
    """A campaign file with the control test's streams, in log-time order."""
    t0, n = 1_700_000_000_000_000_000, int(seconds * 500)
    msgs: list[tuple[str, int, bus.BusMessage]] = []
    for i in range(n):
        t, s = t0 + i * 2_000_000, i * 0.002
        msgs.append((bus.MOTOR_STATE, t, bus.MotorState(seq=i, stamp_s=s, theta_rad=[0.1, 0.2, 0.3, 0.4],
                                                        force_applied_N=[5.0, 6.0, 7.0, 8.0], drive="active",
                                                        epoch="e", bridge="twin")))
        msgs.append((bus.MOTOR_COMMAND, t + 300_000, bus.ForceCommand(
            seq=i, stamp_s=s, force_N=[5.0, 6.0, 7.0, 8.0], source="controller", sender="bench", epoch="e")))
        msgs.append((bus.CONTROLLER_STATUS, t + 400_000, bus.ControllerStatus(
            seq=i, stamp_s=s, law="law2", tick_s=0.002, compute_s=1e-4, overruns=0, deadline_misses=0,
            saturated=[False] * 4, alpha_hat_rad=[0.1] * 3, alpha_d_rad=[0.1] * 3, e_rad=[0.0] * 3, holding=False)))
        msgs.append((bus.TWIN_TRUTH, t + 100_000, bus.Truth(
            seq=i, stamp_s=s, alpha_rad=[0.1] * 3, alpha_dot_rad_s=[0.0] * 3, theta_rad=[0.1] * 4,
            theta_dot_rad_s=[0.0] * 4, tension_N=[5.0] * 4, elongation_m=[1e-3] * 4, slack=[False] * 4,
            near_singular=False)))
        if i % 17 == 0:
            msgs.append((bus.CAMERA_ALPHA, t + 200_000, bus.CameraAlpha(
                seq=i, stamp_s=s, capture_stamp_s=s, alpha_ip_rad=[0.1] * 3, confidence=[1.0] * 3, source="twin")))
    msgs.sort(key=lambda m: m[1])
    write_campaign(path, msgs, {"campaign_id": "bench"})
    add_scene_channel(path, load_params())
    return path


def peak_bytes(fn: Callable[[], object]) -> int:
    """tracemalloc's peak over one call of ``fn``, from what was allocated before it."""
    gc.collect()
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return peak


def record_seconds(path: Path) -> float:
    """The motor states' span (s): what the memory is per second of."""
    t = [m.stamp_s for _, m in read_campaign(path, keys=(bus.MOTOR_STATE,)).messages(bus.MOTOR_STATE)]
    return max(t) - min(t) if len(t) > 1 else float("nan")


def baseline(path: Path) -> int:
    """read_campaign's loop as it was: mcap's log-time ordering."""
    from mcap.reader import SeekingReader

    topics: dict[str, list] = {}
    with open(path, "rb") as f:
        for _, channel, message in SeekingReader(f, validate_crcs=True).iter_messages(log_time_order=True):
            topics.setdefault(channel.topic, []).append((message.log_time, decode_archived(path, channel, message)))
    return sum(len(v) for v in topics.values())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    ap.add_argument("file", nargs="?", type=Path, help="a campaign MCAP file (default: a synthetic control test)")
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = args.file or synthetic(Path(tmp) / "bench.mcap")
        campaign = read_campaign(path)
        n = sum(len(v) for v in campaign.topics.values())
        if baseline(path) != n:
            sys.exit("the baseline read another number of messages")
        print(f"{path.name}: {n} messages, {path.stat().st_size / 1e6:.1f} MB")
        med, p99 = _timing.summary("read_campaign", _timing.time_calls(lambda: read_campaign(path), args.repeats, 1),
                                   unit=1e-3, unit_name="ms")
        bmed, bp99 = _timing.summary("baseline: mcap log_time_order=True", _timing.time_calls(
            lambda: baseline(path), args.repeats, 1), unit=1e-3, unit_name="ms")
        print(f"ratio read_campaign / baseline: median {med / bmed:.2f}, p99 {p99 / bp99:.2f}")
        size, span = path.stat().st_size, record_seconds(path)
        whole = peak_bytes(lambda: read_campaign(path))
        some = peak_bytes(lambda: read_campaign(path, keys=IDENTIFY_KEYS))
        folded = peak_bytes(lambda: campaign_data_from_mcap(path))
        metrics_kept = peak_bytes(lambda: read_campaign(path, keys=METRICS_KEYS))
        metrics_folded = peak_bytes(lambda: metrics_from_archive(path))
        for label, peak in (("read_campaign, whole", whole), ("read_campaign, xneck identify's keys", some),
                            ("xneck identify's read (motor states folded)", folded),
                            ("read_campaign, the campaign metrics' keys", metrics_kept),
                            ("campaign metrics (statuses and commands folded)", metrics_folded)):
            print(f"{label:<58s} peak {peak / 1e6:8.1f} MB   {peak / size:5.1f}x the file   "
                  f"{peak / span / 1e6:6.2f} MB per s of record ({peak / span * 600 / 1e9:.2f} GB for 600 s)")
        print(f"ratio identify's keys / whole: {some / whole:.2f}; folded / whole: {folded / whole:.2f}; "
              f"metrics folded / their keys kept: {metrics_folded / metrics_kept:.2f}")


if __name__ == "__main__":
    main()
