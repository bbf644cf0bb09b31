"""The clock-offset estimator on its own (bridge/clock_sync.py): the smallest round trip wins,
steps are told from jitter, hostile samples are refused and counted."""

from __future__ import annotations

import math

import pytest

from bridge.clock_sync import ClockSample, ClockTracker, estimate_offset


def sample(t0: float, offset: float, out_s: float, back_s: float) -> ClockSample:
    """A query leaving at local ``t0``, taking ``out_s`` to the remote and ``back_s`` back, on a
    remote clock ``offset`` ahead."""
    return ClockSample(t0, t0 + out_s + offset, t0 + out_s + back_s)


def test_the_sample_with_the_smallest_round_trip_is_kept_and_its_half_round_trip_bounds_the_error() -> None:
    # One symmetric quick query and slow ones delayed on one leg (a scheduler, a busy network): the
    # slow ones are biased by half their asymmetry, the quick one is not.
    burst = [sample(100.0, 12.345, 0.020, 0.001), sample(100.1, 12.345, 0.0002, 0.0002),
             sample(100.2, 12.345, 0.001, 0.030), sample(100.3, 12.345, 0.005, 0.005)]
    est = estimate_offset(burst)
    assert est is not None and est.samples == 4
    assert est.offset_s == pytest.approx(12.345, abs=1e-9)
    assert est.uncertainty_s == pytest.approx(0.0002, abs=1e-12)
    assert est.at_s == pytest.approx(100.1002, abs=1e-9)
    # Asymmetric legs: the estimate is off by half the asymmetry, within ± RTT/2.
    lopsided = estimate_offset([sample(5.0, -3.0, 0.004, 0.0)])
    assert lopsided is not None and abs(lopsided.offset_s - (-3.0)) == pytest.approx(0.002)
    assert abs(lopsided.offset_s - (-3.0)) <= lopsided.uncertainty_s + 1e-12


@pytest.mark.parametrize("bad", [ClockSample(1.0, math.nan, 1.001), ClockSample(1.0, math.inf, 1.001),
                                 ClockSample(math.nan, 5.0, 1.001), ClockSample(1.0, 5.0, -math.inf),
                                 ClockSample(1.0, 5.0, 0.999)])  # the last: the local clock stepped back mid-query
def test_hostile_or_broken_samples_are_refused_counted_and_never_chosen(bad: ClockSample) -> None:
    assert bad.problem()
    good = sample(10.0, 1.0, 0.003, 0.003)
    est = estimate_offset([bad, good])
    assert est is not None and est.samples == 1 and est.offset_s == pytest.approx(1.0)
    assert estimate_offset([bad]) is None
    tracker = ClockTracker()
    outcome = tracker.add_burst([bad, bad])
    assert not outcome.used and outcome.reason == "no valid reply" and tracker.offset_s is None
    assert tracker.invalid == 2 and tracker.last_invalid == bad.problem()
    assert tracker.add_burst([bad, good]).used and tracker.offset_s == pytest.approx(1.0) and tracker.invalid == 3


def test_a_burst_whose_best_round_trip_is_too_long_is_not_used() -> None:
    tracker = ClockTracker(max_uncertainty_s=0.05)
    outcome = tracker.add_burst([sample(0.0, 2.0, 0.06, 0.06), sample(1.0, 2.0, 0.2, 0.01)])
    assert not outcome.used and tracker.poor == 1 and tracker.offset_s is None
    assert "shortest round trip 120.0 ms" in outcome.reason


def test_jitter_is_not_a_step_but_a_clock_set_between_bursts_is_one() -> None:
    tracker = ClockTracker(step_s=0.05)
    t = 0.0
    for k in range(5):  # 10 s apart, 1 ms of jitter: no step
        outcome = tracker.add_burst([sample(t, 7.0 + (0.001 if k % 2 else -0.001), 0.0005, 0.0005)])
        assert outcome.used and outcome.step_s is None
        t += 10.0
    assert tracker.steps == 0 and tracker.bursts == 5
    # NTP sets the remote clock 3.2 s forward: the next burst sees the offset jump.
    outcome = tracker.add_burst([sample(t, 10.2, 0.0005, 0.0005)])
    assert outcome.used and outcome.step_s == pytest.approx(3.201, abs=1e-6)
    assert tracker.steps == 1 and tracker.last_step == (pytest.approx(6.999), pytest.approx(10.2))
    assert tracker.offset_s == pytest.approx(10.2)
    # 60 ms is a step too (over 50 ms and both uncertainties); 40 ms is not.
    assert tracker.add_burst([sample(t + 10, 10.26, 0.0005, 0.0005)]).step_s == pytest.approx(0.06)
    assert tracker.add_burst([sample(t + 20, 10.30, 0.0005, 0.0005)]).step_s is None
    assert tracker.steps == 2


