"""Fake rcpy.gpio: remembers the levels it was given (and logs them: rcpy._log)."""

from rcpy._log import block_gpio_while_stuck, record

_levels = {}


def set_value(pin, value=0):
    block_gpio_while_stuck()
    _levels[pin] = int(value)
    record("gpio", pin, int(value))


def get_value(pin):
    return _levels.get(pin, 0)
