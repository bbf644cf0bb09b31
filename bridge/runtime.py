"""What every bus process shares: logging, a stop event set by SIGINT/SIGTERM, endpoint options."""

from __future__ import annotations

import logging
import os
import signal
import threading
from typing import Optional

import typer

LISTEN_OPTION = typer.Option(
    None, "--listen", help="Zenoh endpoint to listen on (repeatable), e.g. tcp/127.0.0.1:7447. "
    "Default: $XNECK_ZENOH_LISTEN or an ephemeral loopback port.")
CONNECT_OPTION = typer.Option(
    None, "--connect", help="Zenoh endpoint to connect to (repeatable). Default: $XNECK_ZENOH_CONNECT.")
VERBOSE_OPTION = typer.Option(False, "--verbose", "-v", help="Debug logging.")
INSTANCE_OPTION = typer.Option("", "--instance", help="Name on the bus (default: a random one).")
# The twin's options, shared by `xneck twin` and `xneck bridge --driver twin`.
LOCKSTEP_OPTION = typer.Option(False, "--lockstep", help="Twin only: one tick per command (deterministic; CI mode).")
SEED_OPTION = typer.Option(0, "--seed", help="Twin: seed of the sensor noise.")
CABLE_MODEL_OPTION = typer.Option(None, "--cable-model", help="Twin: rigid, linear or variable (default: the parameter file's).")
NO_FRICTION_OPTION = typer.Option(False, "--no-friction", help="Twin: simulate without motor friction.")


def check_truth(value: str) -> str:
    """Typer callback: ``--truth`` is one of twin.truth.TRUTHS."""
    from twin.truth import TRUTHS

    if value not in TRUTHS:
        raise typer.BadParameter(f"{value!r}: choose {' or '.join(TRUTHS)}")
    return value


TRUTH_OPTION = typer.Option("model", "--truth", callback=check_truth, help="Twin: what it simulates, the parameter file as it is (model) or with a real line's small cable damping (robot); see twin/truth.py.")
MAX_TICKS_OPTION = typer.Option(None, "--max-ticks", help="Stop after this many ticks.")
IDLE_TIMEOUT_OPTION = typer.Option(None, "--idle-timeout", help="Lockstep: stop after this long without a command (s).")
STARTUP_TIMEOUT_OPTION = typer.Option(
    None, "--startup-timeout", help="Lockstep: the same limit before the first command (default: --idle-timeout).")


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


def endpoints(values: Optional[list[str]]) -> Optional[list[str]]:
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
