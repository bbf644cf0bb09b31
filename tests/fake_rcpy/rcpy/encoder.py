"""Fake rcpy.encoder: four quadrature counters that never move. A read blocks while the file
named by FAKE_RCPY_BLOCK exists (rcpy._log: a test's way to hang the bridge's loop).
``FAKE_RCPY_ENCODER_INIT_FAILS=1``: the import fails as upstream's C module does (SystemError)."""

import os

from rcpy._log import BLOCK, hang_while_blocked

if os.environ.get("FAKE_RCPY_ENCODER_INIT_FAILS"):
    # upstream rcpy's _encoder.c when rc_encoder_eqep_init() fails: NULL without an exception
    raise SystemError("initialization of _encoder failed without raising an exception")

_counts = {1: 0, 2: 0, 3: 0, 4: 0}


def get(channel):
    if BLOCK:
        hang_while_blocked(channel)
    if channel not in _counts:
        raise ValueError(f"no encoder channel {channel}")
    return _counts[channel]


def set(channel, count):
    _counts[channel] = int(count)
