"""Robot parameter sets: one TOML file, loaded into a typed, immutable, validated object.

The default is the 3-X prototype (``prototype_3x.toml`` shipped with this package). A user loads
their own file and/or overrides single values with dotted keys::

    params = load_params("my_neck.toml", overrides={"springs.l0": [0.05, 0.05, 0.05]})

Every error names the key and the reason, e.g. ``geometry.b: b = 0.1 m must be smaller than
L = 0.1 m``. SI units throughout, except keys whose name ends in ``_deg``.
"""

from __future__ import annotations

import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import msgspec

from bridge import toml_text
from bridge.small_file import read_input_file

__all__ = ["DEFAULT_PARAMS_FILE", "ParameterError", "Params", "differing_keys", "dotted_parent", "load_params",
           "params_from_dict", "params_from_toml", "parse_override"]

DEFAULT_PARAMS_FILE = "prototype_3x.toml"
_CASES = "abcd"


class ParameterError(ValueError):
    """A parameter file or override is invalid; the message names the key and the reason."""


class _Section(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            value = getattr(self, name)
            values = value if isinstance(value, tuple) else (value,)
            if any(isinstance(v, float) and not math.isfinite(v) for v in values):
                raise ValueError(f"{name} must be finite, got {value}")


#: The stiffest springs and cables the twin's 2 ms step was checked with (tests/test_sim.py: no
#: step refused, tension within a few N of the command); beyond, springs of 1e7 N/m threw the
#: joints to the flat singularity and cables of 1e15 N/m reported 8e7 N for 2 N commanded
#: (audit of 2026-11-26). The prototype's: 200-600 N/m springs, 2-10 kN/m cables.
SPRING_K_MAX_N_M = 1e6
CABLE_K_MAX_N_M = 1e7


def lambda_max_per_m(k_N_m: float, f_max_N: float) -> float:
    """The largest λ (1/m) of eq. 54's cable of stiffness ``k_N_m`` whose stiffness at ``f_max_N``,
    dt/dx = (k + λ·t)²/k, stays within :data:`CABLE_K_MAX_N_M`."""
    return (math.sqrt(CABLE_K_MAX_N_M * k_N_m) - k_N_m) / f_max_N


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def _nonneg(section: _Section, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        values = value if isinstance(value, tuple) else (value,)
        _require(all(v >= 0 for v in values), f"{name} must be >= 0, got {value}")


def _at_most(section: _Section, bound: float, unit: str, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        values = value if isinstance(value, tuple) else (value,)
        _require(all(v <= bound for v in values), f"{name} must be <= {bound:g} {unit}, got {value}")


def _positive(section: _Section, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        values = value if isinstance(value, tuple) else (value,)
        _require(all(v > 0 for v in values), f"{name} must be > 0, got {value}")


class Geometry(_Section, frozen=True, kw_only=True):
    """X-joint and transmission geometry (3-X paper §2): lengths in m."""

    n_joints: int
    L: float
    b: float
    r: float
    r_d: float
    R: float

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self.n_joints >= 1, f"n_joints must be >= 1, got {self.n_joints}")
        _positive(self, "L", "b", "r_d", "R")
        _nonneg(self, "r")
        _require(self.b < self.L, f"b = {self.b} m must be smaller than L = {self.L} m (X-joint assembly)")
        # Cases (a) and (b) need the side length to exceed the pulley radius over the whole range.
        _require(
            self.L - self.b > self.r,
            f"pulley radius r = {self.r} m must be smaller than L - b = {self.L - self.b:.4g} m",
        )


class Springs(_Section, frozen=True, kw_only=True):
    """Lateral springs of every joint: stiffness N/m, rest length m."""

    k_left: tuple[float, ...]
    k_right: tuple[float, ...]
    l0: tuple[float, ...]

    def __post_init__(self) -> None:
        super().__post_init__()
        _nonneg(self, "k_left", "k_right")
        _at_most(self, SPRING_K_MAX_N_M, "N/m", "k_left", "k_right")
        _positive(self, "l0")


class Bars(_Section, frozen=True, kw_only=True):
    """Masses (kg) and inertias about the centre of mass (kg·m²) of every bar, per joint."""

    m_diagonal: tuple[float, ...]
    I_diagonal: tuple[float, ...]
    m_top: tuple[float, ...]
    I_top: tuple[float, ...]

    def __post_init__(self) -> None:
        super().__post_init__()
        _nonneg(self, "m_diagonal", "I_diagonal", "m_top", "I_top")
        _require(any(v > 0 for v in (*self.m_diagonal, *self.I_diagonal, *self.m_top, *self.I_top)),
                 "a neck without any mass or inertia has no dynamics to integrate: give a bar some")


class Motors(_Section, frozen=True, kw_only=True):
    """Geared motors: inertia at the motor shaft (kg·m²) and the electrical data the bridge uses.

    ``gear_loss_forward`` / ``gear_loss_backward`` (dimensionless): the gear's meshing loss that
    grows with the load, a fraction of the motor force when the motor winds its cable and of the
    tension when the cable drives the motor back. Only Table 2's load-friction fit uses them
    (twin.identification.loadfriction): eq. 37's friction, hence the controller, keeps one level
    per cable. 0 (the default): no such loss."""

    I_a: float
    torque_constant: float
    gear_efficiency: float
    current_max: float
    gear_loss_forward: float = 0.0
    gear_loss_backward: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(self, "I_a", "torque_constant", "current_max")
        _require(0 < self.gear_efficiency <= 1, f"gear_efficiency must be in (0, 1], got {self.gear_efficiency}")
        for name in ("gear_loss_forward", "gear_loss_backward"):
            value = getattr(self, name)
            _require(0 <= value < 0.5, f"{name} must be in [0, 0.5) (a fraction of the load), got {value}")


class Friction(_Section, frozen=True, kw_only=True):
    """Dry friction of the geared motors, eqs. 36-37: f_s in N per cable, c_s in s/rad."""

    model: Literal["arctan", "sign"] = "arctan"
    f_s: tuple[float, ...]
    c_s: float

    def __post_init__(self) -> None:
        super().__post_init__()
        _nonneg(self, "f_s")
        _positive(self, "c_s")


class LinearCable(_Section, frozen=True, kw_only=True):
    """Eq. 39: t = k·x + c_a·ẋ. k in N/m, c_a in N·s/m, per cable."""

    k: tuple[float, ...]
    c_a: tuple[float, ...]

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(self, "k")
        _at_most(self, CABLE_K_MAX_N_M, "N/m", "k")


class VariableCable(_Section, frozen=True, kw_only=True):
    """Eq. 54: t = (k + λ·t)·x + c_a·ẋ. k in N/m, λ in 1/m, c_a in N·s/m, per cable."""

    k: tuple[float, ...]
    lam: tuple[float, ...] = msgspec.field(name="lambda")
    c_a: tuple[float, ...]

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(self, "k")
        _at_most(self, CABLE_K_MAX_N_M, "N/m", "k")
        _require(all(v >= 0 for v in self.lam), f"lambda must be >= 0, got {self.lam}")


class Cables(_Section, frozen=True, kw_only=True):
    """Cable routing (one string per cable, e.g. ``"1d 2b"``) and tension models."""

    routing: tuple[str, ...]
    model: Literal["rigid", "linear", "variable"] = "variable"
    linear: LinearCable
    variable: VariableCable

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(len(self.routing) >= 1, "routing needs at least one cable")
        for j, path in enumerate(self.routing):
            _parse_route(path, f"routing[{j}]")


class Limits(_Section, frozen=True, kw_only=True):
    """Force limits of §6.2 (N) and the joint limit used to validate trajectories (deg)."""

    t_min: float
    f_min: float
    f_max: float
    alpha_max_deg: float = 60.0

    def __post_init__(self) -> None:
        super().__post_init__()
        _nonneg(self, "t_min", "f_min")
        _require(self.f_max > self.f_min, f"f_max = {self.f_max} N must exceed f_min = {self.f_min} N")
        _require(0 < self.alpha_max_deg < 90, f"alpha_max_deg must be in (0, 90), got {self.alpha_max_deg}")


class Environment(_Section, frozen=True, kw_only=True):
    gravity: float = 9.81  # m/s², along −y of the base frame

    def __post_init__(self) -> None:
        super().__post_init__()
        _nonneg(self, "gravity")


class Sensors(_Section, frozen=True, kw_only=True):
    """Encoders and the camera (rates Hz, noise deg, latency s)."""

    encoder_counts_per_rev: int = 2048
    camera_rate: float = 30.0
    camera_noise_deg: float = 1.0
    camera_latency: float = 0.05

    def __post_init__(self) -> None:
        super().__post_init__()
        _positive(self, "encoder_counts_per_rev", "camera_rate")
        _nonneg(self, "camera_noise_deg", "camera_latency")


class Params(_Section, frozen=True, kw_only=True):
    """A complete, validated parameter set. Immutable: derive variants with :func:`load_params` overrides."""

    name: str = "unnamed"
    geometry: Geometry
    springs: Springs
    bars: Bars
    motors: Motors
    friction: Friction
    cables: Cables
    limits: Limits
    environment: Environment = Environment()
    sensors: Sensors = Sensors()

    @property
    def n_joints(self) -> int:
        return self.geometry.n_joints

    @property
    def n_cables(self) -> int:
        return len(self.cables.routing)

    @property
    def motor_peak_force_N(self) -> float:
        """The largest cable force a motor gives (N): its controller's current limit through the
        torque constant, the gear and the drum, as the bridge converts forces (no gear efficiency:
        the identified friction holds the gear's losses)."""
        m, g = self.motors, self.geometry
        return m.current_max * m.torque_constant * g.R / g.r_d

    @property
    def routes(self) -> tuple[tuple[tuple[int, str], ...], ...]:
        """Routing as data: for each cable, the (joint index from 0, case letter) pairs it runs along."""
        return tuple(_parse_route(p, "routing") for p in self.cables.routing)

    def __post_init__(self) -> None:
        super().__post_init__()
        n, m = self.n_joints, self.n_cables
        per_joint = {
            "springs": ("k_left", "k_right", "l0"),
            "bars": ("m_diagonal", "I_diagonal", "m_top", "I_top"),
        }
        per_cable = {"friction": ("f_s",), "cables.linear": ("k", "c_a"), "cables.variable": ("k", "lambda", "c_a")}
        for section, names in per_joint.items():
            for name in names:
                got = len(getattr(getattr(self, section), name))
                _require(got == n, f"{section}.{name} has {got} values, expected one per joint (n_joints = {n})")
        for section, names in per_cable.items():
            obj = self
            for part in section.split("."):
                obj = getattr(obj, part)
            for name in names:
                got = len(getattr(obj, "lam" if name == "lambda" else name))
                _require(got == m, f"{section}.{name} has {got} values, expected one per cable ({m} in cables.routing)")
        for j, route in enumerate(self.routes):
            for joint, _ in route:
                _require(joint < n, f"cables.routing[{j}] names joint {joint + 1} but n_joints = {n}")
        # Eq. 54's cable stiffens with its tension, dt/dx = (k + λ·t)²/k: at f_max it must stay within
        # what the twin's 2 ms step was checked with (CABLE_K_MAX_N_M). Beyond, a study with
        # λ = 1e12 1/m ran its twin at 0.05 N of tension for 10-90 N commanded and reported the run
        # as finished (audit of session 46); the prototype's λ (53-121 1/m) is 11-46 times below.
        f_max, v = self.limits.f_max, self.cables.variable
        lam_max = [lambda_max_per_m(k, f_max) for k in v.k]
        over = [j for j, (lam, top) in enumerate(zip(v.lam, lam_max, strict=True)) if lam > top]
        _require(not over, "cables.variable.lambda = " + str(list(v.lam)) + " 1/m: a cable's stiffness at "
                 f"limits.f_max, (k + λ·f_max)²/k (eq. 54), must be <= {CABLE_K_MAX_N_M:g} N/m, so λ <= "
                 + ", ".join(f"{lam_max[j]:.4g}" for j in over) + " 1/m for cable(s) "
                 + ", ".join(str(j + 1) for j in over))
        # A motor whose static friction is more than the largest force it can pull its cable with
        # never moves: no robot has such a friction (user audit: a study with friction.f_s = 6e299 N
        # ran its twin stuck at rest and reported the run as finished).
        peak = self.motor_peak_force_N
        _require(max(self.friction.f_s) < peak,
                 f"friction.f_s = {list(self.friction.f_s)} N: each must be below the motors' peak force at the "
                 f"cable, {peak:.4g} N (motors.current_max × motors.torque_constant × geometry.R / geometry.r_d), "
                 "or the motor never overcomes its friction")

    def to_dict(self) -> dict[str, Any]:
        return msgspec.to_builtins(self)

    def to_toml(self) -> str:
        """The parameter set as TOML text that :func:`load_params` reads back identically."""
        return _to_toml(self.to_dict())


def _parse_route(path: str, where: str) -> tuple[tuple[int, str], ...]:
    steps = []
    for token in path.split():
        joint, case = token[:-1], token[-1:]
        if not joint.isdigit() or case not in _CASES or int(joint) < 1:
            raise ValueError(f"{where}: '{token}' is not <joint number from 1><case a-d>, e.g. '2b'")
        steps.append((int(joint) - 1, case))
    joints = [j for j, _ in steps]
    if not steps or len(set(joints)) != len(joints):
        raise ValueError(f"{where}: '{path}' must name each joint at most once and at least one joint")
    return tuple(steps)


def parse_override(text: str) -> tuple[str, Any]:
    """Parse ``key.path=value`` where value is a TOML value (``0.05``, ``[1, 2]``, ``"sign"``)."""
    if "=" not in text:
        raise ParameterError(f"override '{text}' must look like key.path=value")
    key, raw = (s.strip() for s in text.split("=", 1))
    try:
        value = toml_text.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # a bare word is taken as a string, e.g. cables.model=linear
    return key, value


def load_params(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> Params:
    """Load a parameter set (default: the 3-X prototype) and apply dotted-key overrides.

    Raises :class:`ParameterError` naming the key and the reason for unknown keys, non-numbers,
    vectors of the wrong length, b >= L, negative stiffness or mass, non-finite values.
    """
    if path is None:
        source = f"<package>/{DEFAULT_PARAMS_FILE}"
        text = resources.files("twin.model").joinpath(DEFAULT_PARAMS_FILE).read_text()
    else:
        source = str(path)
        try:  # a regular file of bounded size: a FIFO hung the command, /dev/zero exhausted memory (input audit)
            text = read_input_file(path).decode("utf-8")
        except OSError as exc:
            raise ParameterError(f"{source}: cannot read parameter file ({exc.strerror})") from exc
        except UnicodeDecodeError as exc:  # the console answered 500 (audit of 2026-11-26)
            raise ParameterError(f"{source}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    return params_from_toml(text, source, overrides)


def params_from_toml(text: str, source: str, overrides: dict[str, Any] | None = None) -> Params:
    """A parameter set from TOML ``text`` (a file's, or an archive's ``parameters_toml``), named
    ``source`` in errors, with dotted-key ``overrides`` applied (:func:`load_params`)."""
    try:
        data = toml_text.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"{source}: not a valid TOML file ({exc})") from exc
    except RecursionError:
        raise ParameterError(f"{source}: nested too deeply") from None
    for key, value in (overrides or {}).items():
        _set_dotted(data, key, value, source)
    if overrides:  # what the file's values refuse of a --set value is said with it, not as the file's fault
        source += " with --set " + ", ".join(f"{k}={_shown(v)}" for k, v in overrides.items())
    return params_from_dict(data, source)


def differing_keys(a: Params, b: Params) -> list[str]:
    """The dotted keys whose values differ between sets ``a`` and ``b`` (``name`` included)."""
    def leaves(value: Any, prefix: str = "") -> dict[str, Any]:
        if isinstance(value, dict):
            return {k: v for key, sub in value.items() for k, v in leaves(sub, f"{prefix}{key}.").items()}
        return {prefix[:-1]: value}

    la, lb = leaves(msgspec.to_builtins(a)), leaves(msgspec.to_builtins(b))
    return sorted(k for k in la.keys() | lb.keys() if la.get(k) != lb.get(k))


def _shown(value: Any) -> str:
    """An override's value as written after ``--set key=`` (TOML-like: strings bare, lists bracketed)."""
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_shown(v) for v in value) + "]"
    return str(value).lower() if isinstance(value, bool) else str(value)


def params_from_dict(data: dict[str, Any], source: str = "<dict>") -> Params:
    try:
        return msgspec.convert(data, Params, strict=True)
    except msgspec.ValidationError as exc:
        raise ParameterError(f"{source}: {_readable(str(exc))}") from None


def _readable(message: str) -> str:
    """'reason - at `$.a.b`' -> 'a.b: reason'."""
    if " - at `$" in message:
        reason, at = message.rsplit(" - at `$", 1)
        key = at.rstrip("`").lstrip(".")
        return f"{key}: {reason}" if key else reason
    return message


def dotted_parent(data: dict[str, Any], key: str) -> tuple[dict[str, Any], str]:
    """(section, last name) of a dotted ``key`` such as ``cables.variable.k`` in a parameter
    document; ``ValueError`` saying which part is not a section or that the key is unknown."""
    parts = key.split(".")
    node = data
    for i, part in enumerate(parts[:-1]):
        child = node.get(part)
        if not isinstance(child, dict):
            raise ValueError(f"'{'.'.join(parts[: i + 1])}' is not a section")
        node = child
    if parts[-1] not in node:
        raise ValueError(f"unknown key {parts[-1]!r} (in {'.'.join(parts[:-1]) or 'the file'})")
    return node, parts[-1]


def _set_dotted(data: dict[str, Any], key: str, value: Any, source: str) -> None:
    """``data[key] = value``; :class:`ParameterError` beginning ``--set key=value:`` when the value is
    not one the key can take whatever the file holds (not finite; a single value for a list or the other
    way round): the --set value is at fault, not the parameter file (audit: ``--set friction.f_s=nan``
    read '<package>/prototype_3x.toml: friction.f_s: Expected `array`, got `float`')."""
    try:
        node, last = dotted_parent(data, key)
    except ValueError as exc:
        raise ParameterError(f"{source}: override '{key}': {exc}") from None
    old = node[last]
    items = value if isinstance(value, list | tuple) else [value]
    problems = []
    if any(isinstance(v, float) and not math.isfinite(v) for v in items):
        problems.append(f"{key} must be finite, not {_shown(value)} (NaN and infinities are no parameter values)")
    if isinstance(old, list) and not isinstance(value, list | tuple):
        problems.append(f"{key} is a list of {len(old)} values, one per element, not a single value: "
                        f"write --set {key}={_shown(old)} with your values")
    elif isinstance(value, list | tuple) and not isinstance(old, list | dict):
        problems.append(f"{key} is a single value, not a list: write --set {key}={_shown(old)} with your value")
    if problems:
        raise ParameterError(f"--set {key}={_shown(value)}: " + "; and ".join(problems))
    node[last] = value


def _toml_string(text: str) -> str:
    """A TOML basic string of ``text``: quotes, backslashes and the control characters TOML forbids
    raw (all but tab) escaped. A routing of "1d\\n2b" (split on any whitespace, so valid) was written
    with a raw newline: the TOML sent to a controller service did not parse (audit of 2026-11-27)."""
    out = []
    for ch in text:
        if ch in ('"', "\\"):
            out.append("\\" + ch)
        elif (ch < " " and ch != "\t") or ch == "\x7f":
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _to_toml(data: dict[str, Any], prefix: str = "") -> str:
    def value(v: Any) -> str:
        if isinstance(v, str):
            return _toml_string(v)
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    scalars = [f"{k} = {value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    tables = [
        f"\n[{prefix}{k}]\n" + _to_toml(v, f"{prefix}{k}.") for k, v in data.items() if isinstance(v, dict)
    ]
    return "\n".join(scalars) + "\n" + "".join(tables)