def test_the_drift_is_the_offsets_slope_once_the_bursts_span_long_enough() -> None:
    tracker = ClockTracker(drift_min_span_s=20.0)
    drift = 40e-6  # the remote gains 40 µs a second (40 ppm)
    for k in range(3):
        tracker.add_burst([sample(10.0 * k, 5.0 + drift * 10.0 * k, 0.0002, 0.0002)])
    d = tracker.drift()
    assert d is not None and d == pytest.approx(drift, rel=1e-3)
    # A step starts the drift over: the bursts before it belong to another clock setting.
    tracker.add_burst([sample(30.0, 9.0, 0.0002, 0.0002)])
    assert tracker.steps == 1 and tracker.drift() is None


def test_reset_forgets_the_offset_but_keeps_the_counts() -> None:
    tracker = ClockTracker()
    tracker.add_burst([ClockSample(0.0, math.nan, 0.1), sample(0.0, 1.0, 0.001, 0.001)])
    tracker.reset()
    assert tracker.offset_s is None and tracker.invalid == 1 and tracker.bursts == 1
    # and the next clock is not a step of the old one
    assert tracker.add_burst([sample(1.0, 500.0, 0.001, 0.001)]).step_s is None and tracker.steps == 0


def test_a_worse_burst_overlapping_a_tighter_estimate_does_not_replace_it() -> None:
    """Audit of 2026-11-29 (d_worse.py): a burst whose every reply was delayed 80 ms on one leg (a
    GIL, a Wi-Fi retry) replaced a 0.2 ms estimate whole, moving the offset 40 ms silently. As NTP:
    the previous estimate, its uncertainty grown by its age × the drift bound, stays when it is
    the tighter and the two overlap; the burst still counts (and feeds the drift, weighted)."""
    tracker = ClockTracker(drift_bound=100e-6)
    assert tracker.add_burst([sample(0.0, 1000.0, 0.0002, 0.0002)]).used
    outcome = tracker.add_burst([sample(10.0 + k, 1000.0, 0.0799, 0.0001) for k in range(8)])
    assert outcome.used and outcome.kept and outcome.step_s is None and tracker.kept == 1
    assert tracker.offset_s == pytest.approx(1000.0, abs=1e-9)
    assert outcome.estimate is not None and outcome.estimate.uncertainty_s == pytest.approx(0.04, abs=1e-6)
    age = outcome.estimate.at_s - 0.0002  # its round trip's middle less the first one's
    assert tracker.uncertainty_s == pytest.approx(0.0002 + 100e-6 * age, abs=1e-9)  # aged, not the burst's 40 ms
    # a tighter burst replaces it, and the estimate ages from there
    assert not tracker.add_burst([sample(20.0, 1000.0003, 0.0001, 0.0001)]).kept
    assert tracker.offset_s == pytest.approx(1000.0003) and tracker.uncertainty_s == pytest.approx(0.0001)
    assert tracker.uncertainty_at(30.0001) == pytest.approx(0.0001 + 100e-6 * 10.0, abs=1e-9)
    # a worse burst that does not overlap the aged estimate (but is no step) is taken: one of them is wrong
    far = tracker.add_burst([sample(30.0, 1000.03, 0.005, 0.005)])
    assert not far.kept and far.step_s is None and tracker.offset_s == pytest.approx(1000.03)
    # beyond both uncertainties and the step threshold it is a step, as before
    assert tracker.add_burst([sample(40.0, 1003.0, 0.02, 0.02)]).step_s == pytest.approx(2.97)


def test_the_drift_fit_weights_each_burst_by_its_uncertainty() -> None:
    # tight bursts on a 40 ppm line, one loose burst 20 ms off it (within its 30 ms): the fit stays on the line
    tracker = ClockTracker(drift_min_span_s=20.0)
    for k in range(6):
        tracker.add_burst([sample(10.0 * k, 5.0 + 40e-6 * 10.0 * k, 0.0002, 0.0002)])
    tracker.add_burst([sample(60.0, 5.0 + 40e-6 * 60.0 + 0.02, 0.03, 0.03)])
    d = tracker.drift()
    assert d is not None and d == pytest.approx(40e-6, rel=0.02)
