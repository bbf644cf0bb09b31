"""The offset between two clocks from query round trips (NTP's estimate): pure, no bus, no clock.

A querier notes its own clock ``t0_s`` when a query leaves and ``t1_s`` when the reply comes back;
the reply carries the remote clock ``remote_s`` read in between. If the two legs took equally long,
the remote read ``remote_s`` at the local time (t0 + t1)/2, so

    offset_s = remote_s − (t0_s + t1_s)/2          (remote = local + offset)

and whatever the legs took, the truth lies within ± (t1 − t0)/2 of it: the uncertainty is half
the round trip (RTT). Of a burst of queries the one with the smallest round trip is kept (the
others were delayed by a busy scheduler or network on one leg, which biases them).

:class:`ClockTracker` keeps one estimate per burst over time (a burst every few seconds): the
current offset and its uncertainty, the drift of the remote clock against the local one (slope of
the offsets over the bursts since the last step, least squares weighted by 1/u², s/s) once the
bursts span :data:`DRIFT_MIN_SPAN_S`, and *steps*: a burst whose offset differs from the current
one by more than ``step_s`` (50 ms, beyond both uncertainties) means one of the clocks was set
(NTP's first sync on a BeagleBone without an RTC battery, an operator's ``date``); the new offset
is taken at once, counted and said.

An estimate ages: neither clock is perfect, so its uncertainty grows by ``drift_bound`` (100 ppm,
:data:`DRIFT_BOUND`, a crystal's worst) × the time since it was measured
(:meth:`ClockTracker.uncertainty_at`). A burst no step is taken when it is tighter than the current
estimate so aged; a worse one whose interval overlaps it is only *kept* out (``kept``, as NTP's
clock filter): one burst delayed on one leg (a GIL held, a Wi-Fi retry) no longer moves a good
offset by up to its ± half round trip (40 ms, audit of 2026-11-29). A worse one that does not
overlap it (nor is a step) is taken: one of the two is wrong, and the newer is the safer bet.

Samples are untrusted (they come from any peer that answers the query): a non-finite time or a
negative round trip is refused and counted, never used. All times in s.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

STEP_S = 0.05  # s: an offset that moves more than this between bursts (beyond the uncertainties) is a step
MAX_UNCERTAINTY_S = 0.05  # s: a burst whose best round trip is longer than twice this is not used
DRIFT_MIN_SPAN_S = 20.0  # s: bursts spanning less than this give no drift
HISTORY = 64  # bursts kept for the drift
DRIFT_BOUND = 100e-6  # s/s: what an estimate's uncertainty grows by a second (a crystal's worst, 100 ppm)


@dataclass(frozen=True)
class ClockSample:
    """One query: local clock when it left (``t0_s``) and when its reply came (``t1_s``), the
    remote clock in the reply (``remote_s``)."""

    t0_s: float
    remote_s: float
    t1_s: float

    @property
    def rtt_s(self) -> float:
        """Round trip (s)."""
        return self.t1_s - self.t0_s

    @property
    def offset_s(self) -> float:
        """remote − local at the round trip's middle (s)."""
        return self.remote_s - 0.5 * (self.t0_s + self.t1_s)

    def problem(self) -> str:
        """Why this sample cannot be used ('' if it can)."""
        if not all(math.isfinite(x) for x in (self.t0_s, self.remote_s, self.t1_s)):
            return f"non-finite time (t0 {self.t0_s}, remote {self.remote_s}, t1 {self.t1_s})"
        if self.t1_s < self.t0_s:
            return f"negative round trip ({self.rtt_s * 1e3:.3f} ms: the local clock stepped back)"
        return ""


@dataclass(frozen=True)
class OffsetEstimate:
    """``offset_s`` = remote − local (add it to a local time to get the remote's), true within
    ± ``uncertainty_s`` (half the round trip of the sample used); ``at_s`` the local time it
    refers to (that round trip's middle); ``samples`` the valid samples it was chosen from."""

    offset_s: float
    uncertainty_s: float
    at_s: float
    samples: int


def estimate_offset(samples: Iterable[ClockSample]) -> OffsetEstimate | None:
    """The estimate of the valid sample with the smallest round trip; None without a valid one."""
    valid = [s for s in samples if not s.problem()]
    if not valid:
        return None
    best = min(valid, key=lambda s: s.rtt_s)
    return OffsetEstimate(best.offset_s, 0.5 * best.rtt_s, 0.5 * (best.t0_s + best.t1_s), len(valid))


@dataclass(frozen=True)
class BurstOutcome:
    """What :meth:`ClockTracker.add_burst` made of a burst: ``estimate`` (None: nothing usable),
    ``used`` (the tracker took it), ``step_s`` (the offset's jump when it was a step, else None),
    ``reason`` (why it was not used, '' if it was), ``kept`` (used, but the current estimate, aged,
    was tighter and overlapped it: the offset did not move)."""

    estimate: OffsetEstimate | None
    used: bool
    step_s: float | None = None
    reason: str = ""
    kept: bool = False


