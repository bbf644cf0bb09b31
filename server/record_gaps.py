"""Where a recorded campaign has holes, and why (issue 17, campaign honesty).

The identification resamples its records on a uniform grid; a gap longer than five sample
periods is lost data, which it bridges up to 2 s (``twin.identification.processing.check_gaps``,
``fitted_instants``) and refuses beyond. "37 gap(s) in the record" said neither where nor why.
:func:`record_gaps` finds the same gaps in the two records it reads — the bridge's
``MotorState`` (500 Hz, ``stamp_s``) and the camera's ``CameraAlpha`` (30 Hz, ``capture_stamp_s``;
a frame with a missing joint does not count, as the identification's reader drops it) — and, for
each, what the archive says happened then:

- messages missing from the publisher's ``seq`` sequence: published, but not in the record (lost
  on the bus, or dropped by the recorder when its queue was full: its ``xneck.recorder`` record
  counts those);
- no missing ``seq``: the publisher itself published nothing in between (a stalled process);
- the controller's deadline misses counted over the gap (``ControllerStatus.deadline_misses``),
  its holds, the bridge's holds with their reason (``MotorState.hold_reason``);
- camera frames with a missing joint, and frames the camera dropped (``CameraAlpha.dropped``).

Pure functions of a read :class:`bridge.archive_read.Campaign`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bridge import bus
from bridge.archive import RECORDER
from bridge.archive_read import Campaign

MAX_GAP_PERIODS = 5.0  # as twin.identification.processing.gaps_of: longer is lost data, not jitter
CONTEXT_S = 0.05  # s before a gap in which holds and deadline misses are counted as its context
SHOWN = 3  # gaps described one by one per topic
#: What :func:`explain_gaps` reads of a campaign (``read_campaign(path, keys=GAP_KEYS)``).
GAP_KEYS = (bus.MOTOR_STATE, bus.CAMERA_ALPHA, bus.CONTROLLER_STATUS)


@dataclass
class Gap:
    """One hole in a record: the samples around it (seq, time) and what happened then."""

    topic: str
    seq_before: int
    seq_after: int
    t_before_s: float
    t_after_s: float
    causes: list[str] = field(default_factory=list)

    @property
    def missing(self) -> int:
        """Messages of the publisher's sequence that are not in the record."""
        return max(self.seq_after - self.seq_before - 1, 0)

    def describe(self) -> str:
        where = f"t = {self.t_before_s:.3f}-{self.t_after_s:.3f} s ({1e3 * (self.t_after_s - self.t_before_s):.0f} ms)"
        if self.missing:
            what = f"seq {self.seq_before + 1}-{self.seq_after - 1} missing, {where}: {self.missing} message(s) published but not in the record"
        else:
            what = f"seq {self.seq_before}→{self.seq_after}, {where}: nothing published in between (the publisher stalled)"
        return what + ("; " + "; ".join(self.causes) if self.causes else "")


def _gaps(topic: str, seq: np.ndarray, t: np.ndarray, max_gap_periods: float) -> list[Gap]:
    if len(t) < 3:
        return []
    order = np.argsort(t, kind="stable")
    t, seq = t[order], seq[order]
    keep = np.concatenate([[True], np.diff(t) > 0])  # a lockstep bridge re-publishes a waiting state
    t, seq = t[keep], seq[keep]
    dt = np.diff(t)
    period = float(np.median(dt))
    return [Gap(topic, int(seq[k]), int(seq[k + 1]), float(t[k]), float(t[k + 1]))
            for k in np.flatnonzero(dt > max_gap_periods * period)]


def _controller_context(campaign: Campaign, gap: Gap) -> list[str]:
    status = [m for _, m in campaign.messages(bus.CONTROLLER_STATUS)
              if gap.t_before_s - CONTEXT_S <= m.stamp_s <= gap.t_after_s]
    out = []
    if status:
        misses = max(m.deadline_misses for m in status) - min(m.deadline_misses for m in status)
        if misses:
            out.append(f"the controller counted {misses} deadline miss(es) around it")
        holds = sorted({m.hold_reason or "hold" for m in status if m.holding})
        if holds:
            out.append(f"the controller held ({', '.join(holds)})")
    return out


