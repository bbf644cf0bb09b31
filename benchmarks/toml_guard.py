"""The TOML key guard (``bridge.toml_text.check_keys``) on what a bus peer or a token holder may
send: its scan must be linear in the text whatever the text, and the keys it lets through cheap
for ``tomllib``.

Times, for 64 kB (a campaign request's ``parameters_toml`` at most) and 256 kB (a REST upload at
most) of each hostile pattern, the guard's scan (refused or not), and, for texts the guard lets
through, ``tomllib.loads``; the baseline, in the same process, is ``tomllib.loads`` of the
project's own parameter file (``twin/model/prototype_3x.toml``, about 3 kB). Prints median and p99
over the repeats and the ratio of each median to the baseline's.
Run: ``.venv/bin/python benchmarks/toml_guard.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import contextlib
import tomllib
from pathlib import Path

import _repo  # noqa: F401  (this checkout's packages, not the installed ones: benchmarks/_repo.py)
import _timing

from bridge import toml_text

ROOT = Path(__file__).resolve().parents[1]

#: Patterns repeated to the size: unclosed quotes (the scan was quadratic on '"\\': 617 s at 256 kB),
#: multi-line strings, dotted chains, headers.
PATTERNS = ['"\\', '"""\\', '"""\\"', "'''", '\'"', 'a.', '"a".', '[a.', '\\"""', '"""\n', 'a = """\n']


def allowed(size: int) -> str:
    """The most a text of ``size`` may cost tomllib and still pass: keys of 8 parts under a header of 16."""
    header = "[" + ".".join(["h"] * 16) + "]\n"
    body, k = [header], 0
    while sum(map(len, body)) < size:
        body.append(".".join([f"k{k}"] * 1 + ["x"] * 7) + " = 1\n")
        k += 1
    return "".join(body)


def scan(text: str) -> None:
    with contextlib.suppress(tomllib.TOMLDecodeError):
        toml_text.check_keys(text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    own = (ROOT / "twin" / "model" / "prototype_3x.toml").read_text()
    base, _ = _timing.summary("baseline: tomllib.loads(prototype_3x.toml)", _timing.time_calls(lambda: tomllib.loads(own), 50, 5),
                              unit=1e-3, unit_name="ms")
    for size in (64 * 1024, 256 * 1024):
        for pat in PATTERNS:
            text = pat * (size // len(pat))
            med, _ = _timing.summary(f"scan {size // 1024} kB of {pat!r}", _timing.time_calls(lambda t=text: scan(t), args.repeats, 1),
                                     unit=1e-3, unit_name="ms")
            print(f"{'':58s} ratio to the baseline {med / base:8.1f}")
        text = allowed(size)
        toml_text.check_keys(text)  # passes
        med, _ = _timing.summary(f"tomllib of {size // 1024} kB the guard lets through", _timing.time_calls(
            lambda t=text: tomllib.loads(t), args.repeats, 1), unit=1e-3, unit_name="ms")
        print(f"{'':58s} ratio to the baseline {med / base:8.1f}")


if __name__ == "__main__":
    main()
