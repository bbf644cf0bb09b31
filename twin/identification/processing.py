"""Campaign data and its processing (3-X paper §5.2.1): checks, zero-phase filtering, differentiation,
decimation to 31.25 Hz, and the stretch x_c of eq. 27 (our sign, docs/model.md). Pure functions on arrays.

    data = CampaignData(t_s, theta_rad, force_N, t_ip_s, alpha_ip_rad)   # checked on creation
    proc = preprocess(data, params)                                     # Processed at 31.25 Hz
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from bridge.motor_speed import MAX_SPEED_RAD_S
from twin.model import dynamics
from twin.model.numeric import build
from twin.model.params import Params

FloatArray = NDArray[np.float64]

DECIMATION = 16  # 500 Hz -> 31.25 Hz, "the value closest to 30 Hz" (§5.2.1)
MIN_SAMPLES = 64  # decimated samples (≈ 2 s at 31.25 Hz) below which nothing is identified
# Cutoff rule (see cutoff_rule): f_c = CUTOFF_FACTOR · f_99 clipped to [CUTOFF_MIN_HZ, 0.8·f_Nyquist].
CUTOFF_FACTOR = 4.0
CUTOFF_MIN_HZ = 0.5

class IdentificationError(ValueError):
    """The data cannot give a trustworthy identification; the message says why and what to fix."""


# --- campaign data ------------------------------------------------------------------------------


def _as_matrix(name: str, x: Any, cols: int | None) -> FloatArray:
    try:
        arr = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise IdentificationError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim != 2 or (cols is not None and arr.shape[1] != cols):
        want = f"(T, {cols})" if cols is not None else "(T, n)"
        raise IdentificationError(f"{name} must have shape {want}, got {arr.shape}")
    return arr


def _check_finite(name: str, arr: FloatArray, t: FloatArray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        rows = np.flatnonzero(bad.reshape(len(arr), -1).any(axis=1))
        raise IdentificationError(
            f"{name} has {bad.sum()} NaN/inf value(s), first at sample {rows[0]} (t = {t[rows[0]]:.4f} s); "
            "remove or repair them before identifying"
        )


def _check_times(name: str, t: FloatArray) -> None:
    if t.ndim != 1:
        raise IdentificationError(f"{name} must be a 1-D array of times (s), got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise IdentificationError(f"{name} has NaN/inf times")
    d = np.diff(t)
    if np.any(d <= 0):
        k = int(np.flatnonzero(d <= 0)[0])
        raise IdentificationError(f"{name} must increase strictly: t[{k}] = {t[k]} s, t[{k + 1}] = {t[k + 1]} s")


@dataclass(frozen=True, eq=False)
class CampaignData:
    """One identification campaign, as recorded (SI units).

    t_s (T,): encoder/force sample times at the control rate (500 Hz), s.
    theta_rad (T, n_cables): encoder angles at the motor shaft, rad (θ = 0 at the straight,
        unloaded neck, eq. 20).
    force_N (T, n_cables): motor forces applied over each period, N.
    t_ip_s (K,): capture times of the camera frames (same clock as ``t_s``), s.
    alpha_ip_rad (K, n_joints): α_IP from image processing, rad.
    campaign: id or path, kept for provenance.
    excitation_alpha_rad (N, n_joints) or None: the excitation trajectory α^d, rad, sampled at the
        encoder rate, when known (a campaign archive records its trajectory). Only its spectrum is
        used, to set the filter cutoff (:func:`cutoff_rule`), so it need not be aligned with t_s.
    notes: what the reader of an archive set aside and why (stray messages dropped:
        :func:`twin.identification.record.campaign_data_from_mcap`), for the report; () if nothing.
    kind: the campaign's kind as its archive says (``identification``, ``control``, ...); "" unknown.

    Raises :class:`IdentificationError` on wrong shapes, NaNs, non-increasing times, too few
    samples, or camera frames that do not cover the encoder record.
    """

    t_s: FloatArray
    theta_rad: FloatArray
    force_N: FloatArray
    t_ip_s: FloatArray
    alpha_ip_rad: FloatArray
    campaign: str = "unnamed"
    excitation_alpha_rad: FloatArray | None = None
    notes: tuple[str, ...] = ()
    kind: str = ""

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, dtype=float)
        t_ip = np.asarray(self.t_ip_s, dtype=float)
        _check_times("t_s", t)
        _check_times("t_ip_s", t_ip)
        theta = _as_matrix("theta_rad", self.theta_rad, None)
        force = _as_matrix("force_N", self.force_N, theta.shape[1])
        alpha = _as_matrix("alpha_ip_rad", self.alpha_ip_rad, None)
        for name, arr, times in (("theta_rad", theta, t), ("force_N", force, t), ("alpha_ip_rad", alpha, t_ip)):
            if len(arr) != len(times):
                tname = "t_ip_s" if name == "alpha_ip_rad" else "t_s"
                raise IdentificationError(f"{name} has {len(arr)} rows but {tname} has {len(times)} times")
        _check_finite("theta_rad", theta, t)
        _check_finite("force_N", force, t)
        _check_finite("alpha_ip_rad", alpha, t_ip)
        need = MIN_SAMPLES * DECIMATION
        if len(t) < need:
            raise IdentificationError(
                f"too few encoder samples: {len(t)} ({t[-1] - t[0] if len(t) > 1 else 0:.2f} s); identification "
                f"needs at least {need} (about {need / 500:.1f} s at 500 Hz), a full excitation trajectory is ~100 s"
            )
        if len(t_ip) < MIN_SAMPLES:
            raise IdentificationError(f"too few camera frames: {len(t_ip)}, need at least {MIN_SAMPLES}")
        overlap = min(t[-1], t_ip[-1]) - max(t[0], t_ip[0])
        if overlap < 0.5 * (t[-1] - t[0]):
            raise IdentificationError(
                f"camera frames ({t_ip[0]:.2f}-{t_ip[-1]:.2f} s) cover less than half of the encoder record "
                f"({t[0]:.2f}-{t[-1]:.2f} s): are both on the same clock?"
            )
        if self.excitation_alpha_rad is not None:
            exc = _as_matrix("excitation_alpha_rad", self.excitation_alpha_rad, None)
            if exc.shape[1] != alpha.shape[1]:  # "must have shape (T, 2)" said nothing of why (audit of 2026-11-27)
                raise IdentificationError(f"the recorded trajectory moves {exc.shape[1]} joints and the camera "
                                          f"measures {alpha.shape[1]}: not one robot's campaign")
            if len(exc) < MIN_SAMPLES or not np.all(np.isfinite(exc)):
                raise IdentificationError(f"excitation_alpha_rad must hold at least {MIN_SAMPLES} finite rows, "
                                          f"got {len(exc)} rows, {int((~np.isfinite(exc)).sum())} non-finite values")
            object.__setattr__(self, "excitation_alpha_rad", exc)
        for name, arr in (("t_s", t), ("theta_rad", theta), ("force_N", force), ("t_ip_s", t_ip), ("alpha_ip_rad", alpha)):
            object.__setattr__(self, name, arr)

    @property
    def n_cables(self) -> int:
        return int(self.theta_rad.shape[1])

    @property
    def n_joints(self) -> int:
        return int(self.alpha_ip_rad.shape[1])

    @property
    def rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.t_s)))

    def window(self, t0_s: float, t1_s: float) -> CampaignData:
        """The record between ``t0_s`` and ``t1_s`` (s, on the record's clock: the times its
        gaps are reported at), encoders and camera alike; a note says so. For a campaign whose
        record has a gap too long to bridge (:func:`check_gaps`, :func:`longest_common_span`):
        ``xneck identify --window``."""
        if not (math.isfinite(t0_s) and math.isfinite(t1_s) and t0_s < t1_s):
            raise IdentificationError(f"window {t0_s:g}-{t1_s:g} s: the start must be a time before the end")
        keep = (self.t_s >= t0_s) & (self.t_s <= t1_s)
        keep_ip = (self.t_ip_s >= t0_s) & (self.t_ip_s <= t1_s)
        if not keep.any():
            raise IdentificationError(f"window {t0_s:g}-{t1_s:g} s holds no encoder sample: the record spans "
                                      f"t = {self.t_s[0]:.2f}-{self.t_s[-1]:.2f} s")
        note = f"fitted on t = {t0_s:g}-{t1_s:g} s of the record (t = {self.t_s[0]:.2f}-{self.t_s[-1]:.2f} s)"
        return replace(self, t_s=self.t_s[keep], theta_rad=self.theta_rad[keep], force_N=self.force_N[keep],
                       t_ip_s=self.t_ip_s[keep_ip], alpha_ip_rad=self.alpha_ip_rad[keep_ip],
                       notes=(*self.notes, note))


def _cuts(t: FloatArray, max_gap: float, min_gap_s: float = 0.0) -> NDArray[np.int64]:
    """The samples of ``t`` after which comes a gap longer than ``max_gap`` median periods and ``min_gap_s``."""
    return np.flatnonzero(np.diff(t) > max(max_gap * float(np.median(np.diff(t))), min_gap_s))


def gap_free_spans(t: FloatArray, max_gap: float = 5.0, min_gap_s: float = 0.0) -> list[tuple[float, float]]:
    """The spans (s) of ``t`` between gaps longer than ``max_gap`` median periods and ``min_gap_s``."""
    cuts = _cuts(t, max_gap, min_gap_s)
    starts = [0, *(cuts + 1)]
    ends = [*cuts, len(t) - 1]
    return [(float(t[a]), float(t[b])) for a, b in zip(starts, ends, strict=True)]


def longest_common_span(data: CampaignData, max_gap: float = 5.0, min_gap_s: float = 0.0) -> tuple[float, float]:
    """The longest span (s) free of gaps (longer than ``max_gap`` periods and ``min_gap_s``) in both
    the encoder/force and the camera record, rounded inwards to 10 ms so that a window given with
    two decimals stays inside it; (nan, nan) if none."""
    best = (math.nan, math.nan)
    for a0, a1 in gap_free_spans(data.t_s, max_gap, min_gap_s):
        for b0, b1 in gap_free_spans(data.t_ip_s, max_gap, min_gap_s):
            lo, hi = math.ceil(max(a0, b0) * 100) / 100, math.floor(min(a1, b1) * 100) / 100
            if hi > lo and (math.isnan(best[0]) or hi - lo > best[1] - best[0]):
                best = (lo, hi)
    return best


def gaps_of(t: FloatArray, max_gap: float = 5.0) -> FloatArray:
    """(k, 2): the times (s) of the samples before and after each gap of ``t`` longer than
    ``max_gap`` median periods (lost data, not jitter)."""
    if len(t) < 2:
        return np.zeros((0, 2))
    k = _cuts(t, max_gap)
    return np.column_stack([t[k], t[k + 1]])


def check_gaps(data: CampaignData, max_gap: float = 5.0) -> None:
    """Refuse a record with a gap longer than :data:`MAX_GAP_S` (the record is then two campaigns,
    not one with states lost), saying which span could be fitted alone. Shorter gaps are bridged
    by :func:`preprocess`, their instants not fitted (:func:`fitted_instants`)."""
    for what, t in (("encoder/force record", data.t_s), ("camera record", data.t_ip_s)):
        gaps = gaps_of(t, max_gap)
        long = np.flatnonzero(gaps[:, 1] - gaps[:, 0] > MAX_GAP_S)
        if not long.size:
            continue
        k = int(long[0])
        # shorter gaps are bridged: the span runs across them (it stopped at every one: review of session 51)
        lo, hi = longest_common_span(data, max_gap, MAX_GAP_S)
        total = float(max(data.t_s[-1], data.t_ip_s[-1]) - min(data.t_s[0], data.t_ip_s[0]))
        hint = (f"the longest span without a gap beyond {MAX_GAP_S:g} s in either record is t = {lo:.2f}-{hi:.2f} s "
                f"({hi - lo:.1f} s of {total:.1f} s): identify it alone with --window {lo:.2f}:{hi:.2f}") \
            if math.isfinite(lo) else f"no span is without a gap beyond {MAX_GAP_S:g} s in both records"
        raise IdentificationError(
            f"{what}: {long.size} gap(s) in the record longer than {MAX_GAP_S:g} s (too long to bridge: the "
            f"record is two campaigns), the first {gaps[k, 1] - gaps[k, 0]:.3f} s long at t = {gaps[k, 0]:.3f} s "
            f"(sampling period {float(np.median(np.diff(t))) * 1e3:.2f} ms); {hint}"
        )


#: Periods of the filter's cutoff up to which a gap is *bridged*: interpolated linearly, only its
#: own instants not fitted. Why 0.2: the motion lies below f_99 = f_c/4 (:func:`cutoff_rule`),
#: whose linear interpolation over 0.2/f_c errs by at most (2π·0.05)²/8 = 1.2 % of its amplitude at
#: the gap's middle, and the filter spreads that over its memory, ~1/f_c, five times the gap.
#: 125 ms at the §5.2.2 trajectory's 1.6 Hz: 88 of the 95 gaps of a loaded 600 s campaign
#: (docs/console.md "Long campaigns"; 10-819 ms, median 42 ms).
BRIDGE_CUTOFF_PERIODS = 0.2
#: s: a longer gap is refused (:func:`check_gaps`). Shorter and beyond the bridge, a gap is
#: interpolated (the filters and the model's recursions run through it) and the instants within
#: the filter's memory of it (the record ends' edge, two cutoff periods, at least 1 s) are not fitted,
#: nor those :data:`RECURSION_MEMORY_S` further after it.
MAX_GAP_S = 2.0
#: s after a long gap's filter edge not fitted either: the creep state of the load-friction and
#: output-error fits (τ 0.5-8 s), driven through the interpolation, keeps its error for about τ.
#: Without it, seven 1.9 s gaps of frames moved the load-friction fit's k 1.3 σ and β 1.6 σ from
#: the whole record's on the same instants (τ held at 2 s); with it 0.3 and 0.5 σ (review of session 51).
RECURSION_MEMORY_S = 2.0


def fitted_instants(t_s: FloatArray, gaps: FloatArray, bridge_s: float, edge_s: float) -> NDArray[np.bool_]:
    """(n,) which instants ``t_s`` a fit may use, given the record's ``gaps`` ((k, 2), s, both records'):
    not those inside a gap of at most ``bridge_s`` (:data:`BRIDGE_CUTOFF_PERIODS` cutoff periods),
    nor those within ``edge_s`` before a longer one and ``edge_s`` + :data:`RECURSION_MEMORY_S` after it."""
    fitted = np.ones(len(t_s), dtype=bool)
    for a, b in gaps:
        long = b - a > bridge_s
        before, after = (edge_s, edge_s + RECURSION_MEMORY_S) if long else (0.0, 0.0)
        fitted &= ~((t_s > a - before) & (t_s < b + after))
    return fitted


def _gap_note(gaps: FloatArray, n_states: int, fitted: NDArray[np.bool_], bridge_s: float, h: float) -> str:
    """What the gaps cost, for the report; "" without gaps. ``gaps[:n_states]``: the motor states'."""
    if not len(gaps):
        return ""
    length = gaps[:, 1] - gaps[:, 0]
    short = int((length <= bridge_s).sum())
    lost = int((~fitted).sum())
    return (f"{len(gaps)} gap(s) in the record ({n_states} of the motor states, {len(gaps) - n_states} of the camera "
            f"frames; {1e3 * length.min():.0f}-{1e3 * length.max():.0f} ms): {short} of at most {1e3 * bridge_s:.0f} ms "
            f"bridged by interpolation, {len(gaps) - short} longer with the filter's memory around them; {lost} of "
            f"{len(fitted)} instants ({lost * h:.1f} s) not fitted")


