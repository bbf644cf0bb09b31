"""Preloaded by a study's local Dask workers (``LocalCluster(preload=[__name__])``, server.studies.execute).

A stop closes the local workers with runs in flight (it does not wait for them); each such run's
worker then logged 'distributed.worker.state_machine - WARNING - Async instruction ... ended with
CancelledError' on the terminal, news of nothing but the stop. That logger says errors only here.
"""

from __future__ import annotations

import logging
from typing import Any


def dask_setup(worker: Any) -> None:
    logging.getLogger("distributed.worker.state_machine").setLevel(logging.ERROR)
