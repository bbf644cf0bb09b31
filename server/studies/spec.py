"""What a study varies and how: ``--vary PATH=SPEC`` parsed, checked and expanded into runs.

A study is many headless twin runs of one kind (``control``, ``identification``, ``design``).
Each run gets concrete values for the varied parameter paths, a twin seed and a stable run id,
all decided here, on the client, before anything runs: the per-run function
(:func:`server.studies.run.run_one`) then depends on its arguments only, so a retried or resumed
run gives the same row.

SPEC (one scalar per run and path):

- ``10%``: a relative spread, the nominal value times a factor drawn from U(0.9, 1.1); for a vector
  (``friction.f_s``) every element is scaled by the same factor. The stored input is the factor.
- ``N(mu,sigma)``: a normal draw, sigma > 0; ``U(a,b)``: a uniform draw, a < b. A vector path gets
  the drawn value in every element; ``friction.f_s[2]`` (counted from 1, as the papers number
  cables and joints) varies one element.
- ``a:b:n``: a grid of n values from a to b (both included: n >= 2, or ``a:a:1`` for one value). Runs are the product of every grid
  with ``samples`` random draws of the other paths, for every law.

PATH is a parameter-file key (twin/model/params.py), or ``truth.<effect>.<key>`` for the truth file
(twin/sim/truth.py; needs ``--truth robot`` or a truth file). Every error names the path and the
reason, and is raised before anything runs (:class:`StudyError`).
"""

from __future__ import annotations

import hashlib
import json
import math
import operator
import re
import tomllib
from collections.abc import Collection, Container, Iterator, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, overload

import numpy as np

from bridge import toml_text
from bridge.small_file import read_input_file

KINDS = ("control", "identification", "design")
MAX_RUNS = 200_000  # a typo (a grid of 1e6 points) is refused before a cluster spends a day on it
_NUM = r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*"
_PATTERNS = {
    "relative": re.compile(rf"^{_NUM}%$"),
    "normal": re.compile(rf"^[Nn]\({_NUM},{_NUM}\)$"),
    "uniform": re.compile(rf"^[Uu]\({_NUM},{_NUM}\)$"),
    "grid": re.compile(rf"^{_NUM}:{_NUM}:\s*(\d+)\s*$"),
}
_PATH = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)*)(?:\[(\d+)\])?$")


class StudyError(ValueError):
    """A study definition is invalid; the message names the option or path and the reason."""


@dataclass(frozen=True)
class Vary:
    """One varied path: ``kind`` relative|normal|uniform|grid with its numbers ``a``, ``b`` (and ``n`` for a grid)."""

    path: str  # e.g. "friction.f_s", "truth.friction.static_ratio"
    index: int | None  # element counted from 1, or None for the whole value
    kind: str
    a: float
    b: float = 0.0
    n: int = 0

    @property
    def label(self) -> str:
        """The path as written, also the Parquet column suffix (``x:<label>``)."""
        return self.path if self.index is None else f"{self.path}[{self.index}]"

    @property
    def text(self) -> str:
        spec = {"relative": f"{self.a:g}%", "normal": f"N({self.a:g},{self.b:g})", "uniform": f"U({self.a:g},{self.b:g})",
                "grid": f"{self.a:g}:{self.b:g}:{self.n}"}[self.kind]
        return f"{self.label}={spec}"

    def grid(self) -> np.ndarray:
        return np.linspace(self.a, self.b, self.n)

    def draw(self, rng: np.random.Generator) -> float:
        if self.kind == "relative":
            return float(rng.uniform(1.0 - self.a / 100.0, 1.0 + self.a / 100.0))
        if self.kind == "normal":
            return float(rng.normal(self.a, self.b))
        return float(rng.uniform(self.a, self.b))

    def extremes(self) -> tuple[float, ...]:
        """Values checked against the parameter file before anything runs (a normal's mean only: its tails are unbounded)."""
        if self.kind == "relative":
            return (1.0 - self.a / 100.0, 1.0 + self.a / 100.0)
        if self.kind == "normal":
            return (self.a,)
        if self.kind == "uniform":
            return (self.a, self.b)
        return (self.a, self.b)


