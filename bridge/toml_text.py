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

import re
import tomllib
from typing import Any

#: The most dot-separated parts a key or a table header may have. The project's files use 3 at
#: most (``[links.1]``, ``limits.f_max``); 64 costs ``tomllib`` microseconds.
MAX_KEY_PARTS = 64


#: One token of the scan: a quoted string (basic or literal, on one line), a bare word, a dot,
#: spaces, a comment, a line's end or any other character. Each alternative ends at a quote, a
#: line's end or the first character outside its class: one pass, linear in the text.
_TOKEN = re.compile(r'''"(?:[^"\\\n]|\\.)*"|'[^'\n]*'|[A-Za-z0-9_-]+|\.|[ \t]+|#[^\n]*|\n|.''')


def check_keys(text: str) -> None:
    """Raise ``tomllib.TOMLDecodeError`` (a ``ValueError``) naming the line of the first chain of
    more than :data:`MAX_KEY_PARTS` parts (bare words or quoted strings) joined by dots, wherever
    it stands: a key, a table header, an inline table's key. The text is scanned as tokens, so a
    quoted part holding ``=`` or ``]`` counts as one part (splitting the line at its first ``=``
    had let ``"=".a.a…`` through: review of session 53's diff). A chain in a value counts too
    (``1.5`` is two parts): it only errs on the side of refusing what no file here has."""
    parts, line, dot = 0, 1, False
    for match in _TOKEN.finditer(text):
        token = match.group()
        first = token[0]
        if first == "." and len(token) == 1:
            dot = parts > 0
            continue
        if first in " \t" or first == "#":
            continue
        if first == "\n":
            line += 1
            parts, dot = 0, False  # a key never spans lines
            continue
        if (first in "\"'" and len(token) > 1) or first.isalnum() or first in "_-":
            parts = parts + 1 if dot else 1
            dot = False
            if parts > MAX_KEY_PARTS:
                raise tomllib.TOMLDecodeError(f"line {line}: a key of more than {MAX_KEY_PARTS} dotted parts: "
                                              "not a file of this software")
            continue
        parts, dot = 0, False


def loads(text: str) -> dict[str, Any]:
    """``tomllib.loads(text)`` once :func:`check_keys` passed; nesting too deep for the parser is a
    ``tomllib.TOMLDecodeError`` too."""
    check_keys(text)
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise tomllib.TOMLDecodeError("arrays or tables nested too deeply") from None


__all__ = ["MAX_KEY_PARTS", "check_keys", "loads"]
