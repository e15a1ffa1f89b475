"""The JSON encoding of skinstretch's files (summaries, event logs): numpy values as plain numbers, NaN as null."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["json_default", "json_safe"]


def json_safe(value: Any) -> Any:
    """``value`` with non-finite floats replaced by None, recursively (JSON has no NaN or infinity)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def json_default(value: Any) -> Any:
    """``default=`` of :func:`json.dumps`: numpy scalars and arrays as numbers and lists (non-finite as null),
    paths and anything else as their text."""
    if isinstance(value, (np.integer, np.bool_)):
        return value.item()
    if isinstance(value, np.floating):
        return json_safe(float(value))
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, Path):
        return str(value)
    return str(value)
