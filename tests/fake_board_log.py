"""Reading what tests/fake_rcpy was told across processes (``FAKE_RCPY_LOG``, rcpy._log)."""

from __future__ import annotations

from pathlib import Path


def board_log(path: Path) -> list[tuple[int, str, str, str]]:
    """(pid, what, channel or pin, value) lines the fake board was told, in order."""
    if not path.exists():
        return []
    return [(int(p), w, c, v) for p, w, c, v in (line.split() for line in path.read_text().splitlines())]


def levels(lines, pids=None) -> dict[int, int]:
    """The last level each enable pin was set to (by ``pids`` if given)."""
    out: dict[int, int] = {}
    for pid, what, pin, value in lines:
        if what == "gpio" and (pids is None or pid in pids):
            out[int(pin)] = int(value)
    return out