# --- processing (§5.2.1) ----------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Processed:
    """Filtered, differentiated, decimated signals on the identification instants ``t_s``.

    Arrays are (n,) or (n, ·) at 31.25 Hz: θ, θ̇, θ̈ (rad, rad/s, rad/s²) and f (N) from the
    encoders (filtered at 500 Hz, then decimated by 16); α, α̇, α̈ from α_IP (filtered at the
    camera rate, linearly interpolated to ``t_s``, central differences); x_c, ẋ_c, ẍ_c (m, m/s,
    m/s²) from eq. 27 (our sign); the model terms Z, M, c, g at (α, α̇).
    ``fast_*``: the 500 Hz record (raw θ, filtered θ̇, f) for the 2 ms estimators of eqs. 35/58.
    ``fitted`` (n,): the instants a fit uses (:func:`fitted_instants`: not those of a gap in the
    record, where the signals are interpolated); ``notes``: what the gaps cost, for the report.
    """

    t_s: FloatArray
    theta: FloatArray
    theta_dot: FloatArray
    theta_ddot: FloatArray
    force: FloatArray
    alpha: FloatArray
    alpha_dot: FloatArray
    alpha_ddot: FloatArray
    x_c: FloatArray
    x_c_dot: FloatArray
    x_c_ddot: FloatArray
    Z: FloatArray
    M: FloatArray
    c: FloatArray
    g: FloatArray
    cutoff_hz: float
    f_99_hz: float
    rate_hz: float
    bandwidth_from: str  # "alpha_d" (the excitation trajectory), "theta_dot" (the encoders) or "given"
    fast_t_s: FloatArray
    fast_theta: FloatArray
    fast_theta_dot: FloatArray
    fast_force: FloatArray
    fitted: NDArray[np.bool_]
    notes: tuple[str, ...] = ()

    @property
    def n(self) -> int:
        return len(self.t_s)