def _bridge_context(campaign: Campaign, gap: Gap) -> list[str]:
    holds = sorted({m.hold_reason or "hold" for _, m in campaign.messages(bus.MOTOR_STATE)
                    if gap.t_before_s - CONTEXT_S <= m.stamp_s <= gap.t_after_s and m.drive == "hold"})
    return [f"the bridge held ({', '.join(holds)})"] if holds else []


def _camera_context(campaign: Campaign, gap: Gap) -> list[str]:
    frames = [m for _, m in campaign.messages(bus.CAMERA_ALPHA) if gap.t_before_s <= m.capture_stamp_s <= gap.t_after_s]
    out = []
    blind = [m for m in frames if any(a is None for a in m.alpha_ip_rad)]
    if blind:
        joints = sorted({j + 1 for m in blind for j, a in enumerate(m.alpha_ip_rad) if a is None})
        out.append(f"{len(blind)} frame(s) with a missing joint ({', '.join(map(str, joints))}), dropped by the reader")
    if frames and frames[-1].dropped > frames[0].dropped:
        out.append(f"the camera dropped {frames[-1].dropped - frames[0].dropped} frame(s) (it fell behind)")
    return out


def record_gaps(campaign: Campaign, max_gap_periods: float = MAX_GAP_PERIODS) -> list[Gap]:
    """The gaps longer than ``max_gap_periods`` sample periods in the motor and camera records,
    each with its causes (module docstring)."""
    motor = [m for _, m in campaign.messages(bus.MOTOR_STATE)]
    frames = [m for _, m in campaign.messages(bus.CAMERA_ALPHA)]
    measured = [m for m in frames if all(a is not None for a in m.alpha_ip_rad)]
    gaps = _gaps(bus.mcap_topic(bus.MOTOR_STATE), np.array([m.seq for m in motor], dtype=np.int64),
                 np.array([m.stamp_s for m in motor], dtype=float), max_gap_periods)
    for gap in gaps:
        gap.causes = _controller_context(campaign, gap) + _bridge_context(campaign, gap)
    camera = _gaps(bus.mcap_topic(bus.CAMERA_ALPHA), np.array([m.seq for m in measured], dtype=np.int64),
                   np.array([m.capture_stamp_s for m in measured], dtype=float), max_gap_periods)
    for gap in camera:
        gap.causes = _camera_context(campaign, gap)
        if gap.missing == 0 and gap.causes:  # every frame is there, some did not measure every joint
            gap.seq_before = gap.seq_after - 1
    return gaps + camera


def explain_gaps(campaign: Campaign, max_gap_periods: float = MAX_GAP_PERIODS) -> str:
    """One paragraph per gapped record: how many gaps, messages missing, the first few gaps and
    their causes, and the recorder's own drops; '' for a record without gaps."""
    gaps = record_gaps(campaign, max_gap_periods)
    if not gaps:
        return ""
    parts = []
    for topic in dict.fromkeys(g.topic for g in gaps):
        mine = [g for g in gaps if g.topic == topic]
        lost = sum(g.missing for g in mine)
        shown = "; ".join(g.describe() for g in mine[:SHOWN])
        more = f"; and {len(mine) - SHOWN} more" if len(mine) > SHOWN else ""
        parts.append(f"{topic}: {len(mine)} gap(s) longer than {max_gap_periods:g} sample periods, "
                     f"{lost} message(s) missing in them: {shown}{more}")
    dropped = campaign.metadata.get(RECORDER, {}).get("dropped", "0")
    if dropped not in ("", "0"):
        parts.append(f"the recorder dropped {dropped} message(s) (its queue was full: a slow disk or a loaded machine)")
    elif any(g.missing for g in gaps):
        parts.append("the recorder dropped none: the missing messages were lost on the bus")
    return "record gaps: " + " | ".join(parts)