def parse_vary(text: str) -> Vary:
    """``PATH=SPEC`` → :class:`Vary`; :class:`StudyError` saying what is wrong otherwise."""
    if "=" not in text:
        raise StudyError(f"--vary {text!r}: write PATH=SPEC, e.g. friction.f_s=10%")
    raw_path, spec = (s.strip() for s in text.split("=", 1))
    m = _PATH.fullmatch(raw_path)
    if not m:
        raise StudyError(f"--vary {text!r}: {raw_path!r} is not a dotted parameter path (e.g. cables.variable.k or friction.f_s[2])")
    path, index = m.group(1), int(m.group(2)) if m.group(2) else None
    if index is not None and index < 1:
        raise StudyError(f"--vary {text!r}: elements are counted from 1")
    where = f"--vary {text!r}"
    for kind, pattern in _PATTERNS.items():
        g = pattern.fullmatch(spec)
        if not g:
            continue
        a, b = float(g.group(1)), float(g.group(2)) if kind != "relative" else 0.0
        if not all(math.isfinite(v) for v in (a, b)):
            raise StudyError(f"{where}: numbers must be finite")
        if kind == "relative" and not 0 < a < 100:
            raise StudyError(f"{where}: a relative spread must be in (0, 100) %, got {a:g} %")
        if kind == "normal" and not b > 0:
            raise StudyError(f"{where}: sigma must be > 0, got {b:g}")
        if kind == "uniform" and not a < b:
            raise StudyError(f"{where}: U(a,b) needs a < b, got a = {a:g}, b = {b:g}")
        n = 0
        if kind == "grid":
            digits = g.group(3).lstrip("0") or "0"
            # a grid alone past the study limit is refused before np.linspace allocates it (10^11 points
            # asked for 745 GiB); a count too long for int() (4300 digits) is past it too
            if len(digits) > len(str(MAX_RUNS)) or int(digits) > MAX_RUNS:
                shown = digits if len(digits) <= 30 else f"a {len(digits)}-digit number of"
                raise StudyError(f"{where}: the grid has {shown} points, more than the limit of {MAX_RUNS} runs")
            n = int(digits)
        if kind == "grid" and n < 1:
            raise StudyError(f"{where}: a grid a:b:n needs n >= 1 points")
        if kind == "grid" and n == 1 and a != b:  # np.linspace gave a alone: b silently never ran
            raise StudyError(f"{where}: a grid a:b:n includes both ends, and one point cannot include both ends "
                             f"{a:g} and {b:g}: use n >= 2, or {a:g}:{a:g}:1 for the one value")
        if kind == "grid" and n > 1 and a == b:
            raise StudyError(f"{where}: a grid a:b:n of n > 1 points needs a != b (a:a:1 is the one value)")
        return Vary(path, index, kind, a, b, n)
    raise StudyError(f"{where}: SPEC {spec!r} is none of: 10% (relative spread), N(mu,sigma), U(a,b), a:b:n (grid)")


@dataclass(frozen=True)
class Study:
    """A whole study as the flags and the study file say it (everything that decides its rows).

    ``model_follows``: the controller's model gets the sampled values too (a perfectly identified
    robot); by default only the twin does, so a run measures a law against a robot that is off
    from the model it holds, the robustness question.
    """

    kind: str = "control"
    samples: int = 1
    seed: int = 0
    vary: tuple[str, ...] = ()
    laws: tuple[int, ...] = (2,)
    no_pulleys: bool = False
    trajectory: str = "control_test"  # an identification study's default is "identification" (§5.2.2)
    truth: str = "model"  # an identification study's default is "robot" (issue 17: never the controller's own model)
    alpha_ip: str = "noise"
    settle_s: float = 1.0
    model_follows: bool = False
    params_file: str | None = None
    set: tuple[str, ...] = ()  # --set overrides of the base parameter file
    design_configurations: int = 2000  # design: random configurations per design (within the joint limit)
    estimator: str = "auto"  # identification: Table 2's estimator (twin.identification.options.VARIABLE_ESTIMATORS)

    def varies(self) -> tuple[Vary, ...]:
        return tuple(parse_vary(v) for v in self.vary)

    def uses(self) -> tuple[str, ...]:
        """The fields this kind of study runs on (:data:`KIND_FIELDS`; every field for an unknown kind)."""
        return KIND_FIELDS.get(self.kind, tuple(Study.__dataclass_fields__))

    def canonical(self) -> dict[str, Any]:
        """The study as study.json and summary.json record it: the fields its kind uses only (a
        design study showed laws and a trajectory it never ran, user audit)."""
        out = {k: v for k, v in asdict(self).items() if k in self.uses()}
        if out.get("estimator") == "auto":  # the default is left out: a study defined before the field keeps its digest
            del out["estimator"]
        return out

    def digest(self) -> str:
        """Identity of the study's rows: a study directory holds one study and refuses another.
        It depends on the fields its kind uses only; the others enter at their defaults, as
        constants, so that the digests of studies recorded before (every field hashed, the
        unused ones at their defaults from the command line) are kept and their directories resume."""
        doc = {**asdict(self), **{k: v for k, v in _DEFAULTS.items() if k not in self.uses()}}
        if doc["estimator"] == "auto":
            del doc["estimator"]
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