def cutoff_rule(velocity: FloatArray, rate_hz: float, nyquist_hz: float) -> tuple[float, float]:
    """Cutoff (Hz) of the zero-phase Butterworth filter, and the motion bandwidth f_99 (Hz).

    Rule (after Pham, Gautier & Poignet 2001, ref. [37]: the cutoff sits a few times above the
    bandwidth of the motion, so that the filter removes noise and leaves the dynamics alone, and
    both sides of the linear model are filtered alike): f_99 is the frequency below which 99 % of
    the energy of ``velocity`` lies; f_c = 4·f_99, at least 0.5 Hz and at most 0.8 of the Nyquist
    frequency of the slowest stream (the camera, 15 Hz). :func:`preprocess` passes the velocity of
    the excitation trajectory α̇^d when the campaign records it (f_99 = 0.40 Hz on the §5.2.2
    trajectory, f_c = 1.6 Hz), else the motor velocities θ̇. θ̇ is a fallback: it also carries the
    motor-cable mode (≈ 18 kg of reflected motor inertia on a 5-8 kN/m cable, ≈ 3 Hz), which rings
    when the cable damping is small and then holds ~1 % of the θ̇ energy: enough to move f_99 from
    0.43 to 1.7 Hz, hence f_c from 1.7 to 6.8 Hz, which lets α_IP noise into x_c and, twice
    differentiated, into ẍ_c (the Γ_rf error of eq. 52 grows fifteenfold on the twin).
    Why 4 and not the usual 5-10: α_IP carries 1° of white noise up to 15 Hz that enters the
    regressor x_c; the friction regressor arctan(c_s·θ̇) is nonlinear, so a too-low cutoff rounds
    its sign changes (f_s is 2 % low at 0.9 Hz, 0.1 % at 1.7 Hz on the twin).
    """
    v = velocity - velocity.mean(axis=0)
    spec = np.abs(np.fft.rfft(v, axis=0)) ** 2
    power = spec.sum(axis=1)
    cum = np.cumsum(power)
    freqs = np.fft.rfftfreq(len(v), 1.0 / rate_hz)
    if cum[-1] <= 0.0:
        f_99 = CUTOFF_MIN_HZ
    else:
        f_99 = float(freqs[min(np.searchsorted(cum, 0.99 * cum[-1]), len(freqs) - 1)])
    return float(np.clip(CUTOFF_FACTOR * f_99, CUTOFF_MIN_HZ, 0.8 * nyquist_hz)), f_99


