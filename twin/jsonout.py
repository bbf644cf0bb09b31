"""Strict JSON for what users read (``--json`` output, provenance files): numpy values as plain
numbers and every NaN or ±inf as null. ``json.dumps`` would write ``Infinity`` (e.g. the relative σ
of a parameter identified as zero), which jq, JavaScript's ``JSON.parse`` and most other readers
refuse. Light on purpose (numpy only): every command with ``--json`` imports it."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["json_ready", "strict_json"]


def json_ready(value: Any) -> Any:
    """``value`` with mappings, sequences and numpy values turned into JSON builtins, non-finite
    floats into None."""
    if isinstance(value, Mapping):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def strict_json(value: Any, **dumps: Any) -> str:
    """``json.dumps`` of :func:`json_ready` (``value``), refusing NaN outright (allow_nan=False),
    so nothing non-finite can slip through unconverted."""
    return json.dumps(json_ready(value), allow_nan=False, **dumps)
