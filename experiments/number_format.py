"""How skinstretch prints a number in tables (bench, report): the same digits everywhere for the same value."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["format_number"]


def format_number(v: Any) -> str:
    """``v`` for a table: yes/no for booleans, n/a for NaN, 3 significant digits below 1000, integers as they are;
    lists and tuples element by element; anything else as its text."""
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return f"{int(v)}"
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if math.isnan(v):
            return "n/a"
        a = abs(v)
        if a == 0:
            return "0"
        if a >= 1000:
            return f"{v:.0f}"
        if a >= 100:
            return f"{v:.1f}"
        if a >= 0.01:
            return f"{v:.3g}"
        return f"{v:.2e}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(format_number(x) for x in v) + "]"
    return str(v)
