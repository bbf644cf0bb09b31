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

#: The most dot-separated parts a key or a table header may have, and a key and the header of its
#: table together. The project's files use 3 at most (``[links.1]``, ``limits.f_max``); tomllib's
#: cost grows with the header's parts and the key's together (256 kB of 64-part keys under a
#: 64-part header parsed in 6 s: review of this session's diff); at these bounds 256 kB of 8-part
#: keys under a 16-part header parses in about 1 s, 64 kB (a bus message's most) in 0.18 s
#: (``.venv/bin/python benchmarks/toml_guard.py``, 2026-12-01).
MAX_KEY_PARTS = 16
MAX_TABLE_KEY_PARTS = 24


#: One token of the scan: a multi-line string (basic or literal, one token across its lines), a
#: one-line string (unclosed: the rest of its line), a bare word, a dot, spaces, a comment, a
#: line's end or any other character. Possessive repeats: an alternative never re-scans what it
#: took (an unclosed quote had each later quote of its line scan to the line's end again,
#: quadratic: 256 kB of '"\\' took 617 s), so the scan is linear in the text. A multi-line string
#: is one token: read as quotes and words, a key after one on its closing line was taken for
#: part of a string or a comment (review of this session's diff).
_TOKEN = re.compile("|".join((
    r'"""(?:[^"\\]|\\[\s\S]|"(?!""))*+"""(?:""?)?',  # a multi-line basic string (up to two quotes more: content)
    r"'''(?:[^']|'(?!''))*+'''(?:''?)?",  # a multi-line literal string
    r'"(?:[^"\\\n]|\\.)*+"?',  # a basic string, or the rest of its line if unclosed
    r"'[^'\n]*+'?",  # a literal string, likewise
    r"[A-Za-z0-9_-]++", r"\.", r"[ \t]++", r"#[^\n]*+", r"\n", r".",
)))


def _refuse(line: int, what: str) -> tomllib.TOMLDecodeError:
    return tomllib.TOMLDecodeError(f"line {line}: {what}: not a file of this software")


def check_keys(text: str) -> None:
    """Raise ``tomllib.TOMLDecodeError`` (a ``ValueError``) naming the line of the first chain of
    more than :data:`MAX_KEY_PARTS` parts (bare words or quoted strings) joined by dots, wherever
    it stands: a key, a table header, an inline table's key; or of a key whose parts and its
    table header's are more than :data:`MAX_TABLE_KEY_PARTS`. The text is scanned as tokens, so a
    quoted part holding ``=`` or ``]`` counts as one part (splitting the line at its first ``=``
    had let ``"=".a.a…`` through: review of session 53's diff). A chain in a value counts too
    (``1.5`` is two parts): it only errs on the side of refusing what no file here has."""
    parts, line, dot = 0, 1, False
    header = 0  # the parts of the current table's header
    line_start, in_header = True, False
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
            parts, dot, line_start, in_header = 0, False, True, False  # a key never spans lines
            continue
        if token.startswith(('"""', "'''")):  # a value: no key part
            line += token.count("\n")
            parts, dot, line_start = 0, False, False
            continue
        if first == "[" and line_start:  # a table header (or an array's row: counted alike, tighter)
            in_header, line_start, parts, dot = True, False, 0, False
            continue
        line_start = False
        if (first in "\"'" and len(token) > 1) or first.isalnum() or first in "_-":
            parts = parts + 1 if dot else 1
            dot = False
            if parts > MAX_KEY_PARTS:
                raise _refuse(line, f"a key of more than {MAX_KEY_PARTS} dotted parts")
            if in_header:
                header = parts
            elif header + parts > MAX_TABLE_KEY_PARTS:
                raise _refuse(line, f"a key of {parts} dotted parts under a table header of {header}, more than "
                                    f"{MAX_TABLE_KEY_PARTS} dotted parts in all")
            continue
        if first == "]" and in_header:
            in_header = False
        parts, dot = 0, False


def loads(text: str) -> dict[str, Any]:
    """``tomllib.loads(text)`` once :func:`check_keys` passed; nesting too deep for the parser is a
    ``tomllib.TOMLDecodeError`` too."""
    check_keys(text)
    try:
        return tomllib.loads(text)
    except RecursionError:
        raise tomllib.TOMLDecodeError("arrays or tables nested too deeply") from None


__all__ = ["MAX_KEY_PARTS", "MAX_TABLE_KEY_PARTS", "check_keys", "loads"]
