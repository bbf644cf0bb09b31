"""numba's ``njit`` when numba is installed, a do-nothing decorator otherwise.

The model's kernels (jets, X-joint, cables, dynamics, eq. 33) are written once, in the subset of
Python that numba compiles. On the PC they are compiled (the 500 Hz loop and the 50× real-time twin
need microseconds); on the robot's BeagleBone Blue (ARMv7, no numba for Debian 12's Python) the
bridge runs the very same functions as plain Python/numpy: it only needs them once per hold (the
hold forces, eq. 33 + eqs. 63-65), so there is no second implementation of any equation.

``XNECK_NO_NUMBA=1`` forces the plain path even where numba is installed (what the tests and
``benchmarks/bridge.py`` use to check the robot's path on the PC).
"""

from __future__ import annotations

import os

NUMBA = False
if os.environ.get("XNECK_NO_NUMBA", "") in ("", "0"):
    try:
        from numba import njit as _numba_njit

        NUMBA = True
    except ImportError:  # the lean (robot) install has no numba
        pass


def njit(*args, **kwargs):
    """``numba.njit`` if available; otherwise returns the function unchanged. Used both as
    ``@njit`` and as ``@njit(cache=True)``."""
    if NUMBA:
        return _numba_njit(*args, **kwargs)
    if len(args) == 1 and callable(args[0]) and not kwargs:
        return args[0]
    return lambda function: function


__all__ = ["NUMBA", "njit"]