#: The fields each kind of study runs on. Design studies compute statics of the parameter set: no
#: twin, law, trajectory or truth. Only identification studies use an estimator; only design ones
#: a number of configurations.
_COMMON_FIELDS = ("kind", "samples", "seed", "vary", "params_file", "set")
_CAMPAIGN_FIELDS = ("laws", "no_pulleys", "trajectory", "truth", "alpha_ip", "settle_s", "model_follows")
KIND_FIELDS: dict[str, tuple[str, ...]] = {
    "control": _COMMON_FIELDS + _CAMPAIGN_FIELDS,
    "identification": _COMMON_FIELDS + _CAMPAIGN_FIELDS + ("estimator",),
    "design": _COMMON_FIELDS + ("design_configurations",),
}
_DEFAULTS: dict[str, Any] = asdict(Study())


def for_kind(study: Study) -> Study:
    """``study`` with the fields its kind does not use at their defaults: two studies that run
    alike are equal (the console sends a design study its truth select's value)."""
    return replace(study, **{k: v for k, v in _DEFAULTS.items() if k not in study.uses()})


@dataclass(frozen=True)
class RunSpec:
    """One run: its id, law (0 for design), twin seed and the value of every varied path."""

    run_id: str
    law: int
    seed: int
    values: dict[str, float] = field(default_factory=dict)  # Vary.label -> value (a factor for '%')


def study_from(kind: str, file: Path | None = None, **flags: Any) -> Study:
    """The study of a study file (TOML, keys as :class:`Study`'s fields) with the flags that were
    given (not None) on top; checked with :func:`check`'s syntax part."""
    data: dict[str, Any] = {}
    if file is not None:
        try:
            data = toml_text.loads(read_input_file(file).decode("utf-8"))  # a FIFO or a device: refused, not read
        except OSError as exc:
            raise StudyError(f"study file {str(file)!r}: {exc.strerror or exc}") from None
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise StudyError(f"study file {str(file)!r}: {exc}") from None
        unknown = set(data) - set(Study.__dataclass_fields__)
        if unknown:
            raise StudyError(f"study file {str(file)!r}: unknown keys {sorted(unknown)} "
                             f"(known: {', '.join(Study.__dataclass_fields__)})")
        data.setdefault("kind", kind)
        if data["kind"] != kind:
            raise StudyError(f"study file {str(file)!r} is a {data['kind']!r} study, not {kind!r}")
    for key, value in flags.items():
        if value is None or value == ():
            continue
        if key == "vary":  # flags add to the file's
            data["vary"] = (*data.get("vary", ()), *value)
        else:
            data[key] = value
    data["kind"] = kind
    if kind != "design":  # a design study has no trajectory
        data.setdefault("trajectory", "identification" if kind == "identification" else "control_test")
    if kind == "identification":
        # on the model truth an identification finds the parameter file it started from (the
        # identity check): the robot truth, as identification campaigns default to (truth audit
        # of 2026-12-01: studies alone defaulted to the model)
        data.setdefault("truth", "robot")
        data["laws"] = (1,)  # the §5.2.2 campaign runs law 1 (server.cli.campaign): its rows say so
    for key in ("vary", "laws", "set"):
        if key in data:
            data[key] = tuple(data[key])
    try:
        study = Study(**data)
    except TypeError as exc:
        raise StudyError(f"study: {exc}") from None
    return for_kind(_checked_syntax(study))


