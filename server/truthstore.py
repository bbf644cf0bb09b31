"""Truth files the console knows (issue 16): ``<data dir>/truths/<name>.toml``, e.g. written by
``xneck twin calibrate`` and uploaded with ``PUT /api/truths/{name}``.

A campaign request names its truth (``"model"``, ``"robot"`` or one of these names), never a path:
a name is checked against :data:`server.paramsets` 's name rule and resolved here, so a request
cannot make the twin read an arbitrary file (nor can an uploaded truth: its ``robot_params`` is
"prototype" or absent, never a path). Every file is validated as ``--truth FILE`` is
(twin/sim/truth.py) when it is stored and again when a campaign uses it.
"""

from __future__ import annotations

import threading
import tomllib
from pathlib import Path
from typing import Any

from bridge import toml_text
from bridge.archive import atomic_write
from server.paramsets import check_name
from twin.model.params import ParameterError
from twin.sim.truth import TRUTHS, RobotTruth, TruthError, load_truth, parse_truth

TRUTH_DIR = "truths"
MAX_TRUTH_BYTES = 64 * 1024  # the shipped robot truth is 7 kB


class UnknownTruth(KeyError):
    pass


def truth_label(truth: str) -> str:
    """How records name a resolved truth: "model", "robot", or the file's stem."""
    return truth if truth in TRUTHS else Path(truth).stem


class TruthStore:
    """Lists, validates, stores and resolves truth files; thread-safe."""

    def __init__(self, data_dir: Path) -> None:
        self.dir = Path(data_dir) / TRUTH_DIR
        self._lock = threading.Lock()

    def names(self) -> list[str]:
        files = sorted(p.stem for p in self.dir.glob("*.toml")) if self.dir.is_dir() else []
        return [*TRUTHS, *(n for n in files if n not in TRUTHS)]

    def path(self, name: str) -> Path:
        try:
            check_name(name)
        except ParameterError:
            raise UnknownTruth(name) from None
        path = self.dir / f"{name}.toml"
        if name in TRUTHS or not path.is_file():
            raise UnknownTruth(name)
        return path

    def resolve(self, name: str) -> str:
        """What the twin is started with for the truth ``name``: "model", "robot" or the absolute path
        of a stored file that loads; :class:`UnknownTruth` or :class:`TruthError` otherwise."""
        if name in TRUTHS:
            return name
        path = str(self.path(name).resolve())
        load_truth(path)
        return path

    @staticmethod
    def validate(body: bytes, source: str) -> RobotTruth:
        """A truth from uploaded bytes, or :class:`TruthError` naming the reason (hostile input)."""
        if len(body) > MAX_TRUTH_BYTES:
            raise TruthError(f"{source}: {len(body)} bytes, more than {MAX_TRUTH_BYTES} for a truth file")
        try:
            data = toml_text.loads(body.decode("utf-8"))
            truth = parse_truth(data, source)
            if truth.robot_params not in ("", "prototype"):  # a path: the console would read a file the request names
                raise TruthError(f"{source}: robot_params of an uploaded truth is \"prototype\" or absent (the "
                                 f"controller's parameter set), not a path, got {truth.robot_params!r}")
            return truth
        except UnicodeDecodeError:
            raise TruthError(f"{source}: not a text file (invalid UTF-8)") from None
        except tomllib.TOMLDecodeError as exc:
            raise TruthError(f"{source}: not a valid TOML file ({exc})") from None
        except RecursionError:  # tomllib recurses per nesting level: a hostile file, not a traceback
            raise TruthError(f"{source}: arrays or tables nested too deeply for a truth file") from None

    @staticmethod
    def check_new_name(name: str) -> str:
        """``name`` if a truth may be stored under it; :class:`TruthError` otherwise."""
        try:
            check_name(name)
        except ParameterError as exc:
            raise TruthError(str(exc).replace("parameter set", "truth")) from None
        if name in TRUTHS:
            raise TruthError(f"{name!r} is built in and cannot be replaced; upload under another name")
        return name

    def save(self, name: str, body: bytes) -> RobotTruth:
        self.check_new_name(name)
        truth = self.validate(body, f"{name}.toml")
        with self._lock:
            self.dir.mkdir(parents=True, exist_ok=True)
            atomic_write(self.dir / f"{name}.toml", body)
        return truth

    def summary(self, name: str) -> dict[str, Any]:
        """Name, effects on, and for a calibrated truth its fit (campaigns, date, residuals)."""
        truth = load_truth(name if name in TRUTHS else str(self.path(name)))
        out: dict[str, Any] = {"name": name, "effects": list(truth.enabled()), "builtin": name in TRUTHS}
        if truth.calibration is not None:
            c = truth.calibration
            out["calibration"] = {"campaigns": c.campaigns, "date": c.date, "base": c.base,
                                  "residual_rms": c.residual_rms, "fitted": c.fitted, "sigma": c.sigma}
        return out