@dataclass
class ClockTracker:
    """Offset of a remote clock over time, from bursts of samples (module docstring).

    ``offset_s``/``uncertainty_s`` are the current estimate's (None before one): the last used
    burst's, or the one before it kept (``kept`` counts those; module docstring); ``steps`` counts
    the steps seen, ``last_step`` is (offset before, offset after); ``invalid`` counts refused
    samples (``last_invalid`` says why); ``poor`` counts bursts whose best round trip was too long
    to use (uncertainty over ``max_uncertainty_s``); ``bursts`` counts the bursts used.
    """

    step_s: float = STEP_S
    max_uncertainty_s: float = MAX_UNCERTAINTY_S
    drift_min_span_s: float = DRIFT_MIN_SPAN_S
    history: int = HISTORY
    drift_bound: float = DRIFT_BOUND
    bursts: int = 0
    kept: int = 0
    steps: int = 0
    invalid: int = 0
    poor: int = 0
    last_invalid: str = ""
    last_step: tuple[float, float] | None = None
    _estimates: list[OffsetEstimate] = field(default_factory=list)  # used bursts since the last step
    _current: OffsetEstimate | None = None

    def __post_init__(self) -> None:
        if not (self.step_s > 0 and self.max_uncertainty_s > 0 and self.drift_min_span_s > 0 and self.history >= 2
                and self.drift_bound >= 0):
            raise ValueError("step_s, max_uncertainty_s and drift_min_span_s must be > 0 s, history >= 2, "
                             "drift_bound >= 0")

    @property
    def last(self) -> OffsetEstimate | None:
        """The current estimate (its ``uncertainty_s`` as of its ``at_s``)."""
        return self._current

    def uncertainty_at(self, now_s: float) -> float | None:
        """The current estimate's uncertainty at local ``now_s``: grown by ``drift_bound`` × its age."""
        last = self._current
        return None if last is None else last.uncertainty_s + self.drift_bound * abs(now_s - last.at_s)

    @property
    def offset_s(self) -> float | None:
        last = self.last
        return None if last is None else last.offset_s

    @property
    def uncertainty_s(self) -> float | None:
        last = self.last
        return None if last is None else last.uncertainty_s

    def add_burst(self, samples: Sequence[ClockSample]) -> BurstOutcome:
        """Take one burst's samples (module docstring)."""
        for s in samples:
            problem = s.problem()
            if problem:
                self.invalid += 1
                self.last_invalid = problem
        estimate = estimate_offset(samples)
        if estimate is None:
            return BurstOutcome(None, False, reason="no valid reply" if samples else "no reply")
        if estimate.uncertainty_s > self.max_uncertainty_s:
            self.poor += 1
            return BurstOutcome(estimate, False, reason=f"shortest round trip {2e3 * estimate.uncertainty_s:.1f} ms: "
                                                        f"more than {2e3 * self.max_uncertainty_s:.0f} ms")
        previous, step, current = self._current, None, estimate
        if previous is not None:
            aged = self.uncertainty_at(estimate.at_s)
            assert aged is not None
            jump = estimate.offset_s - previous.offset_s
            if abs(jump) > self.step_s + estimate.uncertainty_s + aged:
                step = jump
                self.steps += 1
                self.last_step = (previous.offset_s, estimate.offset_s)
                self._estimates = []  # the drift of before the step says nothing of after it
            elif aged < estimate.uncertainty_s and abs(jump) <= aged + estimate.uncertainty_s:
                current = OffsetEstimate(previous.offset_s, aged, estimate.at_s, previous.samples)
                self.kept += 1
        self._current = current
        self._estimates.append(estimate)
        del self._estimates[:-self.history]
        self.bursts += 1
        return BurstOutcome(estimate, True, step_s=step, kept=current is not estimate)

    def drift(self) -> float | None:
        """Slope of the offset against local time (s/s: 1e-6 is 1 ppm, the remote gaining 1 µs a
        second), least squares weighted by 1/u² over the bursts since the last step; None until they
        span ``drift_min_span_s``."""
        pts = self._estimates
        if len(pts) < 3 or pts[-1].at_s - pts[0].at_s < self.drift_min_span_s:
            return None
        w = [1.0 / max(p.uncertainty_s, 1e-7) ** 2 for p in pts]
        sw = sum(w)
        t_mean = sum(wi * p.at_s for wi, p in zip(w, pts, strict=True)) / sw
        o_mean = sum(wi * p.offset_s for wi, p in zip(w, pts, strict=True)) / sw
        sxx = sum(wi * (p.at_s - t_mean) ** 2 for wi, p in zip(w, pts, strict=True))
        sxy = sum(wi * (p.at_s - t_mean) * (p.offset_s - o_mean) for wi, p in zip(w, pts, strict=True))
        return sxy / sxx if sxx > 0 else None

    def reset(self) -> None:
        """Forget the estimates (a new remote clock: a restarted bridge); the counts stay."""
        self._estimates = []
        self._current = None


__all__ = ["DRIFT_BOUND", "BurstOutcome", "ClockSample", "ClockTracker", "OffsetEstimate", "estimate_offset"]
