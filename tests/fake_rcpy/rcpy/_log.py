"""Where the fake board writes what it was told, for tests that look across processes: each call
appends ``<pid> <what> <channel or pin> <value>`` to the file named by ``FAKE_RCPY_LOG`` (if set)."""

import os


def record(what, channel, value):
    path = os.environ.get("FAKE_RCPY_LOG")
    if path:
        with open(path, "a") as f:
            f.write(f"{os.getpid()} {what} {channel} {value}\n")
