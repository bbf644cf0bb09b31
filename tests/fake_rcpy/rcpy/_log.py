"""Where the fake board writes what it was told, for tests that look across processes: each call
appends ``<pid> <what> <channel or pin> <value>`` to the file named by ``FAKE_RCPY_LOG`` (if set).

And a way to hang the bridge's loop in the lowest layer, as a hardware call that never returns
would (tests/test_bridge_watchdog.py): while the file named by ``FAKE_RCPY_BLOCK`` exists, every
encoder read blocks. Its content says how: ``sleep`` (or empty) blocks in a call that releases
the GIL (a stuck syscall), ``spin`` loops in Python (an endless loop: the GIL is only handed over
at Python's switch interval), ``convoy`` alternates a short call that releases the GIL with less
Python than the switch interval (the releases keep other threads from asking for the GIL:
CPython's convoy effect, docs/bridge.md), ``slow`` makes each read of encoder 1 take 0.4 s and return (a
loop that still ticks, rarely), ``stuck-trip`` blocks the read as ``sleep`` does and every enable
level written meanwhile as well (a trip stuck in the hardware library). The read logs ``hang <channel> <mode>`` when it starts
blocking and ``resume <channel> <mode>`` when the file is gone."""

import os
import time

#: Read once at import: without it an encoder read costs one comparison more (the fake must cost
#: next to nothing, benchmarks/bridge_tick.py).
BLOCK = os.environ.get("FAKE_RCPY_BLOCK") or None


_fd = None


def record(what, channel, value):
    # One write(2) per line on a descriptor kept open in append mode: lines of several processes
    # never interleave, and a process ending by os._exit has lost nothing (no buffer).
    global _fd
    path = os.environ.get("FAKE_RCPY_LOG")
    if path:
        if _fd is None:
            _fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC, 0o644)
        os.write(_fd, f"{os.getpid()} {what} {channel} {value}\n".encode())


def _mode(path):
    try:
        with open(path) as f:
            return f.read().strip() or "sleep"
    except OSError:
        return "sleep"


def block_gpio_while_stuck():
    """``stuck-trip``: an enable level written while the file exists blocks (module docstring)."""
    path = BLOCK
    if not path or not os.path.exists(path) or _mode(path) != "stuck-trip":
        return
    record("gpio-stuck", 0, 0)
    while os.path.exists(path):
        time.sleep(0.002)


def hang_while_blocked(channel):
    """Block while the file named by FAKE_RCPY_BLOCK exists (module docstring)."""
    path = BLOCK
    if not path or not os.path.exists(path):
        return
    mode = _mode(path)
    record("hang", channel, mode)
    if mode == "slow":
        if channel == 1:  # once per tick (a tick reads every encoder)
            # the audit's reads took 0.48 s; 0.4 s keeps the loop's gaps clear of the 0.5 s stall
            # limit on a loaded machine (a tick 0.531 s late took the no-tick path, CI of session 54)
            time.sleep(0.4)
        return
    if mode == "spin":
        while os.path.exists(path):
            # Pure Python for 20 ms between two looks at the file (whose stat releases the GIL:
            # done more often, that is the ``convoy`` mode).
            end = time.perf_counter() + 0.02
            while time.perf_counter() < end:
                pass
    elif mode == "convoy":
        while os.path.exists(path):  # a short call that releases the GIL, then Python for less
            for _ in range(5_000):  # than the switch interval (about 0.1 ms here), for ever
                pass
    else:
        while os.path.exists(path):
            time.sleep(0.002)
    record("resume", channel, mode)
