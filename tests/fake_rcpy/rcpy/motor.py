"""Fake rcpy.motor: refuses what librobotcontrol refuses (bad channel, duty outside [-1, 1])."""


def set(channel, duty):
    if channel not in range(1, 5) or not -1.0 <= duty <= 1.0:
        raise ValueError(f"motor.set({channel}, {duty}) refused")


def enable():
    pass


def disable():
    pass
