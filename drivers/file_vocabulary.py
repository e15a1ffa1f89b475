"""The words skinstretch's HDF5 files use to explain themselves, shared by every file it writes: session files
(:mod:`skinstretch.drivers.session_file`: recorded, simulated, imported, and the log of a played movie) and results
files (:mod:`skinstretch.experiments.results_file`). Documented in docs/session-format.md and
docs/results-format.md ("Files that explain themselves").

Every dataset carries, as HDF5 attributes:

* ``units``: one word of :data:`UNITS`. Dimensionless values all say ``"1"``: a fraction (a strain or a change of
  length or area is stored as a fraction, 0.01 = 1 %; reports and the viewer show it in %), a ratio, a count, an
  index (frame number, track, row), a code or a flag (bool); ``""`` is text. Where the values differ by column:
  for an array whose last axis is a set of named columns, one unit per column, comma-separated in the order of
  ``columns`` (``"N, N, N, N m, N m, N m"``); for a table (an HDF5 compound dataset), a JSON object giving the unit
  of every field (``{"frame": "1", "x": "px", ...}``).
* its axes named, each with a name of :data:`AXES` (HDF5 dimension labels, ``ds.dims[k].label``; scalars have
  none);
* ``description``: one line on the meaning;
* ``columns`` (optional): the names along the last axis when it is a set of columns (``fx, fy, fz, tx, ty, tz``;
  ``dx, dy`` for a displacement, ``x, y`` for a position);
* the key of its codes: ``enum_values`` / ``enum_names`` for a coded dataset (a session's ``status``, a simulated
  session's ``truth/feature_kind``), ``<column>_codes`` (JSON ``{"0": "ok", ...}``) for a coded column of a table
  (``status``, ``kind``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Mapping

import h5py
import numpy as np

__all__ = ["CONVENTIONS", "UNITS", "AXES", "UNSPECIFIED", "DatasetInfo", "describe_dataset", "read_dataset_info",
           "unit_words", "PX", "PX2", "MM", "UM", "S", "DEG", "N", "N_M", "GREY_LEVEL", "ONE", "TEXT"]

#: What every skinstretch file states in its root attribute ``conventions``.
CONVENTIONS = (
    "image pixels, x = column, y = row, origin at the centre of the top-left pixel; every dataset has a units "
    "attribute (px, px^2, mm, um, s, deg, N, N m, grey level; 1 for a dimensionless value: a fraction such as a "
    "strain, a count, an index, a code or a flag; empty for text), one unit per column comma-separated in the "
    "order of its columns attribute (an array) or a JSON object by field (a table) where the columns differ; "
    "axes are named by HDF5 dimension labels; codes are keyed by enum_values / enum_names (a coded dataset) or "
    "<column>_codes (a coded column of a table)"
)

# ---------------------------------------------------------------------------------------------------- units
PX = "px"  # image (or rectified skin) pixels
PX2 = "px^2"  # an area in pixels
MM = "mm"
UM = "um"  # micrometres (contactor positions)
S = "s"  # seconds
DEG = "deg"  # degrees
N = "N"  # newton
N_M = "N m"  # newton metre (a torque)
GREY_LEVEL = "grey level"  # 8-bit image values, 0 black .. 255 white
ONE = "1"  # dimensionless: a fraction (strain), ratio, count, index, code or flag
TEXT = ""  # text

#: Every unit word a skinstretch file uses.
UNITS: frozenset[str] = frozenset({PX, PX2, MM, UM, S, DEG, N, N_M, GREY_LEVEL, ONE, TEXT})
#: The units of a stream a program declared by shape alone (:func:`skinstretch.drivers.session_file.stream_spec`).
UNSPECIFIED = "unspecified"

# ----------------------------------------------------------------------------------------------------- axes
#: Every axis name a skinstretch file uses, with its meaning.
AXES: Mapping[str, str] = {
    "frame": "a frame of the session",
    "pair": "a frame pair (k, k + span) of the analysis",
    "row": "a row of a table",
    "sample": "a sample of a time-stamped stream",
    "y": "image row",
    "x": "image column",
    "feature": "a true feature of a simulated session",
    "track": "a trajectory",
    "grid_y": "a row of a grid of points",
    "grid_x": "a column of a grid of points",
    "component": "the named columns of the last axis (the columns attribute)",
    "contactor_row": "a row of the display's contactors (across the sliding axis for a tactile movie)",
    "contactor_column": "a column of the display's contactors (along the sliding axis for a tactile movie)",
    "contactor_gap": "the gap between two neighbouring contactors of a row",
    "bin": "a position along the stretch profile",
}


@dataclass(frozen=True)
class DatasetInfo:
    """What a dataset holds, written as its attributes so the file explains itself (see the module docstring).

    Attributes
    ----------
    units : str
        The ``units`` attribute: one word of :data:`UNITS`; per column comma-separated in the order of ``columns``
        (an array) or a JSON object by field (a table) when the columns differ. :meth:`column_units` parses it.
    axes : tuple of str
        Name of every axis (HDF5 dimension labels), e.g. ``("frame", "y", "x")``.
    description : str
        One line on the meaning.
    columns : tuple of str
        Names along the last axis (``fx, fy, fz, tx, ty, tz``), or a table's fields; empty otherwise.
    enum : mapping int -> str, optional
        The name of every code of a coded dataset (``status``, ``feature_kind``).
    column_codes : mapping column -> (mapping int -> str)
        The names of the codes of a table's coded columns (``status``, ``kind``).
    """

    units: str
    axes: tuple[str, ...]
    description: str
    columns: tuple[str, ...] = ()
    enum: Mapping[int, str] | None = None
    column_codes: Mapping[str, Mapping[int, str]] = field(default_factory=dict)

    def column_units(self) -> dict[str, str]:
        """The unit of every column ({} when the dataset has no columns)."""
        if self.units.startswith("{"):
            return {str(k): str(v) for k, v in json.loads(self.units).items()}
        words = unit_words(self.units)
        if len(words) == 1:
            return {c: words[0] for c in self.columns}
        return dict(zip(self.columns, words))


def unit_words(units: str) -> list[str]:
    """The unit words of a ``units`` attribute: one, one per column (comma-separated), or a table's (JSON)."""
    if units.startswith("{"):
        return [str(v) for v in json.loads(units).values()]
    return [w.strip() for w in units.split(",")] if "," in units else [units]


