"""Desired joint trajectories α^d(t) for the X-joint neck, and their validation before anything moves.

A trajectory is a list of joint configurations (waypoints) joined by cycloidal point-to-point
motions, as in the 3-X paper (§5.2.2 and §7: "all desired joint configurations are connected with
cycloïdal functions"), with an optional hold (dwell) at each waypoint. Its timeline is::

    dwell_0 | move 0→1 | dwell_1 | move 1→2 | ... | move K-2→K-1 | dwell_{K-1}

Units: SI inside (rad, s); degrees only at the edges (user files, ``to_dict``, error messages).
Indices in messages: waypoints and segments count from 0 (they index the arrays of a user file);
joints count from 1 at the base (α1, α2, α3), as in the paper.

Built-in trajectories: :func:`identification_trajectory` (§5.2.2) and
:func:`control_test_trajectory` (§7, Fig. 10); user files via :func:`load_trajectory`::

    {"name": "nod", "waypoints_deg": [[0, 0, 0], [20, 10, 0], [0, 0, 0]],
     "durations_s": [2.0, 2.0], "dwell_s": 0.5}

A trajectory may also carry a **pretension** schedule (``pretension_N``, one value per waypoint,
N ≥ 0, default 0): tension added to the law's floor t_min (eq. 65) at each waypoint, joined by the
same cycloids as the joints. Raising every cable's floor raises the internal force of the
redundant cables (the null space of Z, eq. 63) without moving the neck: identification
excitations use it to sweep the cables over their tension range (eqs. 54-57), which the joint
motion alone barely does. It starts and ends at 0, so taking over and handing back stay bumpless.

:func:`validate` rejects a trajectory outside the joint limits, too fast, accelerating too hard,
or (given the controller's ``force_check``) needing forces outside [f_min, f_max]; the
:class:`TrajectoryError` names the waypoint or segment and the reason.
"""

from __future__ import annotations

import json
import math
import os
import tomllib
import unicodedata
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, cast

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from bridge import toml_text
from bridge.small_file import read_input_file

