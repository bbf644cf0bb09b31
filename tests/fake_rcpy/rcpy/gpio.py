"""Fake rcpy.gpio: remembers the levels it was given (and logs them: rcpy._log).

``FAKE_RCPY_STUCK_HIGH=<pin>:<n>``: from its n-th write on, that enable line is stuck high (a
shorted line or a dead GPIO): the write is ignored without an error, the line reads 1."""

import os

from rcpy._log import block_gpio_while_stuck, record

_levels = {}
_writes = {}
_stuck = os.environ.get("FAKE_RCPY_STUCK_HIGH", "")
STUCK_PIN, STUCK_FROM = (int(x) for x in _stuck.split(":")) if _stuck else (None, 0)


def set_value(pin, value=0):
    block_gpio_while_stuck()
    _writes[pin] = _writes.get(pin, 0) + 1
    if pin == STUCK_PIN and _writes[pin] >= STUCK_FROM:
        _levels[pin] = 1
        record("gpio-stuck-high", pin, int(value))
        return
    _levels[pin] = int(value)
    record("gpio", pin, int(value))


def get_value(pin):
    return _levels.get(pin, 0)
