"""What the twin simulates where the robot differs from the model the controller runs.

The parameter file (twin/model/prototype_3x.toml) is the *model*: the paper's identified values,
the smooth arctan friction of eq. 37, ideal motors, and c_a = 3000 N·s/m for every cable, which
the 3-X paper (§5.3) chose "in order to damp the elongation in our model". The controller keeps
that model. A *truth* adds what the paper's model leaves out, each effect switchable and every
value with its source (datasheet, measurement, physics estimate, architecture, or none):

``"model"``
    No effect: the twin simulates the parameter file exactly (the paper's simulator, §5.6).
    Controller and twin share one model; campaigns then measure the control law alone.
``"robot"``
    The shipped truth file ``robot_truth.toml`` (beside this module), every effect on.
a path to a TOML file
    Another truth in the same format (e.g. written by ``xneck twin calibrate``).

Which robot the effects apply to: a truth's ``robot_params`` names the parameter file the robot
is built from ("prototype": the shipped 3-X file; a path, relative to the truth file). The
robot truth names the prototype, so the twin's robot stays the prototype whatever parameter set
the controller is given (an identified set, ``--set`` overrides): on the real robot a new
parameter set changes the controller's beliefs, not the robot, and a twin that followed them
made every comparison of parameter sets circular. Without ``robot_params`` (the model truth,
truth files written before 2026-11-27) the effects apply to the controller's parameter set.
In-process users (studies, benchmarks) pass the robot's parameters explicitly and are not
affected: :func:`robot_base` is for the twin processes (twin.sim.driver, twin.sim.calibrate).

The effects (sections of the file; docs/twin-fidelity.md shows what each one changes):

- ``friction``: Coulomb + viscous + Stribeck stiction (static > kinetic), direction asymmetry,
  load-dependent gear losses (direction-dependent efficiency) and tension-dependent pulley
  friction, integrated as set-valued friction (sticks at rest): twin.sim.integrator. Table 1's
  f_s stays the Coulomb level at the reference load (the identification campaign's mean tension);
  pulleys and gears add friction beyond it in proportion to the load.
- ``actuation``: the ESCON current loop (first order, saturating), per-motor torque-constant
  errors, block-commutation torque ripple, cogging, gear backlash (seen when a cable goes slack).
- ``structure``: errors in bar masses, spring constants and free lengths, pulley radius.
- ``cables``: the real line's small damping (instead of 3000 N·s/m) and creep/hysteresis (a
  Kelvin element in series with the eq. 54 spring). Table 2's k and λ stay the truth's.
- ``timing``: the BeagleBone's one-tick command delay and its control-period jitter.
"""

from __future__ import annotations

import math
import tomllib
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import msgspec

from bridge import toml_text
from bridge.small_file import read_input_file
from twin.model.params import ParameterError, Params, load_params

TruthName = Literal["model", "robot"]  # named truths (not the bus message bridge.bus.Truth); a path also works
TRUTHS: tuple[str, ...] = ("model", "robot")
ROBOT_TRUTH_FILE = Path(__file__).with_name("robot_truth.toml")
EFFECTS: tuple[str, ...] = ("friction", "actuation", "structure", "cables", "timing")
SOURCE_KINDS = ("datasheet", "measurement", "physics estimate", "architecture", "none")

C_A_ROBOT = 40.0  # N·s/m, cable damping of the shipped robot truth (robot_truth.toml [cables])


class TruthError(ValueError):
    """A truth name or file is invalid; the message names the key and the reason."""


