"""A recorded campaign as identification data, and the whole offline pipeline on it (3-X paper §5).

:func:`identify_record` is the one pipeline that ``xneck identify``, ``xneck campaign identification``
and the console's results all run. The MCAP is read with :func:`bridge.archive_read.read_campaign`; encoder angles and applied forces come
from ``/xneck/motor/state`` (``theta_rad``, ``force_applied_N``, ``stamp_s``), α_IP from
``/xneck/camera/alpha_ip`` (``alpha_ip_rad``, ``capture_stamp_s``).

What a shared bus may have put in an archive (audit of 2026-11-29):

- One camera. The α_IP of two cameras, recorded interleaved, were fitted as one camera (k(4) 4464
  → 7530 N/m, exit 0): an archive whose α_IP holds more than one ``CameraAlpha.source`` is
  refused, naming them and how many of each, unless one is chosen (``alpha_ip_source``, ``xneck
  identify --alpha-ip-source NAME``). Campaigns now record one camera (server.quality); archives
  of one camera read as before, whatever its source is named ('' for early publishers).
- Strays. One message stamped far off the others (a stray α_IP captured at 1e9 s) got the whole
  record refused for a clock set back. A message whose stamp lies more than
  :data:`CLOCK_STEP_BACK_S` from the median of the :data:`STRAY_WINDOW` received on either side
  of it is dropped, counted and said (:attr:`CampaignData.notes`), as is an α_IP captured after
  its publication (:func:`bridge.bus.check_camera_alpha_stamps`, which the recorder now applies).
  A clock set back mid-record moves many messages at once, which that median follows: it is still
  refused (:func:`_refuse_clock_step_back`), and so is a record with more strays than
  :data:`STRAY_FRACTION_MAX` of its messages (at least :data:`STRAY_COUNT_MIN` pass).
- One bridge run. States of two bridge runs (``MotorState.bridge`` and ``.epoch``: a second
  bridge on the bus, or one restarted), recorded interleaved, were fitted as one record (k −14 %,
  λ +59 %, exit 0: audit of 2026-11-30); the recorder keeps every run's states until the
  campaign's first command names its run (server.quality), so a real archive may hold another
  run's before the campaign's. The states read are those of the campaign's run
  (:func:`_one_bridge_run`): the run the campaign controller's commands (``ForceCommand.epoch``;
  the controller that sent most of the archive's commands: until the recorder follows it, it keeps
  any controller's) answer, else,
  if no command names a run, the run with the most states, provided no other run's state was
  received within its span (first to last state, the recorder's receive time: one clock). The other
  runs' states are dropped, counted and said (:attr:`CampaignData.notes`). Refused: the commands
  answering several runs (a bridge restarted mid-campaign: each run's encoders have their own
  zero), or, with no command naming one, two runs received interleaved (which is the campaign's
  cannot be told).
"""

from __future__ import annotations

from array import array
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

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
MOTOR_COMMAND_TOPIC = "/xneck/motor/command"  # whose epochs name the campaign's bridge run
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


#: messages received on either side of each one whose median stamp it is compared with (module
#: docstring): a run of at most this many strays is told from the record around it.
STRAY_WINDOW = 5
#: at most this fraction of a record's messages, or :data:`STRAY_COUNT_MIN`, are dropped as strays;
#: more is a damaged record or clocks mixed, refused.
STRAY_FRACTION_MAX = 0.01
STRAY_COUNT_MIN = 3
SOURCES_NAMED_MAX = 8  # cameras an error names (an archive is untrusted input)


def _sources_text(counts: Counter[str]) -> str:
    named = [f"{name[:64]!r} ({n} message{'' if n == 1 else 's'})" for name, n in counts.most_common(SOURCES_NAMED_MAX)]
    more = len(counts) - len(named)
    return ", ".join(named) + (f" and {more} more" if more > 0 else "")


def _one_camera(path: str | Path, frames: list, source: str | None) -> list:
    """The α_IP of one camera (module docstring): ``source``'s, else the only one recorded."""
    counts = Counter(m.source for m in frames)
    if source is None:
        if len(counts) > 1:
            raise IdentificationError(
                f"{path}: {CAMERA_TOPIC} holds the α_IP of {len(counts)} cameras: {_sources_text(counts)}. "
                "Two cameras on one bus were recorded interleaved, and fitted as one they give wrong parameters: "
                "choose the campaign's camera (xneck identify --alpha-ip-source NAME)")
        return frames
    if source not in counts:
        raise IdentificationError(f"{path}: no α_IP of {source[:64]!r} in {CAMERA_TOPIC}; it holds {_sources_text(counts)}")
    return [m for m in frames if m.source == source]


