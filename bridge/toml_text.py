"""TOML text from outside (a REST upload, a bus message, a user's file) parsed with a bound on
what Python's ``tomllib`` does with it.

``tomllib`` takes time and memory quadratic in the parts of one dotted key: ``a.a.a…=1`` of 32 kB
took 1.8 s and about 1 GB, one of 120 kB a ``MemoryError`` after 7 s, on the console's event loop
(the e-stop's POST 7 s late; review of session 53). No file of this project has a key of more
than a few parts, so a key (or a table header) of more than :data:`MAX_KEY_PARTS` is refused
before ``tomllib`` sees it; nesting too deep for it is refused as well (``RecursionError`` is no
parse error a caller expects).
"""

from __future__ import annotations

import tomllib
from typing import Any

#: The most dot-separated parts a key or a table header may have. The project's files use 3 at
#: most (``[links.1]``, ``limits.f_max``); 64 costs ``tomllib`` microseconds.
MAX_KEY_PARTS = 64


def check_keys(text: str) -> None:
    """Raise ``tomllib.TOMLDecodeError`` (a ``ValueError``) naming the line of the first key or
    table header of more than :data:`MAX_KEY_PARTS` parts. Counts the dots before a line's
    first ``=`` (or inside its ``[...]`` header): a dot in a quoted key counts too, which only
    errs on the side of refusing a key no file here has."""
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.lstrip()
        if stripped.startswith("["):
            key = stripped.split("]", 1)[0]
        else:
            key = stripped.split("=", 1)[0] if "=" in stripped else ""
        if key.count(".") >= MAX_KEY_PARTS:
            raise tomllib.TOMLDecodeError(f"line {number}: a key of more than {MAX_KEY_PARTS} dotted parts "
                                          f"({key.count('.') + 1}): not a file of this software")


def loads(text: str) -> dict[str, Any]:
    """``tomllib.loads(text)`` once :func:`check_keys` passed; nesting too deep for the parser is a
    ``tomllib.TOMLDecodeError`` too."""
    check_keys(text)
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise tomllib.TOMLDecodeError("arrays or tables nested too deeply") from None


__all__ = ["MAX_KEY_PARTS", "check_keys", "loads"]
