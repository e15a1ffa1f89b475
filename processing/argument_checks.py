"""Argument checks shared by processing functions: each raises InvalidInputError naming the parameter and value."""

from __future__ import annotations

import math

import numpy as np
from skinstretch.processing.errors import InvalidInputError


def positive_number(value: float, name: str) -> float:
    """``value`` as a float when it is a finite number above 0; otherwise InvalidInputError naming ``name``."""
    if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value > 0):
        raise InvalidInputError(f"{name} must be a positive number, got {value!r}")
    return float(value)


def non_negative_number(value: float, name: str) -> float:
    """``value`` as a float when it is a finite number >= 0; otherwise InvalidInputError naming ``name``."""
    if not (isinstance(value, (int, float, np.number)) and math.isfinite(value) and value >= 0):
        raise InvalidInputError(f"{name} must be a number >= 0, got {value!r}")
    return float(value)