def _checked_syntax(s: Study) -> Study:
    if s.kind not in KINDS:
        raise StudyError(f"study kind {s.kind!r}: choose {', '.join(KINDS)}")
    if not isinstance(s.samples, int) or s.samples < 1:
        raise StudyError(f"--samples must be an integer >= 1, got {s.samples!r}")
    if not isinstance(s.seed, int) or s.seed < 0:
        raise StudyError(f"--seed must be an integer >= 0, got {s.seed!r}")
    if not s.laws or any(law not in (1, 2, 3) for law in s.laws) or len(set(s.laws)) != len(s.laws):
        raise StudyError(f"--law: each of 1, 2, 3 at most once, got {list(s.laws)}")
    if not (isinstance(s.settle_s, int | float) and 0 <= s.settle_s <= 60):
        raise StudyError(f"settle_s must be in [0, 60] s, got {s.settle_s!r}")
    if not (isinstance(s.design_configurations, int) and 10 <= s.design_configurations <= 1_000_000):
        raise StudyError(f"design_configurations must be an integer in [10, 1e6], got {s.design_configurations!r}")
    from twin.sim.sensors import ALPHA_IP_KINDS

    if s.alpha_ip not in ALPHA_IP_KINDS:  # else every run failed, after the cluster had started
        raise StudyError(f"--alpha-ip {s.alpha_ip!r}: choose {' or '.join(ALPHA_IP_KINDS)}")
    from twin.identification.options import VARIABLE_ESTIMATORS

    if s.estimator not in VARIABLE_ESTIMATORS:
        raise StudyError(f"--estimator {s.estimator!r}: choose {', '.join(VARIABLE_ESTIMATORS)}")
    if s.estimator != "auto" and s.kind != "identification":
        raise StudyError(f"--estimator applies to identification studies, not to a {s.kind} study")
    labels = [v.label for v in s.varies()]
    if len(set(labels)) != len(labels):
        raise StudyError(f"--vary: a path is varied twice ({', '.join(sorted({x for x in labels if labels.count(x) > 1}))})")
    if s.kind == "design" and any(label.startswith("truth.") for label in labels):
        raise StudyError("--vary truth.*: a design study computes the parameter set's statics, it runs no twin "
                         "and so no truth: vary parameter-file paths")
    if "geometry.n_joints" in labels and s.kind != "design":
        raise StudyError("--vary geometry.n_joints: only a design study changes the number of joints "
                         "(a control or identification trajectory is written for the prototype's joints)")
    n_runs = run_count(s)
    if n_runs > MAX_RUNS:
        laws = 1 if s.kind == "design" else len(s.laws)
        points = n_runs // (laws * s.samples)
        raise StudyError(f"the study has {n_runs} runs ({laws} law{'s' if laws > 1 else ''} × {points} grid "
                         f"point{'s' if points > 1 else ''} × {s.samples} sample{'s' if s.samples > 1 else ''}), "
                         f"more than the limit of {MAX_RUNS}: use fewer samples or coarser grids")
    return s


def run_count(s: Study) -> int:
    """How many runs :func:`expand` gives, counted without building them: the limit is checked on
    this, so a count of 10^12 is refused at once instead of after filling the memory."""
    laws = 1 if s.kind == "design" else len(s.laws)
    return laws * math.prod(v.n for v in s.varies() if v.kind == "grid") * s.samples


def expand(s: Study) -> StudyRuns:
    """Every run of the study in a fixed order: law × grid point × sample, as a view that computes
    each run from its position (:class:`StudyRuns`), never a list of them all. Random draws depend on
    (seed, grid point, sample) only, so every law meets the same robots (common random numbers)."""
    return StudyRuns(s)


_RUN_ID = re.compile(r"^(?:L([1-9])-)?g(\d{4,})-s(\d{5,})$")