class _Effect(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    enabled: bool = False


class FrictionTruth(_Effect, frozen=True, kw_only=True):
    """Motor + pulley friction at the cable (N), against the model's arctan (eq. 37)."""

    static_ratio: float = 1.0  # F_static / F_Coulomb (>= 1)
    stribeck_velocity_rad_s: float = 1.0  # motor shaft
    viscous_N_s_rad: float = 0.0  # N at the cable per rad/s of the motor shaft
    asymmetry: tuple[float, ...] = ()  # per cable: level f_s(1 + a) when winding, f_s(1 − a) unwinding
    gear_loss_forward: float = 0.0  # fraction of the motor force lost when the motor drives (θ̇ > 0)
    gear_loss_backward: float = 0.0  # fraction of the tension lost when the cable drives (θ̇ < 0)
    pulley_friction_per_N: tuple[float, ...] = ()  # per cable, N of friction per N of tension
    pulley_reference_tension_N: float = 0.0  # load at which Table 1's f_s holds the pulley and gear losses


class ActuationTruth(_Effect, frozen=True, kw_only=True):
    current_bandwidth_hz: float = math.inf  # ESCON current loop, first order
    current_max_A: float = math.inf
    torque_constant_factor: tuple[float, ...] = ()  # per motor, true k_t / catalogue k_t
    ripple_fraction: float = 0.0  # torque ripple amplitude / mean torque
    ripple_per_rev: int = 6
    cogging_N: float = 0.0  # cogging amplitude at the cable (N)
    cogging_per_rev: int = 6
    backlash_rad: float = 0.0  # gear backlash at the motor shaft


class StructureTruth(_Effect, frozen=True, kw_only=True):
    mass_factor: tuple[float, ...] = ()  # per joint, all bars of the joint
    spring_factor_left: tuple[float, ...] = ()
    spring_factor_right: tuple[float, ...] = ()
    l0_offset_m: tuple[float, ...] = ()  # per joint, both springs
    pulley_radius_offset_m: float = 0.0


class CableTruth(_Effect, frozen=True, kw_only=True):
    damping_N_s_m: float = 3000.0  # c_a of every cable
    creep_ratio: float = 0.0  # creep stretch / elastic stretch at equilibrium (k / k_creep)
    creep_time_s: float = 1.0


class TimingTruth(_Effect, frozen=True, kw_only=True):
    delay_ticks: int = 0
    jitter_s: float = 0.0  # standard deviation of the control period


class Calibration(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Provenance of a truth written by ``xneck twin calibrate`` (twin/sim/calibrate.py): the
    ``[calibration]`` table of its file. Values are named "section.key" or "section.key[i]"."""

    command: str
    date: str  # ISO 8601, UTC
    campaigns: list[str]  # the recordings fitted (file names)
    base: str  # the truth the fit started from
    fitted: dict[str, float]
    sigma: dict[str, float]  # one standard deviation from the Jacobian at the solution
    residual_rms: dict[str, float]  # theta_rad, alpha_ip_deg, tension_N (those the recordings had)
    evaluations: int
    validation: dict[str, dict[str, float]] = {}  # held-out recording → its residual_rms


class RobotTruth(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """A truth: the effects the twin adds to the model. ``sources``: "section.key" → source;
    ``calibration``: how a calibrated truth was fitted (None for a truth written by hand)."""

    name: str = "model"
    robot_params: str = ""  # "prototype", an absolute path once loaded, or "" (module docstring)
    friction: FrictionTruth = FrictionTruth()
    actuation: ActuationTruth = ActuationTruth()
    structure: StructureTruth = StructureTruth()
    cables: CableTruth = CableTruth()
    timing: TimingTruth = TimingTruth()
    sources: dict[str, str] = {}
    calibration: Calibration | None = None

    def enabled(self) -> tuple[str, ...]:
        return tuple(e for e in EFFECTS if getattr(self, e).enabled)

    def only(self, *effects: str) -> RobotTruth:
        """This truth with only ``effects`` switched on (the others off)."""
        unknown = set(effects) - set(EFFECTS)
        if unknown:
            raise TruthError(f"unknown effects {sorted(unknown)}: choose from {', '.join(EFFECTS)}")
        changes = {e: msgspec.structs.replace(getattr(self, e), enabled=e in effects) for e in EFFECTS}
        label = "+".join(effects) if effects else "none"
        return msgspec.structs.replace(self, name=f"{self.name} [{label}]", **changes)

    def replace(self, section: str, **values: Any) -> RobotTruth:
        """A copy with values of one section changed (validated again)."""
        new = msgspec.structs.replace(getattr(self, section), **values)
        return _validated(msgspec.structs.replace(self, **{section: new}))


MODEL_TRUTH = RobotTruth()


#: Values for which +inf means "ideal" (no bandwidth limit, no saturation); NaN never is a value.
_INFINITE_ALLOWED = frozenset({"actuation.current_bandwidth_hz", "actuation.current_max_A"})


def _not_finite(truth: RobotTruth) -> str | None:
    """The first value of a section that is NaN, or infinite where that means nothing, as
    "section.key" (audit of 2026-11-26: a NaN passed every check and failed the twin 8 s into a
    campaign, naming no key)."""
    for section in EFFECTS:
        body = getattr(truth, section)
        for key in body.__struct_fields__:
            value = getattr(body, key)
            values = value if isinstance(value, tuple) else (value,)
            for x in values:
                if isinstance(x, float) and (math.isnan(x) or (math.isinf(x) and (
                        f"{section}.{key}" not in _INFINITE_ALLOWED or x < 0))):
                    return f"{section}.{key} must be a finite number, got {value}"
    return None


def _validated(truth: RobotTruth) -> RobotTruth:
    f, a, s, c, t = truth.friction, truth.actuation, truth.structure, truth.cables, truth.timing
    not_finite = _not_finite(truth)
    if not_finite:
        raise TruthError(not_finite)
    checks = [
        (f.static_ratio >= 1.0, "friction.static_ratio must be >= 1 (static friction is not below kinetic)"),
        (f.stribeck_velocity_rad_s > 0, "friction.stribeck_velocity_rad_s must be > 0"),
        (f.viscous_N_s_rad >= 0, "friction.viscous_N_s_rad must be >= 0"),
        (all(abs(x) < 1 for x in f.asymmetry), "friction.asymmetry must be within (−1, 1)"),
        (0 <= f.gear_loss_forward < 1 and 0 <= f.gear_loss_backward < 1, "friction.gear_loss_* must be in [0, 1)"),
        (all(x >= 0 for x in f.pulley_friction_per_N), "friction.pulley_friction_per_N must be >= 0"),
        (f.pulley_reference_tension_N >= 0, "friction.pulley_reference_tension_N must be >= 0"),
        (a.current_bandwidth_hz > 0, "actuation.current_bandwidth_hz must be > 0"),
        (a.current_max_A > 0, "actuation.current_max_A must be > 0"),
        (all(x > 0 for x in a.torque_constant_factor), "actuation.torque_constant_factor must be > 0"),
        (0 <= a.ripple_fraction < 1, "actuation.ripple_fraction must be in [0, 1)"),
        (a.cogging_N >= 0 and a.backlash_rad >= 0, "actuation.cogging_N and backlash_rad must be >= 0"),
        (a.ripple_per_rev >= 1 and a.cogging_per_rev >= 1, "actuation.ripple_per_rev and cogging_per_rev must be >= 1"),
        (all(x > 0 for x in s.mass_factor), "structure.mass_factor must be > 0"),
        (all(x > 0 for x in (*s.spring_factor_left, *s.spring_factor_right)),
         "structure.spring_factor_left and spring_factor_right must be > 0"),
        (c.damping_N_s_m >= 0, "cables.damping_N_s_m must be >= 0"),
        (c.creep_ratio >= 0 and c.creep_time_s > 0, "cables.creep_ratio must be >= 0 and creep_time_s > 0"),
        (t.delay_ticks in (0, 1, 2, 3), "timing.delay_ticks must be 0-3"),
        (t.jitter_s >= 0, "timing.jitter_s must be >= 0"),
    ]
    for ok, message in checks:
        if not ok:
            raise TruthError(message)
    return truth


def parse_truth(data: dict[str, Any], name: str = "truth") -> RobotTruth:
    """A truth from a TOML document: each section has ``enabled`` and values written as
    ``key = { value = ..., source = "<kind>: ..." }``, kind one of :data:`SOURCE_KINDS`; an optional
    ``[calibration]`` table says how the values were fitted (:class:`Calibration`)."""
    plain: dict[str, Any] = {"name": str(data.get("name", name))}
    sources: dict[str, str] = {}
    for section, body in data.items():
        if section == "name":
            continue
        if section == "robot_params":
            if not (isinstance(body, str) and (body == "prototype" or body.endswith(".toml"))):
                raise TruthError(f"robot_params: \"prototype\" or the path of a parameter file (.toml), got {body!r}")
            plain[section] = body
            continue
        if section == "calibration":
            plain[section] = body
            continue
        if section not in EFFECTS or not isinstance(body, dict):
            raise TruthError(f"{section}: not an effect section (choose from {', '.join(EFFECTS)})")
        out: dict[str, Any] = {}
        for key, item in body.items():
            if key == "enabled":
                out[key] = item
                continue
            if not (isinstance(item, dict) and set(item) == {"value", "source"}):
                raise TruthError(f"{section}.{key}: write it as {{ value = ..., source = \"<kind>: ...\" }}")
            source = item["source"]
            if not (isinstance(source, str) and source.split(":", 1)[0].strip() in SOURCE_KINDS):
                raise TruthError(f"{section}.{key}: source must start with one of {', '.join(SOURCE_KINDS)} "
                                 f"followed by ':', got {source!r}")
            out[key], sources[f"{section}.{key}"] = item["value"], source
        plain[section] = out
    plain["sources"] = sources
    try:
        return _validated(msgspec.convert(plain, RobotTruth, strict=False))
    except msgspec.ValidationError as exc:
        raise TruthError(f"{name}: {exc}") from None
    except RecursionError:
        raise TruthError(f"{name}: nested too deeply") from None


@lru_cache(maxsize=16)
def _load_file(path: Path, mtime_ns: int) -> RobotTruth:
    try:
        data = toml_text.loads(read_input_file(path).decode("utf-8"))  # a FIFO or a device: refused, not read
    except OSError as exc:
        raise TruthError(f"{path}: cannot read the truth file ({exc.strerror or exc})") from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise TruthError(f"{path}: {exc}") from None
    except RecursionError:
        raise TruthError(f"{path}: nested too deeply") from None
    try:
        truth = parse_truth(data, path.stem)
    except TruthError as exc:
        raise TruthError(f"{path.name}: {exc}") from None
    if truth.robot_params not in ("", "prototype"):  # relative to the truth file, wherever it is read from
        truth = msgspec.structs.replace(truth, robot_params=str((path.parent / truth.robot_params).resolve()))
    return truth


def load_truth(truth: str | Path | RobotTruth = "model") -> RobotTruth:
    """A truth by name ("model", "robot"), by TOML path, or as given."""
    if isinstance(truth, RobotTruth):
        return _validated(truth)
    if truth == "model":
        return MODEL_TRUTH
    path = ROBOT_TRUTH_FILE if truth == "robot" else Path(truth)
    if str(truth) not in TRUTHS and path.suffix != ".toml":
        raise TruthError(f"truth must be one of {', '.join(TRUTHS)} or a .toml file, got {truth!r}")
    if not path.is_file():  # a directory is not "does not exist" (user audit), nor is a FIFO or a device
        why = ("is a directory" if path.is_dir() else "does not exist" if not path.exists()
               else "is not a regular file")
        raise TruthError(f"truth file {str(path)!r} {why}")
    truth_obj = _load_file(path.resolve(), path.stat().st_mtime_ns)
    return msgspec.structs.replace(truth_obj, name="robot") if truth == "robot" else truth_obj


def check_truth(value: str, params: Params | None = None) -> str:
    """``value`` if it names a truth that loads and applies to ``params`` (default: the 3-X
    prototype: one value per joint or cable where a section wants that); :class:`TruthError` with
    the reason otherwise."""
    t = load_truth(value)
    p = robot_base(t, load_params() if params is None else params)
    for key, values in (("friction.asymmetry", t.friction.asymmetry),
                        ("friction.pulley_friction_per_N", t.friction.pulley_friction_per_N),
                        ("actuation.torque_constant_factor", t.actuation.torque_constant_factor)):
        _per(values, p.n_cables, 0.0, key)
    truth_params(p, t)
    return value


def _per(values: tuple[float, ...], n: int, default: float, key: str) -> tuple[float, ...]:
    if not values:
        return (default,) * n
    if len(values) != n:
        raise TruthError(f"{key}: {len(values)} values for {n} joints/cables")
    return tuple(values)


def robot_base(truth: RobotTruth, params: Params) -> Params:
    """The parameter set the robot of ``truth`` is built from: its ``robot_params`` file, else
    ``params`` (the controller's). :class:`TruthError` if that file does not load or describes a
    robot with other joints or cables than ``params`` (the controller could not drive it)."""
    if not truth.robot_params:
        return params
    try:
        base = load_params(None if truth.robot_params == "prototype" else truth.robot_params)
    except ParameterError as exc:
        raise TruthError(f"robot_params of truth {truth.name!r}: {exc}") from None
    if (base.n_joints, base.n_cables) != (params.n_joints, params.n_cables):
        raise TruthError(
            f"truth {truth.name!r} is a robot of {base.n_joints} joints and {base.n_cables} cables "
            f"({truth.robot_params}), the parameter set {params.name!r} one of {params.n_joints} and "
            f"{params.n_cables}: give a truth file for this robot (its robot_params naming its parameter file)")
    return base


def believed_differently(robot: Params, believed: Params) -> list[str]:
    """The dotted keys (``"springs.k_left"``, ``"cables.variable.k"``) whose values differ between
    the robot's parameter file and the set the controller is given (the name aside): what the
    controller believes otherwise than the twin's robot is built."""
    def flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in d.items():
            if isinstance(value, dict):
                out.update(flat(value, f"{prefix}{key}."))
            elif key != "name":
                out[f"{prefix}{key}"] = value
        return out

    a, b = flat(robot.to_dict()), flat(believed.to_dict())
    return sorted(k for k in a.keys() | b.keys() if a.get(k) != b.get(k))


def truth_params(params: Params, truth: str | RobotTruth = "model") -> Params:
    """The parameter set the twin integrates: the model with the truth's structural errors and
    cable damping (the other effects live in the simulator and integrator)."""
    t = load_truth(truth)
    if not (t.structure.enabled or t.cables.enabled):
        return params
    changes: dict[str, Any] = {"name": f"{params.name} ({t.name} truth)"}
    n = params.n_joints
    if t.structure.enabled:
        s = t.structure
        mass = _per(s.mass_factor, n, 1.0, "structure.mass_factor")
        b = params.bars
        changes["bars"] = msgspec.structs.replace(
            b, **{k: tuple(v * f for v, f in zip(getattr(b, k), mass)) for k in ("m_diagonal", "I_diagonal", "m_top", "I_top")})
        sp = params.springs
        kl = _per(s.spring_factor_left, n, 1.0, "structure.spring_factor_left")
        kr = _per(s.spring_factor_right, n, 1.0, "structure.spring_factor_right")
        dl = _per(s.l0_offset_m, n, 0.0, "structure.l0_offset_m")
        changes["springs"] = msgspec.structs.replace(
            sp, k_left=tuple(k * f for k, f in zip(sp.k_left, kl)), k_right=tuple(k * f for k, f in zip(sp.k_right, kr)),
            l0=tuple(v + d for v, d in zip(sp.l0, dl)))
        changes["geometry"] = msgspec.structs.replace(params.geometry, r=params.geometry.r + s.pulley_radius_offset_m)
    if t.cables.enabled:
        c = params.cables
        damping = (t.cables.damping_N_s_m,) * params.n_cables
        changes["cables"] = msgspec.structs.replace(
            c, linear=msgspec.structs.replace(c.linear, c_a=damping), variable=msgspec.structs.replace(c.variable, c_a=damping))
    return msgspec.structs.replace(params, **changes)