def describe_dataset(ds: h5py.Dataset, info: DatasetInfo) -> None:
    """Write ``info`` as the attributes of ``ds`` (units, description, axis labels, columns, code keys)."""
    ds.attrs["units"] = info.units
    ds.attrs["description"] = info.description
    for k, label in enumerate(info.axes[: ds.ndim]):
        ds.dims[k].label = label
    if info.columns and ds.dtype.names is None:  # a table's fields name themselves
        ds.attrs["columns"] = np.array(info.columns, dtype=h5py.string_dtype())
    if info.enum:
        ds.attrs["enum_values"] = np.array(sorted(info.enum), dtype=np.int64)
        ds.attrs["enum_names"] = np.array([info.enum[k] for k in sorted(info.enum)], dtype=h5py.string_dtype())
    for column, codes in info.column_codes.items():
        ds.attrs[f"{column}_codes"] = json.dumps({str(k): v for k, v in sorted(codes.items())})


def _text(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def read_dataset_info(ds: h5py.Dataset) -> DatasetInfo | None:
    """The :class:`DatasetInfo` a dataset's attributes give, or None when it does not carry them all (a file written
    before they existed: its reader describes it from its own tables)."""
    a = ds.attrs
    if "units" not in a or "description" not in a:
        return None
    values, names = a.get("enum_values"), a.get("enum_names")
    enum = {int(v): _text(n) for v, n in zip(values, names)} if values is not None and names is not None else None
    fields = ds.dtype.names or ()
    codes = {c: {int(k): str(v) for k, v in json.loads(_text(a[f"{c}_codes"])).items()}
             for c in fields if f"{c}_codes" in a}
    return DatasetInfo(
        units=_text(a["units"]),
        axes=tuple(_text(d.label) for d in ds.dims),
        description=_text(a.get("description", "")),
        columns=tuple(fields) or tuple(_text(c) for c in a.get("columns", ())),
        enum=enum,
        column_codes=codes,
    )