def _uniform(t: FloatArray, x: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """Samples on a uniform grid at the median rate: linear interpolation of jittered stamps, and
    across gaps (:func:`check_gaps` refused those too long to bridge; :func:`fitted_instants` says
    which instants of a gap's are not fitted)."""
    dt = float(np.median(np.diff(t)))
    n = int(math.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    grid = t[0] + dt * np.arange(n)
    # Length first: with a missed sample the grid is longer than the stamps and cannot be compared.
    if n == len(t) and np.allclose(grid, t, atol=1e-3 * dt, rtol=0.0):
        return t, x, dt
    return grid, np.column_stack([np.interp(grid, t, x[:, j]) for j in range(x.shape[1])]), dt


def _butter(x: FloatArray, cutoff_hz: float, rate_hz: float, order: int = 4) -> FloatArray:
    sos = signal.butter(order, cutoff_hz, fs=rate_hz, output="sos")
    return signal.sosfiltfilt(sos, x, axis=0)


#: How far beyond the parameter set's f_max (or the joint limits) a recorded value may lie before
#: the record is taken for damaged: margins for another set's limits and for camera noise.
PLAUSIBLE_FORCE_FACTOR = 10.0
PLAUSIBLE_ALPHA_RAD = np.pi
#: rad/s at the motor shaft no encoder step between two samples can mean: the bridge's own bound
#: (:data:`bridge.motor_speed.MAX_SPEED_RAD_S`, the controller's ``MOTOR_SPEED_MAX_RAD_S``), twice
#: the EC-max 40's no-load speed (about 785 rad/s); an identification campaign's fastest step is
#: 80 rad/s on the twin, 250 rad/s against the robot truth (its slack and its stamps' jitter). Not
#: larger: one encoder turn (2π rad) in one 2 ms period must stay beyond it (3200 rad/s).
PLAUSIBLE_MOTOR_SPEED_RAD_S = MAX_SPEED_RAD_S


def _check_encoder_steps(data: CampaignData) -> None:
    """Raise :class:`IdentificationError` naming the first step of a motor's θ between two
    consecutive samples that no motor can turn: beyond :data:`PLAUSIBLE_MOTOR_SPEED_RAD_S` times
    the time between them (at least the median period: a state stamped late and the next on time
    are no faster motor). A non-finite θ is refused before (:class:`CampaignData`). The bridge
    and the controller refuse such a reading live; the identification fitted it: one θ sample of 1e6
    rad gave k(1) = 36 N/m (truth ~5400) at a relative σ of 8.5 %, a one-turn jump of θ₁ k(2) 11 %
    and λ(4) 10 % low, unflagged (audit of 2026-11-30)."""
    theta, t = data.theta_rad, data.t_s
    if len(t) < 2:
        return
    dt = np.diff(t)
    dt = np.maximum(dt, float(np.median(dt)))
    with np.errstate(over="ignore", invalid="ignore"):  # a 1e300 rad sample: an inf step, refused
        step = np.diff(theta, axis=0)
    bad = ~(np.abs(step) <= (PLAUSIBLE_MOTOR_SPEED_RAD_S * dt)[:, None])
    if not bad.any():
        return
    rows = np.flatnonzero(bad.any(axis=1))
    i = int(rows[0])
    j = int(np.flatnonzero(bad[i])[0])
    raise IdentificationError(
        f"motor {j + 1}'s encoder jumps {step[i, j]:+.6g} rad between t = {t[i]:.4f} s and {t[i + 1]:.4f} s "
        f"(samples {i} and {i + 1}: θ = {theta[i, j]:.6g} then {theta[i + 1, j]:.6g} rad), more than a motor "
        f"turns in {dt[i] * 1e3:.3g} ms ({PLAUSIBLE_MOTOR_SPEED_RAD_S:g} rad/s): an encoder fault (a glitch, a "
        f"count lost or gained) or a damaged record ({len(rows)} such step{'' if len(rows) == 1 else 's'})")


def _check_plausible(data: CampaignData, params: Params) -> None:
    """Raise :class:`IdentificationError` naming the first sample out of physical reach: a step of
    θ faster than a motor turns (:func:`_check_encoder_steps`), a force beyond
    ±``PLAUSIBLE_FORCE_FACTOR`` × f_max (a measured force may dip below 0 with its noise),
    an α_IP beyond ±π. One force sample of
    1e300 N went through the filters as 32 lines of numpy overflow warnings and an error blaming
    the trajectory's excitation (audit of 2026-11-27)."""
    _check_encoder_steps(data)
    f_max = float(params.limits.f_max)
    bad = np.flatnonzero((np.abs(data.force_N) > PLAUSIBLE_FORCE_FACTOR * f_max).any(axis=1))
    if bad.size:
        i = int(bad[0])
        raise IdentificationError(
            f"force sample {i} (t = {data.t_s[i]:.3f} s) is {data.force_N[i].tolist()} N, beyond ±"
            f"{PLAUSIBLE_FORCE_FACTOR:g} × f_max = {PLAUSIBLE_FORCE_FACTOR * f_max:g} N: a damaged record ({len(bad)} such samples)")
    bad = np.flatnonzero((np.abs(data.alpha_ip_rad) > PLAUSIBLE_ALPHA_RAD).any(axis=1))
    if bad.size:
        i = int(bad[0])
        raise IdentificationError(
            f"camera frame {i} (t = {data.t_ip_s[i]:.3f} s) measures α = {np.degrees(data.alpha_ip_rad[i]).round(1).tolist()}°, "
            f"beyond ±180°: a damaged record ({len(bad)} such frames)")


#: rad by which consecutive camera frames' α_IP may differ (every joint) and still be the same
#: reading: a camera's noise (1° on the twin's) moves it more at every frame, a frozen camera not at all.
FROZEN_STEP_RAD = float(np.radians(0.01))
#: s and frames a run of unchanged α_IP must last for its camera to be judged frozen: a few
#: repeated frames are a still neck seen by a noiseless camera (the twin's rendered one).
FROZEN_MIN_S = 1.0
FROZEN_MIN_FRAMES = 10
#: rad the joint angles estimated from the encoders (eq. 33, the stretch from the forces) must move
#: within such a run for the camera to be taken for frozen. That estimate's error (up to 10-12° on
#: the twin's campaigns) moves little at rest: hundredths of a degree in a hold, about 10° were the
#: base set's k 50 % off and a cable's force to change by f_max there (about 1.6° per mm of a short
#: cable's stretch); the excitation moves the neck 40-86° per joint.
FROZEN_MOTION_RAD = float(np.radians(20.0))


def check_camera_moves(data: CampaignData, params: Params) -> None:
    """Raise :class:`IdentificationError` for a frozen camera: α_IP unchanged (consecutive frames
    within :data:`FROZEN_STEP_RAD`) for at least :data:`FROZEN_MIN_S` and :data:`FROZEN_MIN_FRAMES`
    while the joint angles the encoders give there (eq. 33 on θ, with the stretch f/k of the base
    set's linear cables) move by more than :data:`FROZEN_MOTION_RAD`. A camera whose α_IP stayed
    constant after its fifth frame while the motors moved for 97 s was fitted (k(3) −63 %, exit 0)
    with a note that the record moved too little to tell α_IP's delay (audit of 2026-11-30): a frozen
    camera's α_IP is not the neck's, and nothing fitted on it is."""
    from twin.model.estimation import alpha_hat_3

    t_ip, alpha, t = data.t_ip_s, data.alpha_ip_rad, data.t_s
    if len(t_ip) < 2:
        return
    changed = np.flatnonzero((np.abs(np.diff(alpha, axis=0)) > FROZEN_STEP_RAD).any(axis=1)) + 1
    starts = np.concatenate([[0], changed])
    ends = np.concatenate([changed - 1, [len(t_ip) - 1]])
    m = None
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        inside = np.flatnonzero((t_ip[a:b + 1] >= t[0]) & (t_ip[a:b + 1] <= t[-1])) + a
        if len(inside) < FROZEN_MIN_FRAMES or t_ip[inside[-1]] - t_ip[inside[0]] < FROZEN_MIN_S:
            continue
        m = build(params, "linear") if m is None else m
        theta = np.column_stack([np.interp(t_ip[inside], t, x) for x in data.theta_rad.T])
        force = np.column_stack([np.interp(t_ip[inside], t, x) for x in data.force_N.T])
        guess = np.zeros(m.n_joints)
        hat = np.empty((len(inside), m.n_joints))
        for i in range(len(inside)):
            guess = hat[i] = alpha_hat_3(m, theta[i], force[i] / m.k, guess)
        moved = np.ptp(hat, axis=0)
        j = int(np.argmax(moved))
        if moved[j] > FROZEN_MOTION_RAD:
            raise IdentificationError(
                f"the camera looks frozen: its α_IP stays at {np.degrees(alpha[a]).round(2).tolist()}° from t = "
                f"{t_ip[inside[0]]:.3f} s to {t_ip[inside[-1]]:.3f} s ({len(inside)} frames) while the encoders move "
                f"joint {j + 1} through {np.degrees(moved[j]):.0f}° there (eq. 33 from θ and the forces): a frozen or "
                f"stuck camera's α_IP is not the neck's; check the camera and record again")


#: How far the excitation α^d's range of a joint may differ from what the camera saw it move (rad,
#: and a fraction of the larger of the two) and still describe the record: the closed loop tracks
#: α^d within a few degrees (84 against 80°, 64 against 60° on the twin's campaigns).
EXCITATION_MISMATCH_RAD = float(np.radians(15.0))
EXCITATION_MISMATCH_FRACTION = 0.5


def check_excitation_describes(data: CampaignData) -> None:
    """Raise :class:`IdentificationError` when the excitation α^d (the archive's recorded trajectory)
    does not describe the record: a joint's range in α^d and in α_IP differ by more than
    :data:`EXCITATION_MISMATCH_RAD` and :data:`EXCITATION_MISMATCH_FRACTION` of the larger. The
    filter cutoff follows α^d: an archive whose trajectory said a 0.5° move, beside a record of
    80°, was filtered at 0.5 Hz and gave k(2) −23 %, λ(3) +49 %, exit 0 (audit of 2026-11-30)."""
    if data.excitation_alpha_rad is None or len(data.t_ip_s) < 2:
        return
    inside = (data.t_ip_s >= data.t_s[0]) & (data.t_ip_s <= data.t_s[-1])
    if inside.sum() < 2:
        return
    seen = np.ptp(data.alpha_ip_rad[inside], axis=0)
    planned = np.ptp(data.excitation_alpha_rad, axis=0)
    gap = np.abs(seen - planned)
    bad = np.flatnonzero(gap > np.maximum(EXCITATION_MISMATCH_RAD, EXCITATION_MISMATCH_FRACTION * np.maximum(seen, planned)))
    if bad.size:
        j = int(bad[np.argmax(gap[bad])])
        raise IdentificationError(
            f"the campaign's recorded trajectory does not describe its record: joint {j + 1} moves through "
            f"{np.degrees(planned[j]):.1f}° in it and {np.degrees(seen[j]):.1f}° in α_IP (an edited archive, or "
            f"another campaign's trajectory): the filter cutoff follows the trajectory; --cutoff-hz sets it instead")


def preprocess(data: CampaignData, params: Params, cutoff_hz: float | None = None) -> Processed:
    """§5.2.1: zero-phase Butterworth (order 4, :func:`cutoff_rule` unless ``cutoff_hz``) on θ,
    f and α_IP; central differences; θ and f decimated from 500 Hz to 31.25 Hz (anti-aliased,
    zero phase); α_IP interpolated linearly to the same instants; x_c from eq. 27 (our sign).

    Edge samples spoiled by the filters (two cutoff periods, at least 1 s, at each end) and
    instants outside the camera record are dropped. Gaps in either record (lost states or frames)
    up to :data:`MAX_GAP_S` are interpolated across, their instants marked not fitted
    (``Processed.fitted``, :func:`fitted_instants`); a longer one is refused (:func:`check_gaps`).
    """
    m = build(params)
    if data.n_cables != m.n_cables or data.n_joints != m.n_joints:
        raise IdentificationError(
            f"campaign has {data.n_cables} motors and {data.n_joints} camera angles, the parameter set "
            f"{params.name!r} has {m.n_cables} cables and {m.n_joints} joints"
        )
    _check_plausible(data, params)
    check_gaps(data)
    check_camera_moves(data, params)
    t, enc, dt = _uniform(data.t_s, np.hstack([data.theta_rad, data.force_N]))
    rate = 1.0 / dt
    t_ip, a_ip, dt_ip = _uniform(data.t_ip_s, data.alpha_ip_rad)
    nc = m.n_cables
    raw_theta = enc[:, :nc]
    nyquist = 0.5 * min(rate / DECIMATION, 1.0 / dt_ip)
    if cutoff_hz is not None:
        fc, f_99, source = float(cutoff_hz), float("nan"), "given"
        motion_f99 = cutoff_rule(np.gradient(raw_theta, dt, axis=0), rate, nyquist)[1]  # for the gaps' bridge
        # The edges dropped below (two cutoff periods at each end) must leave MIN_SAMPLES instants:
        # fc ≥ 4/room. Far below that the Butterworth's coefficients are singular too (1e-9 Hz
        # was "error: Singular matrix", input audit). Rounded up to the mHz, as the message says it.
        span = min(t[-1], t_ip[-1]) - max(t[0], t_ip[0])
        room = span - MIN_SAMPLES * DECIMATION * dt
        fc_min = math.ceil(4.0 / max(room, 2.0) * 1000.0) / 1000.0
        if not (fc_min <= fc < nyquist):
            raise IdentificationError(
                f"cutoff {fc:g} Hz is out of range: for this record it must be in [{fc_min:g}, {nyquist:.2f}) Hz "
                f"(below, the filter edges, two cutoff periods dropped at each end of its {span:.1f} s, leave fewer "
                f"than {MIN_SAMPLES} instants; from {nyquist:.2f} Hz up, past the Nyquist frequency of the "
                f"decimated/camera data)")
    elif data.excitation_alpha_rad is not None:
        check_excitation_describes(data)
        fc, f_99 = cutoff_rule(np.gradient(data.excitation_alpha_rad, dt, axis=0), rate, nyquist)
        source = "alpha_d"
    else:
        fc, f_99 = cutoff_rule(np.gradient(raw_theta, dt, axis=0), rate, nyquist)
        source = "theta_dot"
    if source != "given":
        motion_f99 = f_99
    if not (0.0 < fc < nyquist):
        raise IdentificationError(f"cutoff {fc} Hz must be in (0, {nyquist:.2f}) Hz (Nyquist of the decimated/camera data)")

    filt = _butter(enc, fc, rate)
    theta_f, force_f = filt[:, :nc], filt[:, nc:]
    theta_dot = np.gradient(theta_f, dt, axis=0)
    theta_ddot = np.gradient(theta_dot, dt, axis=0)
    # Anti-aliased, zero-phase decimation (FIR: an order-8 IIR is unstable for a factor > 13).
    stack = np.hstack([theta_f, theta_dot, theta_ddot, force_f])
    dec = signal.decimate(stack, DECIMATION, ftype="fir", axis=0, zero_phase=True)
    t_dec = t[:: DECIMATION][: len(dec)]

    alpha_f = _butter(a_ip, fc, 1.0 / dt_ip)
    edge = max(1.0, 2.0 / fc)
    keep = (t_dec >= max(t[0], t_ip[0]) + edge) & (t_dec <= min(t[-1], t_ip[-1]) - edge)
    if keep.sum() < MIN_SAMPLES:
        raise IdentificationError(
            f"only {keep.sum()} identification instants remain after dropping {edge:.1f} s of filter edges "
            f"at each end; need at least {MIN_SAMPLES}"
        )
    t_dec, dec = t_dec[keep], dec[keep]
    # the gaps that touch the instants kept (those in the dropped ends cost nothing)
    states, frames = (g[(g[:, 1] > t_dec[0]) & (g[:, 0] < t_dec[-1])] for g in (gaps_of(data.t_s), gaps_of(data.t_ip_s)))
    gaps = np.concatenate([states, frames])
    # The bridge's bound holds for the motion's bandwidth (BRIDGE_CUTOFF_PERIODS): a cutoff given
    # below the rule's (4·f_99) does not lengthen it.
    bridge_s = BRIDGE_CUTOFF_PERIODS / max(fc, CUTOFF_FACTOR * motion_f99)
    fitted = fitted_instants(t_dec, gaps, bridge_s, edge)
    gap_note = _gap_note(gaps, len(states), fitted, bridge_s, DECIMATION * dt)
    if fitted.sum() < MIN_SAMPLES:
        lo, hi = longest_common_span(data)
        raise IdentificationError(
            f"only {fitted.sum()} identification instants remain fitted, need at least {MIN_SAMPLES}: {gap_note}"
            + (f"; the longest span free of gaps in both records is t = {lo:.2f}-{hi:.2f} s: identify it alone with "
               f"--window {lo:.2f}:{hi:.2f}" if math.isfinite(lo) else ""))
    theta_d, theta_dot_d, theta_ddot_d, force_d = np.split(dec, 4, axis=1)
    alpha = np.column_stack([np.interp(t_dec, t_ip, alpha_f[:, i]) for i in range(m.n_joints)])
    h = DECIMATION * dt
    alpha_dot = np.gradient(alpha, h, axis=0)
    alpha_ddot = np.gradient(alpha_dot, h, axis=0)
    terms = dynamics.evaluate(m, alpha, alpha_dot)
    x_c = terms.l_c - m.l_c0 + m.rho * theta_d  # eq. 27, physical stretch
    x_c_dot = np.gradient(x_c, h, axis=0)
    x_c_ddot = np.gradient(x_c_dot, h, axis=0)
    return Processed(
        t_s=t_dec, theta=theta_d, theta_dot=theta_dot_d, theta_ddot=theta_ddot_d, force=force_d,
        alpha=alpha, alpha_dot=alpha_dot, alpha_ddot=alpha_ddot,
        x_c=x_c, x_c_dot=x_c_dot, x_c_ddot=x_c_ddot,
        Z=terms.Z, M=terms.M, c=terms.c, g=terms.g,
        cutoff_hz=fc, f_99_hz=f_99, rate_hz=1.0 / h, bandwidth_from=source,
        fast_t_s=t, fast_theta=raw_theta, fast_theta_dot=theta_dot, fast_force=enc[:, nc:],
        fitted=fitted, notes=(gap_note,) if gap_note else (),
    )
