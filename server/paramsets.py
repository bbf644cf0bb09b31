"""Parameter sets of the console: the shipped prototype plus uploaded TOML files, one active.

Files live in ``<data_dir>/params/<name>.toml``; the active name in ``<data_dir>/params/active``.
An upload is validated exactly as ``--params FILE`` is (:func:`twin.model.params.params_from_dict`),
so a set the console accepts is one every process accepts. The built-in set ``prototype_3x``
cannot be replaced.
"""

from __future__ import annotations

import re
import threading
import tomllib
from pathlib import Path

from bridge.archive import atomic_write
from twin.model.params import ParameterError, Params, load_params, params_from_dict

BUILTIN = "prototype_3x"
_NAME = re.compile(r"^[A-Za-z0-9_.\-]{1,64}$")
MAX_UPLOAD_BYTES = 256 * 1024
MAX_DEPTH = 16  # tables and arrays in a parameter file nest 3 deep; deeper is not a parameter file


def _depth(value: object) -> int:
    """Nesting depth of parsed TOML, without recursion."""
    deepest, stack = 0, [(value, 1)]
    while stack:
        v, d = stack.pop()
        deepest = max(deepest, d)
        if d > MAX_DEPTH:
            break
        children = v.values() if isinstance(v, dict) else v if isinstance(v, list) else ()
        stack.extend((c, d + 1) for c in children if isinstance(c, (dict, list)))
    return deepest


class UnknownParameterSet(KeyError):
    pass


def check_name(name: str) -> str:
    if not _NAME.fullmatch(name) or name.startswith("."):
        raise ParameterError(f"parameter set name {name!r} must be 1-64 letters, digits, '_', '.', '-'")
    return name


class ParameterStore:
    """Lists, reads, validates and stores parameter sets; thread-safe."""

    def __init__(self, data_dir: Path) -> None:
        self.dir = Path(data_dir) / "params"
        self.dir.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()

    def names(self) -> list[str]:
        return [BUILTIN] + sorted(p.stem for p in self.dir.glob("*.toml") if p.stem != BUILTIN)

    def path(self, name: str) -> Path | None:
        """File of a set (None for the built-in one). Raises :class:`UnknownParameterSet`."""
        if name == BUILTIN:
            return None
        check_name(name)
        p = self.dir / f"{name}.toml"
        if not p.is_file():
            raise UnknownParameterSet(name)
        return p

    def load(self, name: str) -> Params:
        return load_params(self.path(name))

    def text(self, name: str) -> str:
        p = self.path(name)
        return load_params(None).to_toml() if p is None else p.read_text()

    @staticmethod
    def validate(text: str | bytes, source: str = "upload") -> Params:
        """Parse and validate TOML text; :class:`ParameterError` names the key and the reason."""
        if isinstance(text, bytes):
            if len(text) > MAX_UPLOAD_BYTES:
                raise ParameterError(f"{source}: {len(text)} bytes, more than {MAX_UPLOAD_BYTES} for a parameter file")
            try:
                text = text.decode("utf-8")
            except UnicodeDecodeError:
                raise ParameterError(f"{source}: not a text file (invalid UTF-8)") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ParameterError(f"{source}: not a valid TOML file ({exc})") from None
        except RecursionError:  # tomllib recurses per nesting level: a hostile file, not a traceback
            raise ParameterError(f"{source}: arrays or tables nested too deeply (a parameter file nests at most "
                                 f"{MAX_DEPTH} levels)") from None
        if _depth(data) > MAX_DEPTH:
            raise ParameterError(f"{source}: arrays or tables nested too deeply (at most {MAX_DEPTH} levels)")
        return params_from_dict(data, source)

    def save(self, name: str, text: str | bytes) -> Params:
        check_name(name)
        if name == BUILTIN:
            raise ParameterError(f"{BUILTIN!r} is built in and cannot be replaced; upload under another name")
        params = self.validate(text, f"{name}.toml")
        raw = text if isinstance(text, bytes) else text.encode()
        with self._lock:
            atomic_write(self.dir / f"{name}.toml", raw)
        return params

    def delete(self, name: str) -> None:
        p = self.path(name)
        if p is None:
            raise ParameterError(f"{BUILTIN!r} is built in and cannot be deleted")
        if name == self.active():
            raise ParameterError(f"{name!r} is the active parameter set; choose another one first")
        p.unlink()

    def active(self) -> str:
        f = self.dir / "active"
        name = f.read_text().strip() if f.is_file() else BUILTIN
        try:
            self.path(name)
        except (UnknownParameterSet, ParameterError):
            return BUILTIN
        return name

    def set_active(self, name: str) -> None:
        self.path(name)  # raises if unknown
        with self._lock:
            atomic_write(self.dir / "active", (name + "\n").encode())