__all__ = [
    "CONTROL_TEST_WAYPOINTS_DEG",
    "CYCLOID_PEAK_ACCELERATION",
    "CYCLOID_PEAK_VELOCITY",
    "IDENTIFICATION_AMPLITUDES_DEG",
    "NAMED_TRAJECTORIES",
    "ForceCheck",
    "Trajectory",
    "TrajectoryError",
    "TrajectoryFile",
    "TrajectoryLimits",
    "TrajectorySample",
    "approach",
    "approach_duration_s",
    "control_test_trajectory",
    "cycloid",
    "identification_trajectory",
    "load_trajectory",
    "repeated",
    "trajectory_by_name",
    "trajectory_from_json",
    "trajectory_json_schema",
    "validate",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

ForceCheck = Callable[[FloatArray, FloatArray, FloatArray, FloatArray], tuple[BoolArray, str]]
"""(α, α̇, α̈, pretension) on a time grid, each (T, N) in rad, rad/s, rad/s², the pretension (T,) in
N (zeros for a trajectory without one) -> (ok per sample (T,), reason).

Supplied by the controller: forces after tension distribution (§6.2, Eqs. 63-65) within
[f_min, f_max] along the nominal path."""

_TWO_PI = 2.0 * math.pi

# Peaks of s'(τ) = 1 - cos 2πτ and s''(τ) = 2π sin 2πτ: a cycloidal move of amplitude Δ over T
# seconds peaks at 2|Δ|/T (τ = 1/2) and 2π|Δ|/T² (τ = 1/4), so limits are checked exactly.
CYCLOID_PEAK_VELOCITY = 2.0
CYCLOID_PEAK_ACCELERATION = _TWO_PI


#: The shortest move (s) a trajectory may hold: half a 500 Hz control period. Shorter ones are no
#: move any loop tracks, and their cycloid's acceleration 2π·Δ/T² overflows.
SEGMENT_MIN_S = 1e-3


class TrajectoryError(ValueError):
    """A trajectory is malformed or unsafe; the message names the waypoint or segment and why."""


class TrajectorySample(NamedTuple):
    """Desired joint state; each array is ``t.shape + (N,)`` (rad, rad/s, rad/s²)."""

    alpha: FloatArray
    alpha_dot: FloatArray
    alpha_ddot: FloatArray


def cycloid(tau: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Cycloidal profile s(τ) = τ − sin(2πτ)/(2π) and its derivatives ds/dτ, d²s/dτ².

    Rest-to-rest: s(0) = 0, s(1) = 1, and s', s'' vanish at both ends, so joining moves at
    waypoints keeps α^d, α̇^d and α̈^d continuous (no force jumps in the feed-forward of Eq. 66).
    τ is clipped to [0, 1] (before: at the start, after: at the end, both at rest).
    """
    tau = np.clip(np.asarray(tau, dtype=np.float64), 0.0, 1.0)
    phase = _TWO_PI * tau
    inside = (tau > 0.0) & (tau < 1.0)
    # sin(2π) is -2.4e-16, not 0: force the end values so holds are exactly at rest.
    s = np.where(tau >= 1.0, 1.0, tau - np.sin(phase) / _TWO_PI)
    ds = np.where(inside, 1.0 - np.cos(phase), 0.0)
    dds = np.where(inside, _TWO_PI * np.sin(phase), 0.0)
    return s, ds, dds


def cycloid_at(tau: float) -> tuple[float, float, float]:
    """:func:`cycloid` of one τ in plain floats (the controller's per-tick path, where numpy's
    per-call overhead is most of the cost); the same values."""
    tau = min(max(tau, 0.0), 1.0)
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    phase = _TWO_PI * tau
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    return tau - math.sin(phase) / _TWO_PI, 1.0 - math.cos(phase), _TWO_PI * math.sin(phase)


def _deg(values_rad: ArrayLike) -> str:
    """Format joint angles (rad) for a message, in degrees."""
    return "[" + ", ".join(f"{v:.4g}" for v in np.rad2deg(np.atleast_1d(values_rad))) + "]°"


def _per_item(value: ArrayLike, count: int, what: str) -> FloatArray:
    """Broadcast a scalar or check a list of ``count`` values (durations, dwells)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        return np.full(count, float(arr))
    if arr.shape != (count,):
        got = arr.shape[0] if arr.ndim == 1 else f"shape {arr.shape}"
        raise TrajectoryError(f"expected {count} {what} value(s), got {got}")
    return arr.copy()


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Waypoints joined by cycloidal moves, with a hold at each waypoint (immutable).

    Args:
        waypoints_rad: joint configurations α_k, shape (K, N), K ≥ 1, N ≥ 1 joints (rad).
        durations_s: duration of each move k → k+1, shape (K-1,) or a scalar for all (s, > 0).
        dwell_s: hold at each waypoint after arriving, shape (K,) or a scalar for all (s, ≥ 0);
            the hold at waypoint 0 is an initial rest, the one at the last waypoint a final rest.
        name: label recorded with the campaign.
        pretension_N: tension added to the law's floor t_min at each waypoint, shape (K,) or a
            scalar for all (N, ≥ 0; default none): module docstring.

    Structural problems (empty, non-finite, wrong lengths, non-positive durations) raise
    :class:`TrajectoryError` here; physical limits are checked by :func:`validate`.
    """

    waypoints_rad: FloatArray
    durations_s: FloatArray
    dwell_s: FloatArray = field(default_factory=lambda: np.zeros(0))
    name: str = "trajectory"
    pretension_N: FloatArray = field(default_factory=lambda: np.zeros(0))
    _arrive: FloatArray = field(init=False, repr=False)
    _has_pretension: bool = field(init=False, repr=False)
    _depart: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        w = np.array(self.waypoints_rad, dtype=np.float64)
        if w.ndim != 2:
            raise TrajectoryError(f"waypoints must be a (K, N) array of joint angles, got shape {w.shape}")
        k, n = w.shape
        if k == 0:
            raise TrajectoryError("empty trajectory: at least one waypoint is needed")
        if n == 0:
            raise TrajectoryError("waypoints have no joints (shape (K, 0))")
        for i in np.flatnonzero(~np.isfinite(w).all(axis=1)):
            raise TrajectoryError(f"waypoint {i} has a non-finite value: {_deg(w[i])}")
        durations = _per_item(self.durations_s, k - 1, "segment duration (one per move, K-1)")
        for i in np.flatnonzero(~(np.isfinite(durations) & (durations > 0.0))):
            raise TrajectoryError(
                f"segment {i} (waypoint {i} → {i + 1}) has a non-positive or non-finite duration "
                f"{durations[i]} s"
            )
        # A move of 1e-200 s, even one of zero length, made the force check's samples NaN (0·∞)
        # and its refusal read "needs nan N" (audit of 2026-11-27); no loop tracks a move that short.
        for i in np.flatnonzero(durations < SEGMENT_MIN_S):
            raise TrajectoryError(
                f"segment {i} (waypoint {i} → {i + 1}) lasts {durations[i]:.3g} s, under the shortest move "
                f"{SEGMENT_MIN_S * 1e3:g} ms (half a control period at 500 Hz); use a dwell to wait"
            )
        dwell = np.zeros(k) if np.size(self.dwell_s) == 0 else _per_item(self.dwell_s, k, "dwell (one per waypoint)")
        for i in np.flatnonzero(~(np.isfinite(dwell) & (dwell >= 0.0))):
            raise TrajectoryError(f"waypoint {i} has a negative or non-finite dwell {dwell[i]} s")
        pre = np.zeros(k) if np.size(self.pretension_N) == 0 else _per_item(self.pretension_N, k, "pretension (one per waypoint)")
        for i in np.flatnonzero(~(np.isfinite(pre) & (pre >= 0.0))):
            raise TrajectoryError(f"waypoint {i} has a negative or non-finite pretension {pre[i]} N")
        # Departure from waypoint k = Σ_{j≤k} dwell_j + Σ_{j<k} T_j; the last one is the end.
        with np.errstate(over="ignore"):
            depart = np.cumsum(dwell + np.append(0.0, durations))
        if not np.isfinite(depart[-1]):  # finite parts, an overflowing sum: a 500 in previews (audit of 2026-11-27)
            raise TrajectoryError(f"the trajectory's total duration (moves and dwells) is not finite: {depart[-1]} s")
        arrive = depart - dwell
        for name, arr in (("waypoints_rad", w), ("durations_s", durations), ("dwell_s", dwell),
                          ("pretension_N", pre), ("_arrive", arrive), ("_depart", depart)):
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "_has_pretension", bool(np.any(pre > 0.0)))  # read every controller tick

    # -- shape and timing -------------------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return int(self.waypoints_rad.shape[1])

    @property
    def n_waypoints(self) -> int:
        return int(self.waypoints_rad.shape[0])

    @property
    def n_segments(self) -> int:
        return self.n_waypoints - 1

    @property
    def duration_s(self) -> float:
        """Total duration including all dwells (s); after it, the last waypoint is held."""
        return float(self._depart[-1])

    def waypoint_times(self) -> FloatArray:
        """Arrival time at each waypoint, shape (K,) (s); waypoint 0 is at t = 0."""
        return self._arrive

    def segment_times(self) -> FloatArray:
        """Start and end of each move, shape (K-1, 2) (s)."""
        return np.stack([self._depart[:-1], self._arrive[1:]], axis=1)

    def segment_at(self, t: float) -> tuple[str, int]:
        """Where the timeline is at ``t``: ``("segment", i)`` while moving, else ``("hold", k)``."""
        k = int(np.searchsorted(self._arrive, t, side="right")) - 1
        k = max(k, 0)
        if t < self._depart[k] or k == self.n_waypoints - 1:
            return ("hold", k)
        return ("segment", k)

    def describe_time(self, t: float) -> str:
        kind, i = self.segment_at(t)
        if kind == "segment":
            return f"segment {i} (waypoint {i} → {i + 1})"
        return f"hold at waypoint {i}"

    # -- peaks, exact for cycloids ----------------------------------------------------------
    def segment_deltas(self) -> FloatArray:
        """Δα of each move, shape (K-1, N) (rad)."""
        return np.diff(self.waypoints_rad, axis=0)

    def segment_peak_velocity(self) -> FloatArray:
        """Peak |α̇| of each move per joint, 2|Δ|/T, shape (K-1, N) (rad/s)."""
        return CYCLOID_PEAK_VELOCITY * np.abs(self.segment_deltas()) / self.durations_s[:, None]

    def segment_peak_acceleration(self) -> FloatArray:
        """Peak |α̈| of each move per joint, 2π|Δ|/T², shape (K-1, N) (rad/s²)."""
        return CYCLOID_PEAK_ACCELERATION * np.abs(self.segment_deltas()) / self.durations_s[:, None] ** 2

    # -- sampling ---------------------------------------------------------------------------
    def sample(self, t: ArrayLike) -> TrajectorySample:
        """α^d, α̇^d, α̈^d at times ``t`` (s), vectorised; arrays of shape ``t.shape + (N,)``.

        Before t = 0 the first waypoint is held, after :attr:`duration_s` the last one.
        """
        t = np.asarray(t, dtype=np.float64)
        if not np.all(np.isfinite(t)):
            raise TrajectoryError("sample times must be finite")
        w = self.waypoints_rad
        if self.n_segments == 0:
            alpha = np.broadcast_to(w[0], t.shape + w.shape[1:]).copy()
            return TrajectorySample(alpha, np.zeros_like(alpha), np.zeros_like(alpha))
        # Segment i is the last one whose departure is ≤ t; τ outside [0, 1] means a hold.
        seg = np.clip(np.searchsorted(self._depart[:-1], t, side="right") - 1, 0, self.n_segments - 1)
        period = self.durations_s[seg]
        tau = (t - self._depart[seg]) / period
        s, ds, dds = cycloid(tau)
        start, end = w[seg], w[seg + 1]
        delta = end - start
        # At τ ≥ 1 return the next waypoint itself: start + Δ can be off by an ulp.
        alpha = np.where((tau >= 1.0)[..., None], end, start + delta * s[..., None])
        alpha_dot = delta * (ds / period)[..., None]
        alpha_ddot = delta * (dds / period**2)[..., None]
        return TrajectorySample(alpha, alpha_dot, alpha_ddot)

    @property
    def has_pretension(self) -> bool:
        """Whether any waypoint raises the tension floor (module docstring)."""
        return self._has_pretension

    def segment_peak_pretension_rate(self) -> FloatArray:
        """Peak |dP/dt| of each move, 2|ΔP|/T, shape (K-1,) (N/s)."""
        return CYCLOID_PEAK_VELOCITY * np.abs(np.diff(self.pretension_N)) / self.durations_s

    def pretension(self, t: ArrayLike) -> FloatArray:
        """The pretension P(t) (N) at times ``t`` (s), vectorised, shape ``t.shape``: the waypoints'
        values joined by the joints' cycloids, held before 0 and after the end."""
        t = np.asarray(t, dtype=np.float64)
        P = self.pretension_N
        if self.n_segments == 0 or not self.has_pretension:
            return np.full(t.shape, float(P[0]))
        seg = np.clip(np.searchsorted(self._depart[:-1], t, side="right") - 1, 0, self.n_segments - 1)
        s, _, _ = cycloid((t - self._depart[seg]) / self.durations_s[seg])
        return np.where(s >= 1.0, P[seg + 1], P[seg] + (P[seg + 1] - P[seg]) * s)

    def pretension_at(self, t: float) -> float:
        """:meth:`pretension` at one time ``t`` (s), a plain float (the controller's tick)."""
        P = self.pretension_N
        if self.n_segments == 0 or not self.has_pretension:
            return float(P[0])
        seg = min(max(int(np.searchsorted(self._depart[:-1], t, side="right")) - 1, 0), self.n_segments - 1)
        s = cycloid_at((t - float(self._depart[seg])) / float(self.durations_s[seg]))[0]
        return float(P[seg + 1]) if s >= 1.0 else float(P[seg] + (P[seg + 1] - P[seg]) * s)

    def sample_at(self, t: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        """:meth:`sample` at one time ``t`` (s): α^d, α̇^d, α̈^d, each (N,), the same values; the
        controller samples one time per tick, where the vectorised form's overhead dominates."""
        if not math.isfinite(t):
            raise TrajectoryError("sample times must be finite")
        w = self.waypoints_rad
        if self.n_segments == 0:
            return w[0].copy(), np.zeros(w.shape[1]), np.zeros(w.shape[1])
        seg = min(max(int(np.searchsorted(self._depart[:-1], t, side="right")) - 1, 0), self.n_segments - 1)
        period = float(self.durations_s[seg])
        tau = (t - float(self._depart[seg])) / period
        s, ds, dds = cycloid_at(tau)
        start, end = w[seg], w[seg + 1]
        delta = end - start
        alpha = end.copy() if tau >= 1.0 else start + delta * s
        return alpha, delta * (ds / period), delta * (dds / period**2)

    def time_grid(self, dt_s: float = 0.01) -> FloatArray:
        """Times 0, dt, 2dt, ... plus every waypoint arrival/departure and the end (s), sorted."""
        if not (math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s must be positive, got {dt_s}")
        grid = np.arange(0.0, self.duration_s, dt_s)
        return np.unique(np.concatenate([grid, self._arrive, self._depart]))

    # -- serialisation (degrees at this edge) ----------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form, the same schema as a user file (angles in degrees).

        Degrees are rounded to 1e-9° so that deg → rad → deg round trips print cleanly.
        """
        out: dict[str, Any] = {
            "name": self.name,
            "waypoints_deg": np.round(np.rad2deg(self.waypoints_rad), 9).tolist(),
            "durations_s": self.durations_s.tolist(),
            "dwell_s": self.dwell_s.tolist(),
        }
        if self.has_pretension:  # files without one stay as they were
            out["pretension_N"] = self.pretension_N.tolist()
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Trajectory:
        """Inverse of :meth:`to_dict` (same as :func:`load_trajectory` on a mapping)."""
        return load_trajectory(data)

    @classmethod
    def from_degrees(
        cls, waypoints_deg: ArrayLike, durations_s: ArrayLike, dwell_s: ArrayLike = 0.0, name: str = "trajectory",
        pretension_N: ArrayLike = 0.0,
    ) -> Trajectory:
        # __post_init__ checks and converts durations, dwells and pretensions (scalars or arrays)
        return cls(np.deg2rad(np.asarray(waypoints_deg, dtype=np.float64)), cast(FloatArray, durations_s),
                   cast(FloatArray, dwell_s), name, cast(FloatArray, pretension_N))


# -- user files -------------------------------------------------------------------------------


class TrajectoryFile(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Schema of a user trajectory file (JSON or TOML) and of :meth:`Trajectory.to_dict`.

    ``durations_s``, ``dwell_s`` and ``pretension_N`` are a scalar for all segments/waypoints or
    one per item.
    """

    waypoints_deg: list[list[float]]
    durations_s: float | list[float] = msgspec.field(default_factory=list)
    dwell_s: float | list[float] = 0.0
    name: str = "user"
    pretension_N: float | list[float] = 0.0


def trajectory_json_schema() -> dict[str, Any]:
    """JSON Schema of :class:`TrajectoryFile`, for the REST API and editors."""
    return msgspec.json.schema(TrajectoryFile)


#: The longest trajectory name, as the console's (server/campaign_request.py, the library's names).
TRAJECTORY_NAME_MAX = 64
#: Unicode categories a name may not hold: controls (NUL, newline), formats (bidi overrides such as
#: U+202E, zero-width characters), surrogates, line and paragraph separators. The name is shown by
#: the console, printed by the CLI and recorded in archives: such a character hides or reorders text.
_NAME_REFUSED_CATEGORIES = ("Cc", "Cf", "Cs", "Zl", "Zp")


def _check_name(name: str) -> None:
    if len(name) > TRAJECTORY_NAME_MAX:
        raise TrajectoryError(f"name: {len(name)} characters, at most {TRAJECTORY_NAME_MAX}")
    bad = next((c for c in name if unicodedata.category(c) in _NAME_REFUSED_CATEGORIES), None)
    if bad is not None:
        raise TrajectoryError(f"name {name!r}: U+{ord(bad):04X} ({unicodedata.name(bad, 'a control character')}) "
                              f"at {name.index(bad)}: no control, format or line-separator character")


def _from_file_struct(spec: TrajectoryFile) -> Trajectory:
    _check_name(spec.name)
    rows = spec.waypoints_deg
    if rows and len({len(r) for r in rows}) != 1:
        first = len(rows[0])
        bad = next(i for i, r in enumerate(rows) if len(r) != first)
        raise TrajectoryError(f"waypoint {bad} has {len(rows[bad])} joints, waypoint 0 has {first}")
    if not rows:
        raise TrajectoryError("empty trajectory: waypoints_deg has no waypoint")
    return Trajectory.from_degrees(rows, spec.durations_s, spec.dwell_s, spec.name, spec.pretension_N)


def load_trajectory(source: str | os.PathLike[str] | Mapping[str, Any]) -> Trajectory:
    """Build a trajectory from a user file (``.json`` or ``.toml``) or an already parsed mapping.

    Raises :class:`TrajectoryError` naming the key or waypoint/segment on bad content; unknown
    keys are rejected so a typo (``duration_s``) is not silently ignored.
    """
    where = ""
    try:
        if isinstance(source, Mapping):
            spec = msgspec.convert(dict(source), TrajectoryFile)
        else:
            path = Path(source)
            where = f"{path}: "
            suffix = path.suffix.lower()
            # read_input_file: a regular file of at most 1 MiB (a FIFO hung the command, /dev/zero
            # ended in a MemoryError traceback: input audit); the reason is an OSError's, below
            if suffix == ".json":
                spec = msgspec.json.decode(read_input_file(path), type=TrajectoryFile)
            elif suffix == ".toml":
                spec = msgspec.convert(toml_text.loads(read_input_file(path).decode("utf-8")), TrajectoryFile)
            elif not suffix and not path.exists():  # a name: the user meant a built-in one
                raise TrajectoryError(
                    f"no built-in trajectory of that name ({' or '.join(NAMED_TRAJECTORIES)}) and no such file: "
                    "give one of those names, or a .json or .toml file of waypoints")
            else:
                raise TrajectoryError(
                    f"unknown trajectory file type {suffix!r}: give a .json or .toml file of waypoints, or a "
                    f"built-in trajectory by its name ({' or '.join(NAMED_TRAJECTORIES)})"
                )
        return _from_file_struct(spec)
    except (msgspec.ValidationError, msgspec.DecodeError, tomllib.TOMLDecodeError, TrajectoryError) as err:
        raise TrajectoryError(f"{where}{err}") from err
    except OSError as err:  # missing, a directory, unreadable: the user's file, so a TrajectoryError like its content
        raise TrajectoryError(f"{where}cannot read the trajectory file ({err.strerror or err})") from None
    except UnicodeDecodeError as err:
        raise TrajectoryError(f"{where}not a UTF-8 text file (byte {err.start}: {err.reason})") from None
    except RecursionError:  # tomllib recurses per nesting level (audit of 2026-11-28: a traceback)
        raise TrajectoryError(f"{where}nested too deeply") from None


def trajectory_from_json(text: str | bytes) -> Trajectory:
    """A trajectory from JSON text in the user-file schema (:class:`TrajectoryFile`), for input
    that is not trusted (the bus, REST): never a path, so it opens no file; the structure is
    checked while decoding, so deep nesting or a wrong type fails fast with a reason."""
    try:
        return _from_file_struct(msgspec.json.decode(text, type=TrajectoryFile))
    except (msgspec.ValidationError, msgspec.DecodeError) as err:
        raise TrajectoryError(f"trajectory JSON: {err}") from None


# -- the paper's trajectories ---------------------------------------------------------------

IDENTIFICATION_AMPLITUDES_DEG: tuple[tuple[float, float, float], ...] = (
    (40.0, 30.0, 20.0),
    (-40.0, 30.0, 20.0),
    (40.0, -30.0, 20.0),
    (40.0, 30.0, -20.0),
)
"""α^d of the four sequences of §5.2.2 (deg): all joints together, then joint 1, 2, 3 opposed."""

CONTROL_TEST_WAYPOINTS_DEG: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0),
    (50.0, 50.0, 50.0),
    (0.0, 0.0, 0.0),
    (-30.0, -40.0, -50.0),
    (0.0, 0.0, 0.0),
)
"""Waypoints of the control test of §7 / Fig. 10 (deg)."""


#: The most samples :func:`recorded_excitation` draws: 2 hours at 500 Hz, far beyond a campaign (600 s at most).
EXCITATION_SAMPLES_MAX = 3_600_000


def recorded_excitation(trajectory_json: str, t: FloatArray) -> FloatArray | None:
    """α^d (rad) of a campaign's recorded trajectory (its archive's ``trajectory`` metadata, JSON)
    at the times ``t`` (s, from the first sample): the excitation whose spectrum sets the
    identification's filter cutoff (:mod:`twin.identification.record`). None when the record holds
    no readable trajectory, or one that would take more than :data:`EXCITATION_SAMPLES_MAX` samples;
    the cutoff then comes from the encoders."""
    if not trajectory_json or len(t) < 2:
        return None
    try:
        data = json.loads(trajectory_json)
        if isinstance(data, dict):  # the name plays no part in the excitation (older archives: any name)
            data.pop("name", None)
        traj = load_trajectory(data)
    except (TrajectoryError, ValueError, TypeError, RecursionError):  # the archive's word: hostile until read
        return None
    dt = float(np.median(np.diff(t)))
    # The archive's word, not the controller's: a dwell of 1e6 s or a step of 1e-12 s asked numpy
    # for gigabytes (a MemoryError traceback from `xneck identify`; audit of 2026-11-27).
    if not (math.isfinite(dt) and dt > 0 and traj.duration_s / dt <= EXCITATION_SAMPLES_MAX):
        return None
    return traj.sample(np.arange(0.0, traj.duration_s, dt)).alpha


def _rest_dwell(n_waypoints: int, dwell_s: float, rest_s: float | None) -> FloatArray:
    dwell = np.full(n_waypoints, float(dwell_s))
    dwell[[0, -1]] = dwell_s if rest_s is None else rest_s
    return dwell


def identification_trajectory(motion_s: float = 3.0, dwell_s: float = 1.0, rest_s: float | None = None) -> Trajectory:
    """Excitation trajectory of §5.2.2: four sequences of six cycloidal motions (24 in all).

    Each sequence is 0 → α → −α → 0 → −α → α → 0 with α = (40, 30, 20)°, (−40, 30, 20)°,
    (40, −30, 20)°, (40, 30, −20)°; consecutive sequences share their straight configuration,
    so there are 25 waypoints.

    The paper gives no timing. Defaults: every motion ``motion_s`` = 3 s and a ``dwell_s`` = 1 s
    stop at every waypoint (``rest_s`` overrides the initial and final rest), 97 s in all. The
    largest move (α → −α, 80° on joint 1) then peaks at 53°/s and 56°/s², slow enough for the
    simplified model of Eq. 66, while the stops give static samples at every configuration
    (the identification wants "a large set of configurations α", i.e. of Z(α) and of forces).
    """
    rows: list[tuple[float, ...]] = [(0.0, 0.0, 0.0)]
    for amp in IDENTIFICATION_AMPLITUDES_DEG:
        a = np.asarray(amp)
        rows += [tuple(a), tuple(-a), (0.0, 0.0, 0.0), tuple(-a), tuple(a), (0.0, 0.0, 0.0)]
    return Trajectory.from_degrees(rows, motion_s, _rest_dwell(len(rows), dwell_s, rest_s), "identification")


def control_test_trajectory(motion_s: float = 2.0, dwell_s: float = 1.0, rest_s: float | None = None) -> Trajectory:
    """Control-test trajectory of §7: 0 → (50, 50, 50)° → 0 → (−30, −40, −50)° → 0.

    Defaults chosen to match Fig. 10 (straight at 0 s, (50, 50, 50)° at 4 s, straight at 7 s,
    (−30, −40, −50)° at 10 s) *and* the "displacement phases and stop phases" of §7 (Fig. 14):
    a 1 s rest, then 2 s motions each followed by a 1 s stop. The waypoints are reached at
    0, 3, 6, 9, 12 s and left at 1, 4, 7, 10 s, so each configuration of Fig. 10 is the pose
    held at the end of its stop; the trajectory ends at 13 s. Peak rates (0 → 50°):
    50°/s and 79°/s². ``control_test_trajectory(motion_s=3.0, dwell_s=0.0, rest_s=1.0)``
    instead arrives exactly at 4, 7, 10 s without intermediate stops.
    """
    rows = CONTROL_TEST_WAYPOINTS_DEG
    return Trajectory.from_degrees(rows, motion_s, _rest_dwell(len(rows), dwell_s, rest_s), "control_test")


def repeated(traj: Trajectory, n: int) -> Trajectory:
    """``traj`` run ``n`` times back to back (its last waypoint must be its first, as the §5.2.2
    trajectory's straight pose): a longer identification record at the same speeds, whose σ's fall
    as 1/√n. Each pass keeps its holds; the joined waypoint keeps the first pass's final hold."""
    if n < 1:
        raise TrajectoryError(f"a trajectory is repeated at least once, got {n}")
    w = traj.waypoints_rad
    if not np.allclose(w[0], w[-1]):
        raise TrajectoryError(f"{traj.name!r} ends at {_deg(w[-1])}, not at its start {_deg(w[0])}: it cannot be repeated")
    k = traj.n_waypoints
    body = slice(1, k)
    return Trajectory(
        np.vstack([w] + [w[body]] * (n - 1)),
        np.concatenate([traj.durations_s] * n),
        np.concatenate([traj.dwell_s] + [traj.dwell_s[body]] * (n - 1)),
        traj.name if n == 1 else f"{traj.name}-x{n}",
        np.concatenate([traj.pretension_N] + [traj.pretension_N[body]] * (n - 1)),
    )


NAMED_TRAJECTORIES: dict[str, Callable[..., Trajectory]] = {
    "identification": identification_trajectory,
    "control_test": control_test_trajectory,
}


def trajectory_by_name(name: str, **timing: float) -> Trajectory:
    """A built-in trajectory by name (``identification``, ``control_test``); ``timing`` keywords
    (``motion_s``, ``dwell_s``, ``rest_s``) are passed on."""
    key = name.strip().lower().replace("-", "_")
    if key not in NAMED_TRAJECTORIES:
        raise TrajectoryError(f"unknown trajectory {name!r}; known: {', '.join(NAMED_TRAJECTORIES)}")
    return NAMED_TRAJECTORIES[key](**timing)


# -- validation -------------------------------------------------------------------------------


class TrajectoryLimits(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Bounds a desired trajectory must respect, per joint (a scalar applies to every joint).

    Defaults:
      * ``alpha_max_rad`` = 60° (controller issue; ``Limits.alpha_max_deg`` in the robot params).
      * ``alpha_dot_max_rad_s`` = 1.5 rad/s (86°/s) and ``alpha_ddot_max_rad_s2`` = 3.0 rad/s²
        (172°/s²). Not from the paper: the default identification (≤ 0.93 rad/s, 0.98 rad/s²)
        and control-test (≤ 0.87 rad/s, 1.37 rad/s²) trajectories pass with a ×1.6 / ×2 margin,
        while the controller's simplified model (Eq. 66, centrifugal and elongation-acceleration
        terms dropped because "motions are not very fast") stays credible.
      * ``duration_max_s`` = 600 s and ``waypoints_max`` = 2000: what one campaign may ask for
        (the identification trajectory is 97 s and 25 waypoints). Checked first, so that the
        force check, whose cost grows with the duration, never runs on a huge request.
      * ``pretension_rate_max_N_s`` = 100 N/s: the fastest a pretension may change (peak of its
        cycloid, 2|ΔP|/T). Not from the paper: 0.2 N per 500 Hz tick, five times gentler than
        the bridge's bumpless ramp (1 N per tick), and slow next to the current loop.
    """

    alpha_max_rad: float | tuple[float, ...] = math.radians(60.0)
    alpha_dot_max_rad_s: float | tuple[float, ...] = 1.5
    alpha_ddot_max_rad_s2: float | tuple[float, ...] = 3.0
    duration_max_s: float = 600.0
    waypoints_max: int = 2000
    pretension_rate_max_N_s: float = 100.0

    def __post_init__(self) -> None:
        for name in _PER_JOINT:
            values = np.atleast_1d(np.asarray(getattr(self, name), dtype=np.float64))
            if values.size == 0 or not np.all(np.isfinite(values) & (values > 0)):
                raise ValueError(f"{name} must be positive and finite, got {getattr(self, name)}")
        if not (math.isfinite(self.duration_max_s) and self.duration_max_s > 0 and self.waypoints_max >= 1):
            raise ValueError(f"duration_max_s and waypoints_max must be positive, got {self.duration_max_s}, "
                             f"{self.waypoints_max}")
        if not (math.isfinite(self.pretension_rate_max_N_s) and self.pretension_rate_max_N_s > 0):
            raise ValueError(f"pretension_rate_max_N_s must be positive and finite, got {self.pretension_rate_max_N_s}")

    @classmethod
    def from_degrees(
        cls,
        alpha_max_deg: float | tuple[float, ...] = 60.0,
        alpha_dot_max_deg_s: float | tuple[float, ...] = math.degrees(1.5),
        alpha_ddot_max_deg_s2: float | tuple[float, ...] = math.degrees(3.0),
    ) -> TrajectoryLimits:
        def rad(v: float | tuple[float, ...]) -> float | tuple[float, ...]:
            return tuple(math.radians(x) for x in v) if isinstance(v, tuple | list) else math.radians(v)

        return cls(
            alpha_max_rad=rad(alpha_max_deg),
            alpha_dot_max_rad_s=rad(alpha_dot_max_deg_s),
            alpha_ddot_max_rad_s2=rad(alpha_ddot_max_deg_s2),
        )

    def per_joint(self, n_joints: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(|α| max, |α̇| max, |α̈| max), each shape (n_joints,) (rad, rad/s, rad/s²)."""
        out = []
        for name in _PER_JOINT:
            values = np.asarray(getattr(self, name), dtype=np.float64)
            if values.ndim == 1 and values.shape != (n_joints,):
                raise TrajectoryError(f"limit {name} has {values.size} values for {n_joints} joints")
            out.append(np.broadcast_to(values, (n_joints,)).astype(np.float64))
        return out[0], out[1], out[2]


_PER_JOINT = ("alpha_max_rad", "alpha_dot_max_rad_s", "alpha_ddot_max_rad_s2")

# Tolerance on limits: a waypoint written as exactly 60° must pass a 60° limit after deg → rad.
_RTOL = 1e-9


def validate(
    traj: Trajectory,
    limits: TrajectoryLimits,
    n_joints: int,
    force_check: ForceCheck | None = None,
    *,
    dt_s: float = 0.01,
) -> None:
    """Reject an unsafe trajectory before anything moves; returns None if it is acceptable.

    Checks, in order: number of joints; number of waypoints and total duration; every waypoint within ±α_max (a cycloidal move is
    monotonic per joint, so the whole path then stays within limits); each segment's exact peak
    |α̇| = 2|Δ|/T and |α̈| = 2π|Δ|/T²; then, if ``force_check`` is given, the nominal path
    sampled every ``dt_s`` (plus every waypoint time), reporting the first failing sample.

    Raises:
        TrajectoryError: naming the waypoint (with its value in degrees) or segment, the joint
            and the reason; speed/acceleration failures suggest the shortest acceptable duration.
    """
    if not isinstance(traj, Trajectory):
        raise TrajectoryError(f"expected a Trajectory, got {type(traj).__name__}")
    if traj.n_joints != n_joints:
        raise TrajectoryError(
            f"{traj.name!r}: wrong number of joints: waypoints have {traj.n_joints}, the robot has {n_joints}"
        )
    if traj.n_waypoints > limits.waypoints_max:
        raise TrajectoryError(f"{traj.name!r}: {traj.n_waypoints} waypoints, more than the {limits.waypoints_max} "
                              "a campaign may have")
    if traj.duration_s > limits.duration_max_s:
        raise TrajectoryError(f"{traj.name!r}: lasts {traj.duration_s:.4g} s, longer than the "
                              f"{limits.duration_max_s:.4g} s a campaign may last")
    a_max, v_max, acc_max = limits.per_joint(n_joints)
    w = traj.waypoints_rad

    outside = np.abs(w) > a_max * (1 + _RTOL)
    for k in np.flatnonzero(outside.any(axis=1)):
        j = int(np.flatnonzero(outside[k])[0])
        raise TrajectoryError(
            f"{traj.name!r}: waypoint {k} ({_deg(w[k])}) is out of the joint limits: "
            f"α{j + 1} = {math.degrees(w[k, j]):.4g}° exceeds ±{math.degrees(a_max[j]):.4g}°"
        )

    delta = np.abs(traj.segment_deltas())
    for peak, bound, what, unit, power in (
        (traj.segment_peak_velocity(), v_max, "is too fast", "°/s", 1),
        (traj.segment_peak_acceleration(), acc_max, "has too much acceleration", "°/s²", 2),
    ):
        over = peak > bound * (1 + _RTOL)
        for i in np.flatnonzero(over.any(axis=1)):
            j = int(np.argmax(peak[i] / bound))
            gain = CYCLOID_PEAK_VELOCITY if power == 1 else CYCLOID_PEAK_ACCELERATION
            t_min = (gain * delta[i, j] / bound[j]) ** (1.0 / power)
            raise TrajectoryError(
                f"{traj.name!r}: segment {i} (waypoint {i} → {i + 1}, {traj.durations_s[i]:.4g} s) {what}: "
                f"α{j + 1} peaks at {math.degrees(peak[i, j]):.4g}{unit} > {math.degrees(bound[j]):.4g}{unit}; "
                f"needs at least {t_min:.3g} s"
            )

    if traj.has_pretension:
        P = traj.pretension_N
        if P[0] > 0.0 or P[-1] > 0.0:
            raise TrajectoryError(f"{traj.name!r}: the pretension must start and end at 0 N (got {P[0]:.4g} N and "
                                  f"{P[-1]:.4g} N): the law takes over and hands back the neck at its own floor")
        rate = traj.segment_peak_pretension_rate()
        for i in np.flatnonzero(rate > limits.pretension_rate_max_N_s * (1 + _RTOL)):
            raise TrajectoryError(
                f"{traj.name!r}: segment {i} (waypoint {i} → {i + 1}, {traj.durations_s[i]:.4g} s) changes the "
                f"pretension too fast: {P[i]:.4g} → {P[i + 1]:.4g} N peaks at {rate[i]:.4g} N/s > "
                f"{limits.pretension_rate_max_N_s:.4g} N/s; needs at least "
                f"{CYCLOID_PEAK_VELOCITY * abs(P[i + 1] - P[i]) / limits.pretension_rate_max_N_s:.3g} s")

    if force_check is None:
        return
    t = traj.time_grid(dt_s)
    alpha, alpha_dot, alpha_ddot = traj.sample(t)
    ok, reason = force_check(alpha, alpha_dot, alpha_ddot, traj.pretension(t))
    ok = np.asarray(ok)
    if ok.shape != t.shape or ok.dtype != np.bool_:
        raise ValueError(f"force_check must return a bool array of shape {t.shape}, got {ok.dtype} {ok.shape}")
    bad = np.flatnonzero(~ok)
    if bad.size:
        i = int(bad[0])
        raise TrajectoryError(
            f"{traj.name!r}: forces out of bounds in {traj.describe_time(float(t[i]))} at t = {t[i]:.3f} s "
            f"(α^d = {_deg(alpha[i])}): {reason}"
        )


APPROACH_SPEED_MAX_RAD_S = 0.5
APPROACH_ACCELERATION_MAX_RAD_S2 = 1.0


def approach_duration_s(delta_rad: float) -> float:
    """Duration (s) of a gentle cycloidal move over ``delta_rad`` (the largest joint's): peak speed
    at most 0.5 rad/s and acceleration at most 1 rad/s², at least 1 s."""
    return max(1.0, CYCLOID_PEAK_VELOCITY * delta_rad / APPROACH_SPEED_MAX_RAD_S,
               math.sqrt(CYCLOID_PEAK_ACCELERATION * delta_rad / APPROACH_ACCELERATION_MAX_RAD_S2))


BRAKE_ACCELERATION_MAX_RAD_S2 = 3.0  # the trajectories' own bound (TrajectoryLimits.alpha_ddot_max_rad_s2)
BRAKE_DURATION_MIN_S = 0.05  # s: a stop at (almost) rest still ends smoothly over 25 ticks
#: rad/s³: how fast a stop lets go of the acceleration α^d had (:func:`brake_at`): 0.24 rad/s² a
#: tick at 500 Hz, over 0.22 s from 3 rad/s². Starting the brake at α̈ = 0 had stepped the law's
#: forces up to 3.33 N in one tick, 0.62-1.13 N now (docs/safety/stop_brake.py, session 45). 60
#: rad/s³ had made the release overlap the deceleration and the stop travel further.
BRAKE_JERK_MAX_RAD_S3 = 120.0
#: rad/s²: the acceleration a stop lets go of is clipped to this first (a validated trajectory,
#: its resume ramp or a blend reach about 5.5; nothing sane beyond: review of session 45).
BRAKE_RELEASE_ACCELERATION_MAX_RAD_S2 = 6.0
_BRAKE_SAMPLES = 65  # τ samples a brake's path is checked at against the joint limits


def release_duration_s(alpha_ddot_rad_s2: ArrayLike | None) -> float:
    """Duration (s) over which a stop lets go of the acceleration α̈ it starts with (:func:`brake_at`):
    9|α̈|/``BRAKE_JERK_MAX_RAD_S3`` (|g'| ≤ 9, :func:`_release`), at least ``BRAKE_DURATION_MIN_S``;
    0 without one."""
    acc = np.asarray(alpha_ddot_rad_s2 if alpha_ddot_rad_s2 is not None else (), dtype=np.float64)
    a_abs = float(np.max(np.abs(acc))) if acc.size else 0.0
    return 0.0 if a_abs == 0.0 else max(BRAKE_DURATION_MIN_S, 9.0 * a_abs / BRAKE_JERK_MAX_RAD_S3)


def _release(tau: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """g(τ) = (1 − τ)(1 − 8τ + 10τ²) and its first two integrals from 0: α̈₀ is let go of as α̈₀g(τ).
    g(0) = 1 (no step), g(1) = 0, ∫₀¹g = 0 (no speed left) and ∫₀¹∫₀^τ g = 0 (no travel left: a
    stop rests where it would without α̈₀; on the way, at most 0.0173 α̈₀T_r²). Review of session
    45: (1 − τ)(1 − 3τ) had added α̈₀T_r²/12, cubic in α̈₀, beyond the joint limits' reach."""
    t = np.clip(np.asarray(tau, dtype=np.float64), 0.0, 1.0)
    g = (1.0 - t) * (1.0 - 8.0 * t + 10.0 * t * t)
    g1 = t * (1.0 - t * (4.5 - t * (6.0 - 2.5 * t)))
    g2 = t * t * (0.5 - t * (1.5 - t * (1.5 - 0.5 * t)))
    return g, g1, g2


def brake_duration_s(alpha_rad: ArrayLike, alpha_dot_rad_s: ArrayLike, alpha_max_rad: float,
                     alpha_ddot_rad_s2: ArrayLike | None = None) -> float:
    """Duration T (s) of a controlled stop's deceleration from α at speed α̇ (:func:`brake_at`;
    with an acceleration α̈ the stop ends at the later of T and :func:`release_duration_s`): the
    shortest whose |α̈^d| stays within ``BRAKE_ACCELERATION_MAX_RAD_S2`` (2|α̇|/T at rest from
    α̈; with α̈ let go of meanwhile, checked along the path: at most 3 T_fast) or within |α̈| if
    that is larger, and whose path stays within ±``alpha_max_rad`` (or where a joint already is
    beyond it): the stop is then shorter and firmer."""
    a = np.asarray(alpha_rad, dtype=np.float64)
    v = np.asarray(alpha_dot_rad_s, dtype=np.float64)
    acc = None if alpha_ddot_rad_s2 is None else np.asarray(alpha_ddot_rad_s2, dtype=np.float64)
    speed = float(np.max(np.abs(v))) if v.size else 0.0
    a_abs = float(np.max(np.abs(acc))) if acc is not None and acc.size else 0.0
    duration = max(BRAKE_DURATION_MIN_S, CYCLOID_PEAK_VELOCITY * speed / BRAKE_ACCELERATION_MAX_RAD_S2)
    if acc is not None and a_abs > 0.0 and speed > 0.0:
        # α̈ let go of adds to the deceleration where their signs meet: the shortest of a few
        # longer brakes whose sampled path keeps within the bound (vectorised: a stop is
        # handled within a tick)
        ceiling = max(BRAKE_ACCELERATION_MAX_RAD_S2, a_abs) + 1e-9
        for candidate in np.geomspace(duration, 3.0 * duration, 6):
            _, _, acc_path = brake_path(a, v, float(candidate), _brake_times(float(candidate), acc), acc)
            duration = float(candidate)
            if float(np.max(np.abs(acc_path))) <= ceiling:
                break
    room = np.where(v > 0, alpha_max_rad - a, np.where(v < 0, alpha_max_rad + a, np.inf))
    moving = np.abs(v) > 0
    if np.any(moving):
        duration = min(duration, float(np.min(2.0 * np.maximum(room[moving], 0.0) / np.abs(v[moving]))))
    duration = max(duration, 1e-3)
    if acc is None or a_abs == 0.0 or _brake_within(a, v, acc, duration, alpha_max_rad):
        return duration
    if not _brake_within(a, v, acc, 1e-3, alpha_max_rad):
        # the release's own excursion crosses (a joint at its limit, α̈ outward): no shorter
        # brake helps, and one within a tick would stop every joint dead (review of session 45)
        return duration
    lo, hi = 1e-3, duration  # the release turns the path on its way: the longest that fits (to 0.4 %:
    for _ in range(8):  # a stop is handled within a tick, 0.1 ms each)
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _brake_within(a, v, acc, mid, alpha_max_rad) else (lo, mid)
    return lo


def _brake_times(duration_s: float, acc: np.ndarray | None) -> FloatArray:
    """Times (s) a brake's path is checked at: over the whole stop."""
    return np.linspace(0.0, max(duration_s, release_duration_s(acc)), _BRAKE_SAMPLES)


def _brake_within(a: np.ndarray, v: np.ndarray, acc: np.ndarray, duration_s: float, alpha_max_rad: float) -> bool:
    """Whether a brake's path stays within ±alpha_max (or |α₀|, where a joint is beyond it)."""
    bound = np.maximum(alpha_max_rad, np.abs(a)) + 1e-12
    alpha, _, _ = brake_path(a, v, duration_s, _brake_times(duration_s, acc), acc)
    return bool(np.all(np.abs(alpha) <= bound))


def brake_path(alpha0_rad: np.ndarray, alpha_dot0_rad_s: np.ndarray, duration_s: float, t_s: ArrayLike,
               alpha_ddot0_rad_s2: np.ndarray | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`brake_at` at many times ``t_s`` (shape (k,)) at once: arrays of shape (k, N)."""
    t = np.asarray(t_s, dtype=np.float64)[:, None]
    tau = np.clip(t / duration_s, 0.0, 1.0)
    s, ds, _ = cycloid(tau)
    travelled = tau * tau / 2.0 + (np.cos(_TWO_PI * tau) - 1.0) / (_TWO_PI * _TWO_PI)
    alpha = alpha0_rad + alpha_dot0_rad_s * duration_s * (tau - travelled)
    alpha_dot = alpha_dot0_rad_s * (1.0 - s)
    alpha_ddot = -alpha_dot0_rad_s * (ds / duration_s)
    release_s = release_duration_s(alpha_ddot0_rad_s2)
    if alpha_ddot0_rad_s2 is not None and release_s > 0.0:
        g, g1, g2 = _release(t / release_s)
        alpha = alpha + alpha_ddot0_rad_s2 * (release_s * release_s * g2)
        alpha_dot = alpha_dot + alpha_ddot0_rad_s2 * (release_s * g1)
        alpha_ddot = alpha_ddot + alpha_ddot0_rad_s2 * g
    return alpha, alpha_dot, alpha_ddot


def brake_at(alpha0_rad: np.ndarray, alpha_dot0_rad_s: np.ndarray, duration_s: float,
             t_s: float, alpha_ddot0_rad_s2: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """α, α̇, α̈ at ``t_s`` into a controlled stop from (α₀, α̇₀, α̈₀): the velocity α̇₀(1 − s(t/T))
    with the cycloid s over T = ``duration_s``, plus α̈₀ let go of as α̈₀g(t/T_r) over
    T_r = :func:`release_duration_s` (:func:`_release`): α^d, α̇^d and α̈^d start where they were
    and end at rest at α₀ + α̇₀T/2 once both are over, without a step (a stop that set
    α^d to α̂ at rest stepped the law's forces by its rate bound, 10 N a tick: audit of
    2026-11-26; one that started at α̈ = 0, 2.35 N at 2.9 rad/s²: session 45)."""
    tau = min(max(t_s / duration_s, 0.0), 1.0)
    s, ds, _ = cycloid_at(tau)
    travelled = tau * tau / 2.0 + (math.cos(_TWO_PI * tau) - 1.0) / (_TWO_PI * _TWO_PI)  # ∫₀^τ s
    alpha = alpha0_rad + alpha_dot0_rad_s * duration_s * (tau - travelled)
    alpha_dot = alpha_dot0_rad_s * (1.0 - s)
    alpha_ddot = -alpha_dot0_rad_s * (ds / duration_s)
    release_s = release_duration_s(alpha_ddot0_rad_s2)
    if alpha_ddot0_rad_s2 is not None and release_s > 0.0:
        r = min(max(t_s / release_s, 0.0), 1.0)  # _release in plain floats (the per-tick path)
        g = (1.0 - r) * (1.0 - 8.0 * r + 10.0 * r * r)
        g1 = r * (1.0 - r * (4.5 - r * (6.0 - 2.5 * r)))
        g2 = r * r * (0.5 - r * (1.5 - r * (1.5 - 0.5 * r)))
        alpha = alpha + alpha_ddot0_rad_s2 * (release_s * release_s * g2)
        alpha_dot = alpha_dot + alpha_ddot0_rad_s2 * (release_s * g1)
        alpha_ddot = alpha_ddot + alpha_ddot0_rad_s2 * g
    return alpha, alpha_dot, alpha_ddot


def approach(traj: Trajectory, alpha_now: ArrayLike, tolerance_rad: float = math.radians(0.5)) -> Trajectory:
    """``traj`` preceded, if the neck is not already at its first waypoint, by a gentle cycloidal
    move from ``alpha_now`` (rad): peak speed at most 0.5 rad/s and acceleration at most 1 rad/s²,
    at least 1 s. A controller that runs campaigns back to back never jumps to a start pose."""
    now = np.asarray(alpha_now, dtype=np.float64)
    w = np.asarray(traj.waypoints_rad, dtype=np.float64)
    delta = float(np.max(np.abs(w[0] - now)))
    if delta <= tolerance_rad:
        return traj
    move_s = approach_duration_s(delta)
    durations = np.broadcast_to(np.asarray(traj.durations_s, dtype=np.float64), (len(w) - 1,))
    dwell = np.broadcast_to(np.asarray(traj.dwell_s, dtype=np.float64), (len(w),)) if np.size(traj.dwell_s) else np.zeros(len(w))
    return Trajectory(
        waypoints_rad=np.vstack([now, w]),
        durations_s=np.concatenate([[move_s], durations]),
        dwell_s=np.concatenate([[0.0], dwell]),
        name=traj.name,
        pretension_N=np.concatenate([[0.0], traj.pretension_N]),
    )
