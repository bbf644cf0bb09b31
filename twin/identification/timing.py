"""Whether α_IP is on the encoders' time: the delay at which the camera best matches the motors.

The identification pairs each camera frame with the motor states at its capture stamp
(``CameraAlpha.capture_stamp_s``). A live camera's stamp is its grab time minus a latency that is
a guess until measured (``xneck camera --latency``, 50 ms by default) plus the bridge's clock offset
(docs/camera.md, "One clock"); either wrong by d shifts every α_IP by d against θ and f, and at the
excitation's 86°/s 20 ms is 1.7°: k and λ come out biased with nothing else to show it.

This module measures the shift from the record itself. Over one campaign the joint angles are
close to a linear function of the motor angles and the cable forces (the cables' lengths follow
θ, their stretch the tensions, eqs. 20-22), so α_IP(t) ≈ A·θ(t − τ) + C·f(t − τ) + b is fitted by
least squares for each τ of a grid and the τ of least residual is the camera's delay against the
encoders: τ > 0 means α_IP is stamped τ late (its latency set τ too short, or its clock τ ahead).
The map is not the model (it is fitted per τ, nothing of the parameter set enters), so the check
holds whatever the parameters; a nonlinear remainder raises the residual at every τ alike and
moves its minimum little.

Times in s, angles in rad (degrees in the report's text only).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np

from twin.identification.processing import CampaignData, gaps_of

#: s searched either side of the stamps as recorded: above a camera's latency guess's error (the
#: default 50 ms entirely wrong) and a frame period's several, below the excitation's period.
MAX_DELAY_S = 0.25
#: s between the delays tried around the coarse grid's least residual, before the parabola.
STEP_S = 0.002
#: s between the delays of the first, coarse pass over ±``MAX_DELAY_S``.
COARSE_STEP_S = 0.01
#: |τ| (s) above which the report warns: half a frame at 30 fps. Below it the camera's own
#: quantisation of its capture time dominates.
WARN_DELAY_S = 1.0 / 60.0
#: The residual at the stamps as recorded must exceed the least one by this factor, and by
#: :data:`MIN_DIFFERENCE_RAD`, for the stamps to count as off: a noisy minimum a few ms away is no
#: delay (audit of 2026-11-29: 6° of camera noise put it 28 ms away at 5.907° against 5.914°).
MIN_CONTRAST = 1.02
#: rad the residual must vary by over the grid for the record to tell anything (a frozen camera,
#: a still neck), and by which the residual as stamped must exceed the least one (above).
MIN_DIFFERENCE_RAD = float(np.radians(0.005))

Verdict = Literal["aligned", "delayed", "out_of_range", "uninformative"]


class AlphaIpTiming(NamedTuple):
    """What :func:`alpha_ip_timing` found (s, and the fitted map's residuals in rad). ``verdict``:
    ``aligned`` (the stamps do as well as any delay), ``delayed`` (the least residual is at τ and
    the stamps do measurably worse), ``out_of_range`` (the least residual is at the grid's edge,
    ±``searched_s``, and the stamps do measurably worse: |τ| at least that), ``uninformative``
    (too few frames, or a residual flat over the grid: a still neck, a frozen camera; the
    identification refuses the latter before: :func:`twin.identification.processing.check_camera_moves`)."""

    delay_s: float  # τ of least residual: α_IP stamped this much late (negative: early)
    rms_rad: float  # residual at τ
    rms_at_stamps_rad: float  # residual at τ = 0, the stamps as recorded
    frames: int  # camera frames used (those at least ``searched_s`` inside the encoder record)
    verdict: Verdict
    searched_s: float = MAX_DELAY_S

    @property
    def resolved(self) -> bool:
        """Whether the record tells the delay (or that there is none)."""
        return self.verdict != "uninformative"

    @property
    def warn(self) -> bool:
        """Whether the stamps are off by more than :data:`WARN_DELAY_S`, measurably."""
        return self.verdict == "out_of_range" or (self.verdict == "delayed" and abs(self.delay_s) > WARN_DELAY_S)

    def text(self) -> str:
        """One line for the identification's output."""
        if self.verdict == "uninformative":
            return (f"α_IP timing: the record is too short or moves too little to tell a delay ({self.frames} frames)")
        where = (f"{'+' if self.delay_s > 0 else '-'}{self.searched_s * 1e3:.0f} ms or more (the edge of the "
                 f"search)" if self.verdict == "out_of_range" else f"{self.delay_s * 1e3:+.1f} ms")
        head = (f"α_IP timing: best matched by the encoders and forces {where} from its stamps (rms "
                f"{np.degrees(self.rms_rad):.2f}° there, {np.degrees(self.rms_at_stamps_rad):.2f}° as stamped; "
                f"{self.frames} frames)")
        if self.verdict == "aligned":
            return head + ": consistent with its stamps"
        if not self.warn:
            return head
        late = "late" if self.delay_s > 0 else "early"
        by = f"at least {self.searched_s * 1e3:.0f}" if self.verdict == "out_of_range" else f"{abs(self.delay_s) * 1e3:.0f}"
        return (head + f": WARNING, α_IP looks stamped {by} ms {late}: set the camera's --latency "
                f"{'longer' if self.delay_s > 0 else 'shorter'} by that much, or check its clock "
                f"(docs/camera.md, One clock), and record again")

    def as_dict(self) -> dict[str, float | int | bool | str | None]:
        """For JSON (a non-finite residual, too few frames, is null: strict JSON has no NaN)."""
        def finite(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {"delay_s": self.delay_s, "rms_deg": finite(np.degrees(self.rms_rad)),
                "rms_at_stamps_deg": finite(np.degrees(self.rms_at_stamps_rad)), "frames": self.frames,
                "verdict": self.verdict, "resolved": self.resolved, "warn": self.warn,
                "warn_above_s": WARN_DELAY_S, "searched_s": self.searched_s}


def _residual(t: np.ndarray, signals: np.ndarray, t_ip: np.ndarray, alpha: np.ndarray, tau_s: float) -> float:
    """RMS residual (rad) of the best linear map from ``signals`` (θ and f, sampled at ``t``) at
    t − τ to ``alpha`` at ``t_ip`` (every t_ip − τ inside ``t``'s span)."""
    ts = t_ip - tau_s
    X = np.column_stack([*(np.interp(ts, t, x) for x in signals.T), np.ones(len(ts))])
    coef, *_ = np.linalg.lstsq(X, alpha, rcond=None)
    r = alpha - X @ coef
    return float(np.sqrt(np.mean(r * r)))


def alpha_ip_timing(data: CampaignData, max_delay_s: float = MAX_DELAY_S, step_s: float = STEP_S) -> AlphaIpTiming:
    """The delay of α_IP against the encoders and forces (module docstring): the residual on a grid
    of ±``max_delay_s`` every :data:`COARSE_STEP_S`, then every ``step_s`` within one coarse step of
    its least, refined by a parabola through the least one and its two neighbours. The same frames count at every τ: those at least ``max_delay_s`` inside the
    encoder record, and not within ``max_delay_s`` of a gap in it (its interpolated states gave a
    lossy record a false "α_IP stamped 250 ms early": review of session 51)."""
    t = data.t_s
    keep = (data.t_ip_s >= t[0] + max_delay_s) & (data.t_ip_s <= t[-1] - max_delay_s)
    for a, b in gaps_of(t):
        keep &= ~((data.t_ip_s > a - max_delay_s) & (data.t_ip_s < b + max_delay_s))
    t_ip, alpha = data.t_ip_s[keep], data.alpha_ip_rad[keep]
    signals = np.concatenate([data.theta_rad, data.force_N], axis=1)
    if len(t_ip) < 3 * (signals.shape[1] + 1):  # too few frames to fit the map with a residual to compare
        return AlphaIpTiming(0.0, float("nan"), float("nan"), len(t_ip), "uninformative", max_delay_s)
    def residuals(taus: np.ndarray) -> np.ndarray:
        return np.array([_residual(t, signals, t_ip, alpha, float(tau)) for tau in taus])

    # Coarse, then fine around the coarse least: the residual is smooth over tens of ms (the
    # excitation's bandwidth is a few Hz), and a 1 h record took 29 s at the fine step throughout.
    coarse_taus = np.linspace(-max_delay_s, max_delay_s, 2 * max(1, round(max_delay_s / COARSE_STEP_S)) + 1)
    rms = residuals(coarse_taus)
    c = int(np.argmin(rms))
    interior = 0 < c < len(coarse_taus) - 1
    lo = max(-max_delay_s, float(coarse_taus[c]) - COARSE_STEP_S)
    hi = min(max_delay_s, float(coarse_taus[c]) + COARSE_STEP_S)
    fine_taus = np.arange(lo, hi + step_s / 2, step_s)
    fine = residuals(fine_taus)
    i = int(np.argmin(fine))
    delay = float(fine_taus[i])
    if 0 < i < len(fine_taus) - 1:
        # Parabola through three points: the vertex, within one step of the grid's least.
        y0, y1, y2 = fine[i - 1], fine[i], fine[i + 1]
        den = y0 - 2 * y1 + y2
        if den > 0:
            delay += float(np.clip(0.5 * (y0 - y2) / den, -1.0, 1.0)) * step_s
    rms = np.concatenate([rms, fine])
    at_delay = min(_residual(t, signals, t_ip, alpha, delay), float(fine[i]))
    at_stamps = _residual(t, signals, t_ip, alpha, 0.0)
    verdict: Verdict
    if not (rms.max() > MIN_CONTRAST * rms.min() and rms.max() - rms.min() > MIN_DIFFERENCE_RAD):
        verdict = "uninformative"
    elif not (at_stamps > MIN_CONTRAST * at_delay and at_stamps - at_delay > MIN_DIFFERENCE_RAD):
        verdict = "aligned"
    else:
        verdict = "delayed" if interior else "out_of_range"
    return AlphaIpTiming(delay, at_delay, at_stamps, len(t_ip), verdict, max_delay_s)