RUNS_NAMED_MAX = 4  # bridge runs an error or a note names (an archive is untrusted input)


class _Run:
    """One bridge run's angles and forces, in the order its states were read."""

    def __init__(self, width: int) -> None:
        self.width = width
        self.theta_rad, self.force_N = array("d"), array("d")
        self.rows = 0
        self.ragged = ""  # why its states cannot be one array ('' if they can)


class MotorStates:
    """An archive's motor states as columns, folded as they are read (``read_campaign(fold=...)``):
    decoded one by one, 577 s of them had taken 565 MB of Python objects in ``xneck identify``
    (audit of 2026-11-30). Each bridge run's angles and forces are kept apart: a run whose states
    do not all carry as many motors is refused only if it is the campaign's (another's are dropped
    anyway, as before)."""

    def __init__(self, path: str | Path) -> None:
        self.path = path
        self.log_ns, self.stamp_s = array("Q"), array("d")  # MCAP log times are unsigned 64-bit
        self.code, self.row = array("q"), array("q")  # per state: its run, its row in that run's arrays
        self.runs: dict[tuple[str, str], int] = {}
        self._runs: list[_Run] = []

    def add(self, log_ns: int, m: Any) -> None:
        from bridge.archive_read import FoldError
        from bridge.bus import MotorState

        if not isinstance(m, MotorState):
            raise FoldError(IdentificationError(
                f"{self.path}: motor or camera messages are malformed (a {type(m).__name__} on {MOTOR_TOPIC})"))
        code = self.runs.setdefault((m.bridge, m.epoch), len(self.runs))
        if code == len(self._runs):
            self._runs.append(_Run(len(m.theta_rad)))
        r = self._runs[code]
        if len(m.theta_rad) != r.width or len(m.force_applied_N) != r.width:
            r.ragged = r.ragged or (f"{self.path}: motor or camera messages are malformed (a motor state of "
                                    f"{len(m.theta_rad)} angles and {len(m.force_applied_N)} forces, its run's "
                                    f"first had {r.width})")
            row = -1
        else:
            r.theta_rad.extend(m.theta_rad)
            r.force_N.extend(m.force_applied_N)
            row, r.rows = r.rows, r.rows + 1
        self.log_ns.append(log_ns)
        self.stamp_s.append(m.stamp_s)
        self.code.append(code)
        self.row.append(row)

    def __len__(self) -> int:
        return len(self.stamp_s)

    def ordered(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[tuple[str, str]]]:
        """(order, log_time_ns, stamp_s, run, names): the states in the order ``read_campaign``
        keeps a topic (log time, ties in file order; ``order``: their places as read), each one's
        run numbered as first seen in that order, ``names[run]`` its (bridge, epoch)."""
        log = np.frombuffer(self.log_ns, dtype=np.uint64) if len(self) else np.zeros(0, np.uint64)
        order = np.argsort(log, kind="stable")
        code = np.frombuffer(self.code, dtype=np.int64)[order] if len(self) else np.zeros(0, np.int64)
        _, first = np.unique(code, return_index=True)
        seen = np.unique(code)[np.argsort(first, kind="stable")]  # the codes, first seen first
        renumber = np.empty(len(self._runs), dtype=np.int64)
        renumber[seen] = np.arange(len(seen))
        by_code = {k: name for name, k in self.runs.items()}
        stamp = np.frombuffer(self.stamp_s, dtype=float)[order] if len(self) else np.zeros(0)
        return order, log[order], stamp, renumber[code], [by_code[int(k)] for k in seen]

    def columns(self, places: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(theta_rad (N, n), force_N (N, n)) of the states at ``places`` (as read), all of one run;
        :class:`IdentificationError` if that run's states do not all carry as many motors."""
        if len(places) == 0:
            return np.zeros((0, 0)), np.zeros((0, 0))
        r = self._runs[int(self.code[int(places[0])])]
        if r.ragged:
            raise IdentificationError(r.ragged)
        rows = np.frombuffer(self.row, dtype=np.int64)[places]
        theta = np.frombuffer(r.theta_rad, dtype=float).reshape(r.rows, r.width)[rows]
        return theta, np.frombuffer(r.force_N, dtype=float).reshape(r.rows, r.width)[rows]


class CommandRuns:
    """How many commands each (sender, epoch) sent, folded as they are read: all
    :func:`_one_bridge_run` needs of them. :meth:`in_order` gives them as they first came in log
    time (ties as read): the order a tie between senders is broken in, as before they were folded."""

    def __init__(self) -> None:
        self.counts: Counter[tuple[str, str]] = Counter()
        self.first: dict[tuple[str, str], tuple[int, int]] = {}
        self._n = 0

    def add(self, log_ns: int, c: Any) -> None:
        sender, epoch = getattr(c, "sender", None), getattr(c, "epoch", None)
        self._n += 1
        if isinstance(sender, str) and isinstance(epoch, str):
            key = (sender, epoch)
            self.counts[key] += 1
            self.first[key] = min(self.first.get(key, (log_ns, self._n)), (log_ns, self._n))

    def in_order(self) -> Counter[tuple[str, str]]:
        return Counter({k: self.counts[k] for k in sorted(self.counts, key=self.first.__getitem__)})


def _runs_text(runs: dict[tuple[str, str], np.ndarray], stamp_s: np.ndarray) -> str:
    """``runs`` (bridge, epoch) → the indices of their states in ``stamp_s``, most states first,
    e.g. "bridge 'b' run 'e' (3000 states, stamped 0-6 s)"."""
    ordered = sorted(runs.items(), key=lambda kv: -len(kv[1]))
    named = [f"bridge {bridge[:64]!r} run {epoch[:64]!r} ({len(idx)} state{'' if len(idx) == 1 else 's'}, "
             f"stamped {stamp_s[idx[0]]:.6g}-{stamp_s[idx[-1]]:.6g} s)"
             for (bridge, epoch), idx in ordered[:RUNS_NAMED_MAX]]
    more = len(ordered) - len(named)
    return ", ".join(named) + (f" and {more} more" if more > 0 else "")


def _one_bridge_run(path: str | Path, log_ns: np.ndarray, stamp_s: np.ndarray, run: np.ndarray,
                    names: list[tuple[str, str]], commands: Counter[tuple[str, str]],
                    notes: list[str]) -> np.ndarray:
    """The indices of the motor states (``log_ns``, ``stamp_s``, ``run``: in receive order; ``names``:
    (bridge, epoch) of each run, first seen first) of the campaign's bridge run (module docstring,
    "One bridge run"); a note for the other runs' states dropped, or :class:`IdentificationError`
    when which run is the campaign's cannot be told. ``commands``: how many commands each
    (sender, epoch) sent, first sent first (:meth:`CommandRuns.in_order`)."""
    runs = {name: np.flatnonzero(run == k) for k, name in enumerate(names)}
    if len(runs) <= 1:
        return np.arange(len(stamp_s))
    # The campaign's controller is the sender of most commands: until the recorder follows it, it
    # keeps every controller's, and another's few, answering its own bridge, had the record refused
    # as one restarted mid-campaign (review of session 49).
    senders: Counter[str] = Counter()
    for (sender, _), n in commands.items():
        senders[sender] += n
    own = senders.most_common(1)[0][0] if senders else ""
    if len(senders) > 1:
        strays = {s: n for s, n in senders.items() if s != own}
        notes.append(f"{sum(strays.values())} command(s) of {len(strays)} other controller(s) "
                     f"({', '.join(repr(s[:64]) for s in list(strays)[:3])}{', …' if len(strays) > 3 else ''}) not "
                     f"counted in telling the campaign's bridge run: the campaign's is {own[:64]!r}, the sender of "
                     f"most ({senders[own]})")
    answered = Counter({epoch: n for (sender, epoch), n in commands.items() if sender == own})
    named = [r for r in runs if answered.get(r[1], 0) > 0]
    if len(named) > 1:
        raise IdentificationError(
            f"{path}: the campaign's commands answer {len(named)} bridge runs: "
            f"{_runs_text({r: runs[r] for r in named}, stamp_s)}. Its bridge restarted mid-campaign (each run's encoders "
            "have their own zero) or two bridges obeyed its controller: fitted as one record they give wrong "
            "parameters; record the campaign again")
    if named:
        chosen, why = named[0], "the run the campaign's commands answer"
    else:
        chosen = max(runs, key=lambda r: len(runs[r]))
        first, last = log_ns[runs[chosen][0]], log_ns[runs[chosen][-1]]
        within = {r: v for r, v in runs.items()
                  if r != chosen and bool(np.any((log_ns[v] > first) & (log_ns[v] < last)))}
        if within:
            raise IdentificationError(
                f"{path}: {MOTOR_TOPIC} holds the states of {len(runs)} bridge runs received interleaved: "
                f"{_runs_text(runs, stamp_s)}, and no command names the campaign's. Two bridges on one bus were recorded "
                "together, and fitted as one record they give wrong parameters")
        why = "the run with the most states, none of another received within its span; no command names a run"
    others = {r: v for r, v in runs.items() if r != chosen}
    dropped = sum(len(v) for v in others.values())
    notes.append(f"{dropped} motor state(s) of {len(others)} other bridge run(s) dropped: "
                 f"{_runs_text(others, stamp_s)}; "
                 f"kept bridge {chosen[0][:64]!r} run {chosen[1][:64]!r} ({len(runs[chosen])} states: {why})")
    return runs[chosen]


def _strays(stamps: np.ndarray) -> np.ndarray:
    """Which of ``stamps`` (receive order) lie more than :data:`CLOCK_STEP_BACK_S` from the median
    of the :data:`STRAY_WINDOW` messages on either side of each (and itself)."""
    w = STRAY_WINDOW
    if len(stamps) <= 2 * w:
        return np.zeros(len(stamps), dtype=bool)
    windows = np.lib.stride_tricks.sliding_window_view(np.pad(stamps, w, constant_values=np.nan), 2 * w + 1)
    return np.abs(stamps - np.nanmedian(windows, axis=1)) > CLOCK_STEP_BACK_S


def _drop_strays(path: str | Path, what: str, stamps: np.ndarray, notes: list[str]) -> np.ndarray:
    """The mask of ``stamps`` to keep (module docstring); a note for those dropped, or
    :class:`IdentificationError` when they are more than a stray or two."""
    stray = _strays(stamps)
    n = int(stray.sum())
    if n == 0:
        return ~stray
    allowed = max(STRAY_COUNT_MIN, int(STRAY_FRACTION_MAX * len(stamps)))
    shown = ", ".join(f"{x:.6g}" for x in stamps[stray][:3]) + (", …" if n > 3 else "")
    if n > allowed:
        raise IdentificationError(
            f"{path}: {n} of {len(stamps)} {what} are stamped far off the others (more than {CLOCK_STEP_BACK_S} s "
            f"from the median of the {2 * STRAY_WINDOW} received around each; stamps {shown} s): more than "
            f"{allowed} strays, a damaged record or two clocks mixed")
    notes.append(f"{n} {what[:-1]}(s) stamped far off the others dropped: stamp {shown} s (more than "
                 f"{CLOCK_STEP_BACK_S} s from the median of the {2 * STRAY_WINDOW} received around each: a stray "
                 "publisher's or a damaged message)")
    return ~stray


def campaign_data_from_mcap(path: str | Path, excitation: Excitation | None = None, *,
                            alpha_ip_source: str | None = None) -> CampaignData:
    """Campaign arrays from an archived campaign; with ``excitation``, α^d of its recorded
    trajectory too (the filter cutoff then follows the excitation). ``alpha_ip_source``: the
    camera (``CameraAlpha.source``) whose α_IP is read, needed when the archive holds several;
    stray messages and the states of another bridge run than the campaign's are dropped and said
    in the data's ``notes`` (module docstring). Raises :class:`IdentificationError` for a missing,
    truncated or damaged file, for missing or empty channels, for the α_IP of several cameras none
    chosen, for states of several bridge runs the campaign's cannot be told from, and for a clock
    set back."""
    from bridge.archive import ArchiveError
    from bridge.archive_read import read_campaign
    from bridge.bus import CAPTURE_AFTER_PUBLICATION_MAX_S

    states, commands = MotorStates(path), CommandRuns()
    try:
        camp = read_campaign(path, keys=(CAMERA_TOPIC,), fold={MOTOR_TOPIC: states.add, MOTOR_COMMAND_TOPIC: commands.add})
    except ArchiveError as exc:
        raise IdentificationError(f"cannot read campaign: {exc}") from None
    missing = [t for t, n in ((MOTOR_TOPIC, len(states)), (CAMERA_TOPIC, len(camp.messages(CAMERA_TOPIC)))) if not n]
    if missing:
        have = ", ".join(sorted(camp.counts)) or "none"
        raise IdentificationError(f"{path}: missing channel(s) {', '.join(missing)} (channels present: {have})")
    notes: list[str] = []
    try:
        order, log_ns, stamps, run, names = states.ordered()
        chosen = _one_bridge_run(path, log_ns, stamps, run, names, commands.in_order(), notes)
        frames = _one_camera(path, [m for _, m in camp.messages(CAMERA_TOPIC)], alpha_ip_source)
        # Captured after its publication: refused by the recorder since, possibly in an older archive.
        late = [m for m in frames if m.capture_stamp_s > m.stamp_s + CAPTURE_AFTER_PUBLICATION_MAX_S]
        if late:
            notes.append(f"{len(late)} camera frame(s) captured after its publication dropped: capture "
                         f"{late[0].capture_stamp_s:.6g} s, published {late[0].stamp_s:.6g} s"
                         f"{', …' if len(late) > 1 else ''} (an exposure ends before the message that reports it)")
            frames = [m for m in frames if m.capture_stamp_s <= m.stamp_s + CAPTURE_AFTER_PUBLICATION_MAX_S]
        t = stamps[chosen]
        theta, force = states.columns(order[chosen])
        t_ip = np.array([m.capture_stamp_s for m in frames], dtype=float)
        alpha = np.array([m.alpha_ip_rad for m in frames], dtype=float)
    except IdentificationError:
        raise
    except (AttributeError, ValueError) as exc:
        raise IdentificationError(f"{path}: motor or camera messages are malformed ({exc})") from None
    keep = _drop_strays(path, "motor states", t, notes)
    t, theta, force = t[keep], theta[keep], force[keep]
    keep = _drop_strays(path, "camera frames", t_ip, notes)
    t_ip, alpha = t_ip[keep], alpha[keep]
    # A camera frame with a missing joint (CameraAlpha v2: null, read as NaN) is a frame not measured:
    # drop it; the pipeline interpolates across gaps, not fitting their instants, and refuses those beyond 2 s.
    measured = np.isfinite(alpha).all(axis=1) if alpha.ndim == 2 else np.zeros(len(t_ip), dtype=bool)
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
                        excitation_alpha_rad=alpha_d, notes=tuple(notes), kind=str(camp.info.get("kind", "")))


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
                    sigma: str = "hac", bounded: bool = True, creep_time_s: float | None = None,
                    alpha_ip_source: str | None = None,
                    window_s: tuple[float, float] | None = None) -> Identification:
    """The offline pipeline on an archived campaign: read, process (filter, decimate), estimate
    (Tables 1-2) with ``estimator`` ("auto", the default: where the campaign rejects eqs. 54-55, the output
    error if the line's damping is light and no creep time is held, else the load-friction fit; "iv" where
    it keeps them; or "iv", "ols", "wls", "loadfriction", "outputerror", :func:`identify_all`), ``sigma``
    ("hac" or "white") and physical bounds unless ``bounded`` is False, keep what is well
    identified, and validate (Figs. 4-8). ``creep_time_s``: the line's creep time constant (s) held in
    the load-friction fit (pipeline.identify_variable). ``alpha_ip_source``: the camera read
    (:func:`campaign_data_from_mcap`). ``window_s``: fit only the record between these times (s,
    :meth:`CampaignData.window`), e.g. the span without gaps an error named. Raises
    :class:`IdentificationError` with the reason."""
    data = campaign_data_from_mcap(path, excitation, alpha_ip_source=alpha_ip_source)
    if window_s is not None:
        data = data.window(*window_s)
    proc = preprocess(data, base, cutoff_hz)
    est = identify_all(proc, base, threshold=threshold, estimator=estimator, sigma=sigma, bounded=bounded,
                       creep_time_s=creep_time_s)
    prov = make_provenance(f"{data.campaign} ({path})", proc, threshold=threshold, estimates=est)
    new, report, prov = identified_params(base, est, prov)
    val = validate(data, proc, new, est, alpha_hat=alpha_hat) if with_validation else None
    return Identification(data, proc, est, prov, new, report, val)
