"""The one feature table every stage uses (extraction, editing, tracking, evaluation, results files).

A feature table is a NumPy structured array with the fixed columns of :data:`FEATURE_DTYPE`. It is written to
results files as is (HDF5 compound dataset), so its columns are part of the on-disk format: add columns at the
end, never rename or reorder them. Coordinates are image pixels with the origin at the centre of the top-left
pixel: ``x`` is the column and ``y`` the row, both sub-pixel floats.

Columns
-------
id : int64
    Unique within one table (and within one results file).
frame : int32
    Index of the frame the feature was found in.
x, y : float64
    Position in pixels (column, row).
kind : int8
    A :class:`FeatureKind`: 0 valley ending, 1 valley bifurcation, 2 pore (seed 4.7: circle, square, triangle).
orientation : float32
    Direction in degrees, counter-clockwise from +x with y up the image (``atan2(-dy, dx)``), in [0, 360); NaN
    exactly when ``orientation_known`` is False (pores, minutiae whose valleys are too short or incoherent).
orientation_known : bool
    Whether ``orientation`` holds a value.
quality : float32
    Confidence in [0, 1] (1 = clean, isolated, well-contrasted).
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from skinstretch.processing.errors import InvalidInputError


class FeatureKind(IntEnum):
    """Feature kinds of seed 4.7 (the skeleton is the valley skeleton: ridges are dark in FTIR images)."""

    VALLEY_ENDING = 0
    VALLEY_BIFURCATION = 1
    PORE = 2

    @property
    def label(self) -> str:
        return self.name.lower()


KIND_NAMES: dict[int, str] = {k.value: k.label for k in FeatureKind}

FEATURE_DTYPE = np.dtype(
    [
        ("id", np.int64),
        ("frame", np.int32),
        ("x", np.float64),
        ("y", np.float64),
        ("kind", np.int8),
        ("orientation", np.float32),
        ("orientation_known", np.bool_),
        ("quality", np.float32),
    ]
)


def empty_features(n: int = 0) -> np.ndarray:
    """A feature table of ``n`` rows: ids 0..n-1, frame 0, orientation unknown (NaN), quality 1."""
    table = np.zeros(n, dtype=FEATURE_DTYPE)
    table["id"] = np.arange(n)
    table["orientation"] = np.nan
    table["quality"] = 1.0
    return table


def make_features(
    x,
    y,
    kind,
    *,
    frame=0,
    orientation=None,
    quality=None,
    ids=None,
) -> np.ndarray:
    """Build a feature table from columns; ``orientation`` may hold NaN where unknown.

    >>> t = make_features([1.5, 2.0], [3.0, 4.0], [FeatureKind.PORE, FeatureKind.VALLEY_ENDING], orientation=[np.nan, 90.0])
    >>> t["orientation_known"].tolist()
    [False, True]
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    n = x.size
    table = empty_features(n)
    table["x"] = x
    table["y"] = _column(y, n, "y", np.float64)
    table["kind"] = _column(kind, n, "kind", np.int8)
    table["frame"] = _column(frame, n, "frame", np.int32)
    if ids is not None:
        table["id"] = _column(ids, n, "ids", np.int64)
    if orientation is not None:
        o = _column(orientation, n, "orientation", np.float64)
        known = np.isfinite(o)
        table["orientation"] = np.where(known, np.mod(o, 360.0), np.nan)
        table["orientation_known"] = known
    if quality is not None:
        table["quality"] = np.clip(_column(quality, n, "quality", np.float64), 0.0, 1.0)
    validate_features(table)
    return table


_KNOWN_KIND = np.zeros(256, bool)  # indexed by the kind byte (int8 viewed as uint8)
_KNOWN_KIND[np.array([k.value for k in FeatureKind], dtype=np.int8).view(np.uint8)] = True


def validate_features(table: np.ndarray) -> np.ndarray:
    """Check that ``table`` is a well-formed feature table; return it unchanged or raise InvalidInputError."""
    if not isinstance(table, np.ndarray) or table.dtype != FEATURE_DTYPE:
        got = getattr(table, "dtype", type(table))
        raise InvalidInputError(f"features must be a structured array of FEATURE_DTYPE, got {got}")
    if table.ndim != 1:
        raise InvalidInputError(f"features must be one-dimensional, got shape {table.shape}")
    if not (np.all(np.isfinite(table["x"])) and np.all(np.isfinite(table["y"]))):
        raise InvalidInputError("features have non-finite x or y")
    kinds = table["kind"]
    if not _KNOWN_KIND[kinds.view(np.uint8)].all():
        bad_kind = ~_KNOWN_KIND[kinds.view(np.uint8)]
        raise InvalidInputError(f"features have unknown kind values {np.unique(kinds[bad_kind]).tolist()}")
    known = table["orientation_known"]
    o = table["orientation"]
    if np.any(np.isnan(o) & known) or np.any(np.isfinite(o) & ~known):
        raise InvalidInputError("orientation must be finite exactly where orientation_known is True")
    return table


def _column(values, n: int, name: str, dtype) -> np.ndarray:
    arr = np.asarray(values, dtype=dtype)
    if arr.ndim == 0:
        return np.full(n, arr, dtype=dtype)
    arr = arr.ravel()
    if arr.size != n:
        raise InvalidInputError(f"{name} has {arr.size} values, expected {n}")
    return arr
