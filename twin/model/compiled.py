"""numba's ``njit`` when numba is wanted and installed, a do-nothing decorator otherwise.

The model's kernels (jets, X-joint, cables, dynamics, eq. 33) are written once, in the subset of
Python that numba compiles. On the PC they are compiled (the 500 Hz loop and the 50× real-time twin
need microseconds); the bridge with a real or replayed driver runs the very same functions as plain
Python/numpy: it needs them once per hold (the hold forces, eq. 33 + eqs. 63-65), and the robot's
BeagleBone Blue (ARMv7, 512 MB) has no numba for Debian 12's Python. So there is no second
implementation of any equation, only two ways to run it.

The choice is made once, when the first kernel is decorated (that is, when the first model module
is imported):
- numba is used when it imports, unless ``XNECK_NO_NUMBA=1`` (tests and ``benchmarks/bridge_tick.py``
  use it to run the robot's path on the PC), or :func:`prefer_plain_python` was called before
  (``xneck bridge --driver beaglebone|replay`` does, so it never loads numba, llvmlite or scipy).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import TypeVar

import numpy as np

R = TypeVar("R")

_use_numba: bool | None = None  # None: not decided yet
_numba_njit: Callable | None = None


def prefer_plain_python() -> bool:
    """Run the model as plain Python in this process; call before importing any model module.
    Returns False when it is too late (kernels already compiled with numba, e.g. a test process
    that ran the twin before): they stay compiled, which gives the same numbers."""
    global _use_numba
    if _use_numba is None:
        _use_numba = False
    return not _use_numba


def numba_enabled() -> bool:
    """Whether the kernels of this process are compiled with numba (decides if not decided yet)."""
    global _use_numba, _numba_njit
    if _use_numba is None:
        _use_numba = False
        if os.environ.get("XNECK_NO_NUMBA", "") in ("", "0"):
            try:
                from numba import njit as numba_njit
            except ImportError:  # the lean (robot) install has no numba
                pass
            else:
                _numba_njit, _use_numba = numba_njit, True
    return _use_numba


def njit(*args, **kwargs):
    """``numba.njit`` when :func:`numba_enabled`, else the function unchanged. Used both as
    ``@njit`` and as ``@njit(cache=True)``."""
    if numba_enabled() and _numba_njit is not None:
        return _numba_njit(*args, **kwargs)
    if len(args) == 1 and callable(args[0]) and not kwargs:
        return args[0]
    return lambda function: function


def bind(kernel: Callable[..., R], *args) -> Callable[[], R]:
    """``kernel(*args)`` as a call without arguments, always on these very objects (arrays that
    the caller updates in place, a Model).

    Why: numba's dispatcher types every argument on every call to pick the compiled version, and
    a Model (a NamedTuple of 25 fields) costs it about 2 µs, more than half of a twin tick's
    integration. Here the version for these arguments' types is compiled (or loaded from the cache)
    once and called directly. Numba's entry point trusts its arguments' types (an array of another
    rank crashes the process), which is why the arguments are bound here and cannot change. As
    plain Python (no numba) it is the same function on the same arguments."""
    if numba_enabled() and hasattr(kernel, "compile") and hasattr(kernel, "typeof_pyval"):
        kernel = kernel.compile(tuple(kernel.typeof_pyval(a) for a in args))
    return functools.partial(kernel, *args)


def kernel_array(x) -> np.ndarray:
    """``x`` as a C-contiguous, writeable float64 array (a copy only when it is not one already),
    the one form the model's public functions hand their kernels.

    Why: numba compiles, and caches, one machine code per argument type, and a read-only array is
    another type (an archive's columns come from ``np.frombuffer``; ``np.broadcast_to`` views are
    read-only). Each such variant of a batch kernel cost a fresh checkout's first analysis another
    5-10 s of compilation (14 variants in one test run, 2026-11-28)."""
    return np.require(x, dtype=np.float64, requirements=["C", "W"])


__all__ = ["bind", "kernel_array", "njit", "numba_enabled", "prefer_plain_python"]
