"""Where a controller tick spends its time, and how late its commands leave (issue 21).

:class:`TickTimes` is filled by the tick itself (a few array stores into memory allocated once:
nothing on the hot path allocates) and read about once a second, off the tick, by the process
shell, which publishes it as a :class:`bridge.bus.ControllerTiming` (recorded in each campaign's
MCAP). Stages of one tick, in ns from the state's arrival at the subscriber (the start of Zenoh's
callback):

- ``decode``: JSON to a ``MotorState`` and the receiver's checks (the gate);
- ``law``: the campaign service and the compiled law;
- ``encode``: the ``ForceCommand`` built and encoded;
- ``put``: handed to Zenoh — the end of the state-to-command latency.

A tick whose command leaves more than one period after its state arrived is a deadline miss.
Histograms use fixed bin edges (:data:`BIN_EDGES_MS`) so windows and campaigns add up.
"""

from __future__ import annotations

import numpy as np

from bridge import bus

STAGES = ("decode", "law", "encode", "put")
#: Histogram bin edges in ms for the tick period and the state-to-command latency (the last bin
#: takes everything above 50 ms).
BIN_EDGES_MS = (0.0, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 1.8, 1.9, 2.0, 2.1, 2.2, 2.5, 3.0, 4.0, 5.0, 10.0, 20.0,
                50.0, 1e6)
_EDGES_NS = np.array(BIN_EDGES_MS) * 1e6


def histogram(ns: np.ndarray) -> np.ndarray:
    """Counts of ``ns`` (durations in ns) in the bins of :data:`BIN_EDGES_MS`."""
    idx = np.clip(np.searchsorted(_EDGES_NS, ns, side="right") - 1, 0, len(_EDGES_NS) - 2)
    return np.bincount(idx, minlength=len(_EDGES_NS) - 1).astype(np.int64)


def quantile_ms(counts: np.ndarray, q: float) -> float:
    """The upper edge (ms) of the bin holding quantile ``q`` of a histogram: an upper bound."""
    total = int(counts.sum())
    if total == 0:
        return 0.0
    k = int(np.searchsorted(np.cumsum(counts), q * total, side="left"))
    return float(BIN_EDGES_MS[min(k + 1, len(BIN_EDGES_MS) - 1)])


class TickTimes:
    """Stage stamps of the last ticks (a ring of ``capacity``), the tick periods, and the
    campaign's histograms. :meth:`record` runs in the tick; :meth:`window` off it."""

    def __init__(self, capacity: int = 2048) -> None:
        self.capacity = capacity
        self.stamps = np.zeros((capacity, len(STAGES) + 1), dtype=np.int64)  # arrival, then each stage's end
        self.period = np.zeros(capacity, dtype=np.int64)
        self.n = 0
        self.skipped = 0  # stale states of a burst not answered (controller.process), this window
        self.last_arrival_ns = 0
        self.window_skipped = 0
        self.reset_campaign()

    def reset_campaign(self) -> None:
        self.campaign_latency = np.zeros(len(BIN_EDGES_MS) - 1, dtype=np.int64)
        self.campaign_period = np.zeros(len(BIN_EDGES_MS) - 1, dtype=np.int64)

    def record(self, arrival_ns: int, decoded_ns: int, law_ns: int, encoded_ns: int, put_ns: int) -> int:
        """One tick's stamps (ns, one clock); returns its state-to-command latency (ns)."""
        k = self.n % self.capacity
        row = self.stamps[k]
        row[0], row[1], row[2], row[3], row[4] = arrival_ns, decoded_ns, law_ns, encoded_ns, put_ns
        self.period[k] = arrival_ns - self.last_arrival_ns if self.last_arrival_ns else 0
        self.last_arrival_ns = arrival_ns
        self.n += 1
        return put_ns - arrival_ns

    def window(self) -> tuple[np.ndarray, np.ndarray]:
        """(per-stage durations (ticks, 4) ns, tick periods (ticks,) ns) since the last call,
        added to the campaign's histograms. At most ``capacity`` ticks: call it often enough."""
        n = min(self.n, self.capacity)
        stamps, period = self.stamps[:n].copy(), self.period[:n].copy()
        self.n = 0
        self.window_skipped, self.skipped = self.skipped, 0
        stages = np.diff(stamps, axis=1)
        period = period[period > 0]
        self.campaign_latency += histogram(stamps[:, -1] - stamps[:, 0])
        self.campaign_period += histogram(period)
        return stages, period


def timing_message(seq: int, stamp_s: float, campaign_id: str, stages_ns: np.ndarray, period_ns: np.ndarray,
                   times: TickTimes, ticks: int, deadline_misses: int, overruns: int) -> bus.ControllerTiming:
    """The ``ControllerTiming`` of one window (``stages_ns``, ``period_ns`` from
    :meth:`TickTimes.window`) and the campaign so far (``ticks``, misses and overruns: the
    service's counts since the campaign started)."""
    latency = stages_ns.sum(axis=1) if len(stages_ns) else np.zeros(0)

    def pct(x: np.ndarray, q: float) -> float:
        return float(np.percentile(x, q)) * 1e-6 if len(x) else 0.0

    return bus.ControllerTiming(
        seq=seq, stamp_s=stamp_s, campaign_id=campaign_id, window_ticks=len(stages_ns),
        window_skipped=times.window_skipped,
        latency_p50_ms=pct(latency, 50), latency_p99_ms=pct(latency, 99),
        latency_max_ms=float(latency.max()) * 1e-6 if len(latency) else 0.0,
        period_p50_ms=pct(period_ns, 50), period_p99_ms=pct(period_ns, 99),
        stage_p50_ms={s: pct(stages_ns[:, i], 50) for i, s in enumerate(STAGES)},
        stage_p99_ms={s: pct(stages_ns[:, i], 99) for i, s in enumerate(STAGES)},
        bin_edges_ms=list(BIN_EDGES_MS), latency_counts=histogram(latency).tolist(),
        period_counts=histogram(period_ns).tolist(), campaign_ticks=ticks, campaign_deadline_misses=deadline_misses,
        campaign_overruns=overruns, campaign_latency_counts=times.campaign_latency.tolist(),
        campaign_period_counts=times.campaign_period.tolist(),
        campaign_latency_p50_ms=quantile_ms(times.campaign_latency, 0.5),
        campaign_latency_p99_ms=quantile_ms(times.campaign_latency, 0.99))


__all__ = ["BIN_EDGES_MS", "STAGES", "TickTimes", "histogram", "quantile_ms", "timing_message"]
