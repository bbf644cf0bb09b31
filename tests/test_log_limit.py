"""bridge.log_limit: one line a period for what any peer can cause, the rest counted."""

from __future__ import annotations

import pytest

from bridge.log_limit import LogLimit


def test_one_event_a_period_is_logged_and_the_next_line_says_how_many_were_not() -> None:
    now = {"s": 10.0}
    limit = LogLimit(1.0, clock=lambda: now["s"])
    assert limit.allow() == 0  # the first of a burst at once
    assert [limit.allow() for _ in range(5)] == [None] * 5
    now["s"] += 0.999
    assert limit.allow() is None
    now["s"] += 0.002
    assert limit.allow() == 6 and "6 more" in LogLimit.tail(6) and LogLimit.tail(0) == ""
    now["s"] += 5.0
    assert limit.allow() == 0 and limit.suppressed == 6


@pytest.mark.parametrize("period", [0.0, -1.0, float("nan")])
def test_a_period_that_is_not_positive_is_refused(period: float) -> None:
    with pytest.raises(ValueError, match="period_s"):
        LogLimit(period)
