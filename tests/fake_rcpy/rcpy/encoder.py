"""Fake rcpy.encoder: four quadrature counters that never move."""

_counts = {1: 0, 2: 0, 3: 0, 4: 0}


def get(channel):
    if channel not in _counts:
        raise ValueError(f"no encoder channel {channel}")
    return _counts[channel]


def set(channel, count):
    _counts[channel] = int(count)