class StudyRuns(Sequence[RunSpec]):
    """The runs of a study, the k-th computed from k alone: as a list, a study at the limit (200,000
    runs) held 83 MB of run descriptions, built in 3.7 s before its first run was submitted.

    Position k is (law, grid point g, sample) in that order of nesting, and g the grid point's index
    in the product of the grid axes, the last axis fastest (itertools.product's order, numpy's
    ``unravel_index`` in C order); each run is then what the eager expansion built: its values drawn
    from ``SeedSequence([seed, g, sample])``, the twin seed from the same sequence, the run id
    ``[L<law>-]g<g:04d>-s<sample:05d>``. Held: the grid axes' values (each at most :data:`MAX_RUNS`),
    not their product. Counting, a window of runs, resuming (:meth:`unfinished`) and a page
    (``runs[a:b]``, a list of that page) cost what they touch."""

    def __init__(self, study: Study) -> None:
        varies = study.varies()
        self.study = study
        self._grids = tuple(v for v in varies if v.kind == "grid")
        self._randoms = tuple(v for v in varies if v.kind != "grid")
        self._axes = tuple(v.grid() for v in self._grids)  # each axis's values; their product is never built
        self._shape = tuple(v.n for v in self._grids)
        self._laws = (0,) if study.kind == "design" else tuple(study.laws)
        self._samples = study.samples
        self.points = math.prod(self._shape)  # grid points (1 without a grid)
        self._len = len(self._laws) * self.points * self._samples  # = run_count(study), Python ints: no overflow

    def __len__(self) -> int:
        return self._len

    def __repr__(self) -> str:
        return f"StudyRuns({self._len} runs of {self.study.kind} study {self.study.digest()})"

    def __eq__(self, other: object) -> bool:
        if isinstance(other, StudyRuns):  # the runs are a function of the study alone
            return self.study == other.study
        if isinstance(other, Sequence) and not isinstance(other, str | bytes):
            return len(self) == len(other) and all(a == b for a, b in zip(self, other))
        return NotImplemented

    def __hash__(self) -> int:
        return hash(self.study)

    @overload
    def __getitem__(self, k: int) -> RunSpec: ...

    @overload
    def __getitem__(self, k: slice) -> list[RunSpec]: ...

    def __getitem__(self, k: int | slice) -> RunSpec | list[RunSpec]:
        if isinstance(k, slice):  # a page: the runs it spans only
            return [self._run(i) for i in range(self._len)[k]]
        return self._run(self._index(k))

    def __iter__(self) -> Iterator[RunSpec]:
        return (self._run(i) for i in range(self._len))

    def _index(self, k: int) -> int:
        k = operator.index(k)
        i = k + self._len if k < 0 else k
        if not 0 <= i < self._len:
            raise IndexError(f"run {k} of a study of {self._len} runs")
        return i

    def _slot(self, i: int) -> tuple[int, int, int]:
        """(law, grid point, sample) of position ``i`` (0 <= i < len)."""
        law, rest = divmod(i, self.points * self._samples)
        g, k = divmod(rest, self._samples)
        return self._laws[law], g, k

    def __contains__(self, run: object) -> bool:  # by the run's id: Sequence's would build every run
        if not isinstance(run, RunSpec):
            return False
        i = self.position(run.run_id)
        return i is not None and self._run(i) == run

    def index(self, run: object, start: int = 0, stop: int | None = None) -> int:
        i = self.position(run.run_id) if isinstance(run, RunSpec) else None
        if i is None or self._run(i) != run or i not in range(self._len)[start:stop]:
            raise ValueError(f"{run!r} is not a run of this study here")
        return i

    def count(self, run: object) -> int:
        return int(run in self)  # run ids are unique

    def run_id(self, k: int) -> str:
        """The id of run ``k`` without drawing its values (what resuming compares)."""
        law, g, sample = self._slot(self._index(k))
        return f"L{law}-g{g:04d}-s{sample:05d}" if law else f"g{g:04d}-s{sample:05d}"

    def position(self, run_id: str) -> int | None:
        """The position of the run with this id, None when the study has no such run."""
        m = _RUN_ID.fullmatch(run_id)
        if m is None:
            return None
        law, g, sample = int(m.group(1) or 0), int(m.group(2)), int(m.group(3))
        if law not in self._laws or not (g < self.points and sample < self._samples):
            return None
        i = (self._laws.index(law) * self.points + g) * self._samples + sample
        return i if self.run_id(i) == run_id else None  # the id as written: no other zero padding

    def count_finished(self, done: Collection[str]) -> int:
        """How many of this study's runs ``done`` names (ids of another study or none are not counted)."""
        return sum(1 for run_id in done if self.position(run_id) is not None)

    def unfinished(self, done: Container[str]) -> Iterator[RunSpec]:
        """The runs whose ids ``done`` does not hold, in order, each built when it is taken."""
        return (self._run(i) for i in range(self._len) if self.run_id(i) not in done)

    def _run(self, i: int) -> RunSpec:
        law, g, sample = self._slot(i)
        point, rest = [0.0] * len(self._axes), g
        for a in reversed(range(len(self._axes))):  # g → one index per axis, the last fastest (unravel_index, C order)
            rest, j = divmod(rest, self._shape[a])  # Python ints: a product past 2**63 does not wrap
            point[a] = float(self._axes[a][j])  # the value the eager grid().tolist() gave
        seq = np.random.SeedSequence([self.study.seed, g, sample])
        rng = np.random.default_rng(seq)
        values = {v.label: x for v, x in zip(self._grids, point)}
        values.update({v.label: v.draw(rng) for v in self._randoms})
        twin_seed = int(seq.generate_state(1)[0])
        prefix = f"L{law}-" if law else ""
        return RunSpec(f"{prefix}g{g:04d}-s{sample:05d}", law, twin_seed, values)
