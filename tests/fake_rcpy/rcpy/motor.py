"""Fake rcpy.motor: refuses what librobotcontrol refuses (bad channel, duty outside [-1, 1]);
logs what it was given (rcpy._log)."""

from rcpy._log import record

_duty = {}


def set(channel, duty):
    if channel not in range(1, 5) or not -1.0 <= duty <= 1.0:
        raise ValueError(f"motor.set({channel}, {duty}) refused")
    if _duty.get(channel) != float(duty):  # changes only: a bridge sets every output 500 times a second
        _duty[channel] = float(duty)
        record("motor", channel, float(duty))


def enable():
    record("motor", "all", "enable")


def disable():
    record("motor", "all", "disable")
