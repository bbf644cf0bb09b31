"""What every bus process shares: logging, a stop event set by SIGINT/SIGTERM, endpoint lists, priority.

The command-line options of these processes live with the one ``xneck`` command line
(:mod:`server.cli.options`); this module only holds what runs inside the processes."""

from __future__ import annotations

import logging
import os
import signal
import threading


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
    )


def stop_on_signals() -> threading.Event:
    """An event set by Ctrl-C or SIGTERM, so loops end cleanly and sessions get closed."""
    stop = threading.Event()

    def handler(signum: int, _frame: object) -> None:
        logging.getLogger("xneck").info("signal %s: stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop


def endpoints(values: list[str] | None) -> list[str] | None:
    """CLI endpoint list: None (not given) defers to the environment."""
    return list(values) if values else None


def raise_priority(niceness: int = -10) -> bool:
    """Ask the OS to schedule this real-time process before ordinary work (the console, a
    browser rendering WebGL in software): on a small machine they would otherwise delay ticks.
    Needs the right to lower niceness (root or CAP_SYS_NICE); without it, carries on as is."""
    try:
        os.nice(niceness)
        return True
    except (PermissionError, OSError):
        logging.getLogger("xneck").info("could not raise the scheduling priority (needs CAP_SYS_NICE)")
        return False
