"""Second-order forward-mode automatic differentiation of scalar functions of one angle.

A jet is a tuple ``(v, d, dd)``: a value and its first and second derivatives with respect to
one variable (here always the angle α_i of one X-joint). Every cable length and bar position of
joint i depends on α_i alone, so jets give Z = −∂l_c/∂α (3-X paper eq. 22), Ż and the bias
accelerations of the dynamics exactly, without finite differences and without symbolic algebra.
All functions are numba-compiled where numba is installed (twin.model.compiled), so the 500 Hz loop
and the twin pay microseconds; the robot's lean bridge runs them as plain Python.
"""

from __future__ import annotations

import math

from twin.model.compiled import njit

Jet = tuple[float, float, float]


@njit(cache=True)
def const(c: float) -> Jet:
    return (c, 0.0, 0.0)


@njit(cache=True)
def add(a: Jet, b: Jet) -> Jet:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit(cache=True)
def sub(a: Jet, b: Jet) -> Jet:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit(cache=True)
def scale(a: Jet, k: float) -> Jet:
    return (k * a[0], k * a[1], k * a[2])


@njit(cache=True)
def shift(a: Jet, c: float) -> Jet:
    return (a[0] + c, a[1], a[2])


@njit(cache=True)
def mul(a: Jet, b: Jet) -> Jet:
    return (a[0] * b[0], a[0] * b[1] + a[1] * b[0], a[0] * b[2] + 2.0 * a[1] * b[1] + a[2] * b[0])


@njit(cache=True)
def sqrt(a: Jet) -> Jet:
    v = math.sqrt(a[0])
    d = a[1] / (2.0 * v)
    return (v, d, (a[2] - 2.0 * d * d) / (2.0 * v))


@njit(cache=True)
def sin(a: Jet) -> Jet:
    s, c = math.sin(a[0]), math.cos(a[0])
    return (s, c * a[1], c * a[2] - s * a[1] * a[1])


@njit(cache=True)
def cos(a: Jet) -> Jet:
    s, c = math.sin(a[0]), math.cos(a[0])
    return (c, -s * a[1], -s * a[2] - c * a[1] * a[1])


@njit(cache=True)
def atan(a: Jet) -> Jet:
    q = 1.0 / (1.0 + a[0] * a[0])
    return (math.atan(a[0]), q * a[1], q * a[2] - 2.0 * a[0] * q * q * a[1] * a[1])


@njit(cache=True)
def atan2(y: Jet, x: Jet) -> Jet:
    r2 = x[0] * x[0] + y[0] * y[0]
    num = x[0] * y[1] - y[0] * x[1]  # its time derivative is x·y'' − y·x'' (the x'y' terms cancel)
    d = num / r2
    dd = (x[0] * y[2] - y[0] * x[2]) / r2 - num * 2.0 * (x[0] * x[1] + y[0] * y[1]) / (r2 * r2)
    return (math.atan2(y[0], x[0]), d, dd)
