"""A recorded campaign as identification data, and the whole offline pipeline on it (3-X paper §5).

:func:`identify_record` is the one pipeline that ``xneck identify``, ``xneck campaign identification``
and the console's results all run. The MCAP is read with :func:`bridge.archive_read.read_campaign`; encoder angles and applied forces come
from ``/xneck/motor/state`` (``theta_rad``, ``force_applied_N``, ``stamp_s``), α_IP from
``/xneck/camera/alpha_ip`` (``alpha_ip_rad``, ``capture_stamp_s``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from twin.identification.pipeline import (
    DEFAULT_THRESHOLD,
    CampaignData,
    Estimate,
    IdentificationError,
    ParameterReport,
    Processed,
    Provenance,
    Validation,
    identified_params,
    identify_all,
    make_provenance,
    preprocess,
    validate,
)
from twin.model.params import Params

Excitation = Callable[[str, np.ndarray], "np.ndarray | None"]
"""(the campaign's recorded trajectory as JSON, sample times in s) → α^d (rad) at those times, or None.
Given by the caller (:func:`controller.trajectory.recorded_excitation`): trajectories are the
controller's, and the identification must not depend on them."""

MOTOR_TOPIC = "/xneck/motor/state"
CAMERA_TOPIC = "/xneck/camera/alpha_ip"


#: s a record's stamps may go back in receive order (a re-ordered message) before the record is
#: taken for two times mixed: a clock set back while recording.
CLOCK_STEP_BACK_S = 0.5


def _refuse_clock_step_back(path: str | Path, what: str, stamps: np.ndarray) -> None:
    """Raise :class:`IdentificationError` if ``stamps`` (receive order) go back by more than
    :data:`CLOCK_STEP_BACK_S`: sorted, the samples of two moments interleave, and the fit took them
    for one record ("well identified", k(1) 8 % off: audit of 2026-11-27)."""
    if len(stamps) < 2:
        return
    steps = np.diff(stamps)
    i = int(np.argmin(steps))
    if steps[i] < -CLOCK_STEP_BACK_S:
        raise IdentificationError(
            f"{path}: the {what}' clock steps back by {-steps[i]:.3g} s after {what.split()[-1][:-1]} {i} "
            f"(stamp {stamps[i]:.3f} s, then {stamps[i + 1]:.3f} s): a clock set back while recording mixes two "
            "times; identify the part before or after it (the controller aborts a campaign whose bridge clock steps)")


def campaign_data_from_mcap(path: str | Path, excitation: Excitation | None = None) -> CampaignData:
    """Campaign arrays from an archived campaign; with ``excitation``, α^d of its recorded
    trajectory too (the filter cutoff then follows the excitation). Raises
    :class:`IdentificationError` for a missing, truncated or damaged file and for missing or empty
    channels."""
    from bridge.archive import ArchiveError
    from bridge.archive_read import read_campaign

    try:
        camp = read_campaign(path)
    except ArchiveError as exc:
        raise IdentificationError(f"cannot read campaign: {exc}") from None
    missing = [t for t in (MOTOR_TOPIC, CAMERA_TOPIC) if not camp.topics.get(t)]
    if missing:
        have = ", ".join(sorted(camp.topics)) or "none"
        raise IdentificationError(f"{path}: missing channel(s) {', '.join(missing)} (channels present: {have})")
    motor = [m for _, m in camp.topics[MOTOR_TOPIC]]
    frames = [m for _, m in camp.topics[CAMERA_TOPIC]]
    try:
        t = np.array([m.stamp_s for m in motor], dtype=float)
        theta = np.array([m.theta_rad for m in motor], dtype=float)
        force = np.array([m.force_applied_N for m in motor], dtype=float)
        t_ip = np.array([m.capture_stamp_s for m in frames], dtype=float)
        alpha = np.array([m.alpha_ip_rad for m in frames], dtype=float)
    except (AttributeError, ValueError) as exc:
        raise IdentificationError(f"{path}: motor or camera messages are malformed ({exc})") from None
    # A camera frame with a missing joint (CameraAlpha v2: null, read as NaN) is a frame not measured:
    # drop it; the pipeline interpolates across short gaps and refuses long ones (_uniform).
    measured = np.isfinite(alpha).all(axis=1) if alpha.ndim == 2 else np.zeros(len(frames), dtype=bool)
    if not measured.any():
        raise IdentificationError(f"{path}: no camera frame measures every joint")
    t_ip, alpha = t_ip[measured], alpha[measured]
    for what, stamps in (("motor states", t), ("camera frames", t_ip)):
        _refuse_clock_step_back(path, what, stamps)
    # Recorder order is receive order; the identification needs sample order. A lockstep twin
    # re-publishes its state while it waits for a command: keep one sample per time stamp.
    _, order = np.unique(t, return_index=True)
    _, order_ip = np.unique(t_ip, return_index=True)
    campaign = camp.info.get("campaign_id") or Path(path).stem
    trajectory_json = camp.info.get("trajectory")
    alpha_d = None
    if excitation is not None and trajectory_json and len(t) >= 2:
        alpha_d = excitation(trajectory_json, t[order])
    return CampaignData(t[order], theta[order], force[order], t_ip[order_ip], alpha[order_ip], campaign=campaign,
                        excitation_alpha_rad=alpha_d)


class Identification(NamedTuple):
    """Everything one identification produced (3-X paper §5.2-5.6)."""

    data: CampaignData
    processed: Processed
    estimate: dict[str, Estimate]  # by model name, as identify_all returns them
    provenance: Provenance
    params: Params  # the identified parameter set (flagged values kept at base)
    report: ParameterReport  # which estimates replaced a base value, which did not and why
    validation: Validation | None


def identify_record(path: str | Path, base: Params, *, excitation: Excitation | None = None,
                    cutoff_hz: float | None = None, threshold: float = DEFAULT_THRESHOLD,
                    with_validation: bool = True, alpha_hat: bool = True, estimator: str = "auto",
                    sigma: str = "hac", bounded: bool = True, creep_time_s: float | None = None) -> Identification:
    """The offline pipeline on an archived campaign: read, process (filter, decimate), estimate
    (Tables 1-2) with ``estimator`` ("auto", the default: the load-friction fit where the campaign rejects
    eqs. 54-55, else "iv"; or "iv", "ols", "wls", "loadfriction", :func:`identify_all`), ``sigma``
    ("hac" or "white") and physical bounds unless ``bounded`` is False, keep what is well
    identified, and validate (Figs. 4-8). ``creep_time_s``: the line's creep time constant (s) held in
    the load-friction fit (pipeline.identify_variable). Raises :class:`IdentificationError` with the reason."""
    data = campaign_data_from_mcap(path, excitation)
    proc = preprocess(data, base, cutoff_hz)
    est = identify_all(proc, base, threshold=threshold, estimator=estimator, sigma=sigma, bounded=bounded,
                       creep_time_s=creep_time_s)
    prov = make_provenance(f"{data.campaign} ({path})", proc, threshold=threshold, estimates=est)
    new, report, prov = identified_params(base, est, prov)
    val = validate(data, proc, new, est, alpha_hat=alpha_hat) if with_validation else None
    return Identification(data, proc, est, prov, new, report, val)
