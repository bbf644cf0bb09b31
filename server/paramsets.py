"""Parameter sets of the console: the shipped prototype plus uploaded TOML files, one active.

Files live in ``<data_dir>/params/<name>.toml``; the active name in ``<data_dir>/params/active``.
An upload is validated exactly as ``--params FILE`` is (:func:`twin.model.params.params_from_dict`),
so a set the console accepts is one every process accepts. The built-in set ``prototype_3x``
cannot be replaced.

A set is chosen active only if it loads. One that no longer does when the console starts (edited
by hand, another encoding, a stricter loader after an update) is not used: the console runs on
``prototype_3x`` and :attr:`ParameterStore.fallback` says which set was named and why, while the
``active`` file keeps the operator's choice for when the set is repaired.
"""

from __future__ import annotations

import re
import threading
import tomllib
from pathlib import Path

from bridge import toml_text
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


# What loading a file can raise besides ParameterError: a loader that does not yet name every
# fault (undecodable bytes, nesting deeper than the parser's recursion) must not crash a route.
LOAD_FAULTS = (UnicodeDecodeError, RecursionError, ValueError)


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
        self.fallback: tuple[str, str] | None = None  # (set named active, why it does not load) while prototype_3x stands in

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
        """Raises :class:`UnknownParameterSet`, or :class:`ParameterError` naming the file and why it
        does not load."""
        path = self.path(name)
        try:
            return load_params(path)
        except ParameterError:
            raise
        except LOAD_FAULTS as exc:
            reason = "nested too deeply" if isinstance(exc, RecursionError) else f"{type(exc).__name__}: {exc}"
            raise ParameterError(f"{path}: does not load ({reason})") from None

    def text(self, name: str) -> str:
        """The file's TOML text. Raises :class:`UnknownParameterSet`, or :class:`ParameterError` when
        the file is not UTF-8 text."""
        p = self.path(name)
        if p is None:
            return load_params(None).to_toml()
        try:
            return p.read_bytes().decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ParameterError(f"{p.name}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None

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
            data = toml_text.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ParameterError(f"{source}: not a valid TOML file ({exc})") from None
        except RecursionError:  # tomllib recurses per nesting level: a hostile file, not a traceback
            raise ParameterError(f"{source}: arrays or tables nested too deeply (a parameter file nests at most "
                                 f"{MAX_DEPTH} levels)") from None
        if _depth(data) > MAX_DEPTH:
            raise ParameterError(f"{source}: arrays or tables nested too deeply (at most {MAX_DEPTH} levels)")
        return params_from_dict(data, source)

    def save(self, name: str, text: str | bytes, *, replace: bool = True) -> Params:
        """Validate and store ``text`` as ``name``. ``replace=False``: :class:`FileExistsError` if a
        set of that name exists (checked under the store's lock: two requests cannot both create it)."""
        check_name(name)
        if name == BUILTIN:
            raise ParameterError(f"{BUILTIN!r} is built in and cannot be replaced; upload under another name")
        params = self.validate(text, f"{name}.toml")
        raw = text if isinstance(text, bytes) else text.encode()
        with self._lock:
            if not replace and (self.dir / f"{name}.toml").exists():
                raise FileExistsError(f"a parameter set {name!r} exists: choose another name")
            atomic_write(self.dir / f"{name}.toml", raw)
        return params

    def delete(self, name: str) -> None:
        """Raises :class:`UnknownParameterSet`, or :class:`ParameterError` for the built-in or the
        active set. Under the store's lock, as :meth:`set_active`: a set being chosen active and
        deleted at once was both (the active file then named a set that no longer existed), and
        two deletes at once made the second a storage fault (audit of 2026-11-27)."""
        with self._lock:
            p = self.path(name)
            if p is None:
                raise ParameterError(f"{BUILTIN!r} is built in and cannot be deleted")
            if name == self.active():
                raise ParameterError(f"{name!r} is the active parameter set; choose another one first")
            p.unlink()

    def _named(self) -> str:
        """The name the ``active`` file holds (``prototype_3x`` without one)."""
        f = self.dir / "active"
        if not f.is_file():
            return BUILTIN
        try:
            return f.read_bytes().decode("utf-8").strip()
        except UnicodeDecodeError:
            return ""  # not a name check_name accepts: active() falls back

    def active(self) -> str:
        if self.fallback is not None:
            return BUILTIN
        name = self._named()
        try:
            self.path(name)
        except (UnknownParameterSet, ParameterError):
            return BUILTIN
        return name

    def load_active(self) -> tuple[str, Params]:
        """(name, parameters) of the active set, at start-up. A set named active that does not load
        is replaced by ``prototype_3x`` until another is chosen; :attr:`fallback` says why."""
        named = self._named()
        try:
            return named, self.load(named)
        except UnknownParameterSet:
            self.fallback = (named, f"no parameter set {named!r} in {self.dir}")
        except ParameterError as exc:
            self.fallback = (named, str(exc))
        return BUILTIN, self.load(BUILTIN)

    def active_status(self) -> dict[str, str | None]:
        """The active set, and which set is named active instead and why it is not used (None, None
        when it is)."""
        named, reason = self.fallback or (None, None)
        return {"active": self.active(), "fallback_from": named, "reason": reason}

    def set_active(self, name: str) -> None:
        """Raises :class:`UnknownParameterSet`, or :class:`ParameterError` with the loader's message:
        a set that does not load is never chosen (the console could not start on it)."""
        with self._lock:  # not while it is deleted (:meth:`delete`)
            self.load(name)
            atomic_write(self.dir / "active", (name + "\n").encode())
            self.fallback = None
