"""The results of ``skinstretch analyze``: ``OUTDIR/results.h5`` (everything) and ``OUTDIR/summary.json``.

The layout is documented in ``docs/results-format.md``; this module is the only code that reads or writes it.
:class:`ResultsWriter` writes a results file while the analysis runs (tables grow as frame pairs are measured, so
memory does not grow with the session); :func:`read_results` opens one as a :class:`Results`, which reads each
part when it is first asked for. Variable-length per-pair data (motion samples, triangulation edges and triangles)
are flat tables with a ``pair`` column indexing a per-span ``pairs`` table that carries each pair's status.
Every dataset explains itself in the words of :mod:`skinstretch.drivers.file_vocabulary` (shared with session
files): ``units`` (a JSON object naming the unit of each field for tables), named axes, a ``description``,
``columns``; coded columns (pair ``status``, feature ``kind``) have their keys in a ``<column>_codes`` attribute;
image axes are named ``x``/``y``. :data:`RESULTS_DATASETS` says how each is described.
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from collections.abc import Sequence
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass, field
from enum import IntEnum
from functools import cached_property
from pathlib import Path
from typing import Any, Callable, Iterator

import h5py
import numpy as np

from skinstretch.drivers.disk_space import SpaceReserve, close_on_a_full_disk
from skinstretch.drivers.errors import DiskFullError, SessionFileError
from skinstretch.drivers.file_vocabulary import (CONVENTIONS, DEG, ONE, PX, PX2, TEXT, UM, DatasetInfo,
                                                  describe_dataset, read_dataset_info)
from skinstretch.experiments.output_paths import OutputPathError, check_output_dir
from skinstretch.processing.errors import Remedy
from skinstretch.processing.feature_table import KIND_NAMES
from skinstretch.processing.fingertip import FingertipMotion, VisibilityWindow
from skinstretch.processing.stretch import StretchProfile
from skinstretch.processing.strain_tensor import TENSOR_STATUS_NAMES
from skinstretch.processing.tracking import TRAJECTORY_DTYPE, MotionSample, Trajectories

__all__ = [
    "FORMAT_NAME", "FORMAT_VERSION", "PairStatus", "PAIR_DTYPE", "MOTION_DTYPE", "EDGE_DTYPE", "TRIANGLE_DTYPE",
    "TRACK_DTYPE", "TENSOR_COLUMNS", "SpanStrain", "CumulativeStrain", "TactileMovieTable", "FlowResults",
    "MeshDensity", "Results", "ResultsWriter",
    "read_results", "AXIS_NAMES", "RESULTS_DATASETS", "results_dataset_info", "RESULTS_FILE", "SUMMARY_FILE",
    "held_results", "check_results_dir", "refuse_held_results", "pair_index", "pair_row_offsets",
]

log = logging.getLogger(__name__)

FORMAT_NAME = "skinstretch-results"
FORMAT_VERSION = 2
#: The files ``skinstretch analyze`` writes into its output directory.
RESULTS_FILE, SUMMARY_FILE = "results.h5", "summary.json"

#: Image axes by index: 0 = x (columns), 1 = y (rows).
AXIS_NAMES = ("x", "y")


class PairStatus(IntEnum):
    """Why a frame pair has (or has not) a measurement; stored as int8 with its keys in ``status_codes``."""

    OK = 0
    NO_MOTION = 1  # no displacement measured between the two frames
    TOO_FEW_POINTS = 2  # fewer than 3 distinct matched points
    COLLINEAR = 3  # the matched points are collinear
    NO_USABLE_TRIANGLE = 4  # every triangle too thin or too long
    DOUBTED = 5  # measured, but a self-check failed (the reason says which): not a number to trust

    @property
    def key(self) -> str:
        return self.name.lower()


PAIR_DTYPE = np.dtype(
    [("frame_a", np.int32), ("frame_b", np.int32), ("n_points", np.int32), ("status", np.int8), ("reason", "S96")]
)
MOTION_DTYPE = np.dtype(
    [("pair", np.int32), ("id", np.int64), ("x", np.float64), ("y", np.float64), ("dx", np.float64), ("dy", np.float64),
     ("sigma", np.float64), ("match", np.float64)]
)
EDGE_DTYPE = np.dtype(
    [("pair", np.int32), ("id_a", np.int64), ("id_b", np.int64), ("xa", np.float64), ("ya", np.float64),
     ("xb", np.float64), ("yb", np.float64), ("length", np.float64), ("change", np.float64),
     ("change_sigma", np.float64)]
)
TRIANGLE_DTYPE = np.dtype(
    [("pair", np.int32), ("id_a", np.int64), ("id_b", np.int64), ("id_c", np.int64), ("x0", np.float64),
     ("y0", np.float64), ("x1", np.float64), ("y1", np.float64), ("x2", np.float64), ("y2", np.float64),
     ("area", np.float64), ("change", np.float64), ("flipped", np.bool_), ("change_sigma", np.float64),
     ("exx", np.float64), ("eyy", np.float64), ("exy", np.float64), ("e1", np.float64), ("e2", np.float64),
     ("angle_deg", np.float64), ("tensor_status", np.int8)]
)
#: The strain-tensor columns of a triangle table (absent from files written before they were measured).
TENSOR_COLUMNS = ("exx", "eyy", "exy", "e1", "e2", "angle_deg")
#: One row per kept trajectory.
TRACK_DTYPE = np.dtype([("track", np.int64), ("kind", np.int8), ("n_frames", np.int32), ("first_frame", np.int32),
                        ("last_frame", np.int32)])


def _table_units(**units: str) -> str:
    return json.dumps(units)


_XY, _DXY = ("x", "y"), ("dx", "dy")
_CODES = {"status": {int(s): s.key for s in PairStatus}, "kind": dict(KIND_NAMES),
          "tensor_status": dict(TENSOR_STATUS_NAMES)}
_PAIRS = DatasetInfo(_table_units(frame_a=ONE, frame_b=ONE, n_points=ONE, status=ONE, reason=TEXT), ("pair",),
                     "one row per frame pair: its frames, the points measured, status 0 or why not (reason)",
                     column_codes={"status": _CODES["status"]})
_MOVIE_AXES = ("frame", "contactor_row", "contactor_column")

_EDGES = DatasetInfo(
    _table_units(pair=ONE, id_a=ONE, id_b=ONE, xa=PX, ya=PX, xb=PX, yb=PX, length=PX, change=ONE,
                 change_sigma=ONE), ("row",),
    "Delaunay edges of every pair: endpoints in frame a, length, change L_b/L_a - 1 (a fraction) and its standard "
    "error (inf where an endpoint's is)")
_TRIANGLES = DatasetInfo(
    _table_units(pair=ONE, id_a=ONE, id_b=ONE, id_c=ONE, x0=PX, y0=PX, x1=PX, y1=PX, x2=PX, y2=PX, area=PX2,
                 change=ONE, flipped=ONE, change_sigma=ONE, exx=ONE, eyy=ONE, exy=ONE, e1=ONE, e2=ONE,
                 angle_deg=DEG, tensor_status=ONE), ("row",),
    "Delaunay triangles of every pair: corners in frame a, area, change A_b/A_a - 1 (a fraction) and its standard "
    "error (inf where a corner's is), flipped; "
    "Green-Lagrange strain of frame b relative to frame a (fractions, image axes, exy = E[0,1] = half the "
    "engineering shear), principal strains e1 >= e2 and the angle of e1 from +x towards +y (deg); tensor_status "
    "0 ok, else the tensor is 0 and not a measurement", column_codes={"tensor_status": _CODES["tensor_status"]})

#: Every dataset of a results file (``strain/span_<s>/...`` for every span ``s``), as the writer describes it in
#: the file (:mod:`skinstretch.drivers.file_vocabulary`); :meth:`Results.dataset_info` reads it back.
RESULTS_DATASETS: dict[str, DatasetInfo] = {
    "frame_flags": DatasetInfo(TEXT, ("frame",), "empty, or why a frame gave nothing (all_black, saturated, "
                                                 "no_finger, no contact)"),
    "motion_pairs": _PAIRS,
    "motion": DatasetInfo(_table_units(pair=ONE, id=ONE, x=PX, y=PX, dx=PX, dy=PX, sigma=PX, match=ONE), ("row",),
                          "every displacement measured between consecutive frames: point in frame a, to frame b, "
                          "its predicted standard error per axis (inf, no bound, where its windows do not match or "
                          "do not fit in the image) and its windows' match after the motion (1 identical, 0 "
                          "unrelated or no window)"),
    "fingertip/displacement": DatasetInfo(PX, ("pair", "component"), "mean displacement per consecutive pair; 0 "
                                          "where not valid", _DXY),
    "fingertip/n_points": DatasetInfo(ONE, ("pair",), "displacements averaged"),
    "fingertip/valid": DatasetInfo(ONE, ("pair",), "at least 3 displacements averaged (bool)"),
    "fingertip/position": DatasetInfo(PX, ("frame", "component"), "fingertip displacement since frame 0", _XY),
    "window_centers": DatasetInfo(PX, ("frame", "component"), "centre of the visibility window", _XY),
    "profile/position": DatasetInfo(PX, ("bin",), "position along the sliding axis (the group's axis attribute)"),
    "profile/change": DatasetInfo(ONE, ("bin",), "change in stretch averaged over the sequence (a fraction); NaN "
                                                 "exactly where not valid"),
    "profile/valid": DatasetInfo(ONE, ("bin",), "the change was measured there (bool)"),
    "tactile_movie/positions_um": DatasetInfo(UM, _MOVIE_AXES, "contactor positions along the sliding direction "
                                              "(the group's motion_axis attribute), clipped to +/-50 um"),
    "tactile_movie/reset": DatasetInfo(ONE, _MOVIE_AXES, "contactor reset that frame (bool)"),
    "tactile_movie/clipped": DatasetInfo(ONE, _MOVIE_AXES, "position clipped to the display's range (bool)"),
    "tactile_movie/stretch_change": DatasetInfo(ONE, ("frame", "contactor_row", "contactor_gap"),
                                                "change in stretch between neighbours along the sliding axis "
                                                "(a fraction)"),
    "features": DatasetInfo(_table_units(id=ONE, frame=ONE, x=PX, y=PX, kind=ONE, orientation=DEG,
                                         orientation_known=ONE, quality=ONE), ("row",),
                            "every extracted feature (id = row)", column_codes={"kind": _CODES["kind"]}),
    "trajectories": DatasetInfo(_table_units(frame=ONE, track=ONE, x=PX, y=PX, raw_x=PX, raw_y=PX, feature_index=ONE,
                                             linked=ONE, refined=ONE, run=ONE, anchor_sigma=PX), ("row",),
                                "one row per track per frame it is present in: refined position, extracted "
                                "position (NaN where followed by registration), row in features (-1 there), "
                                "standard error of the key-frame anchoring"),
    "tracks": DatasetInfo(_table_units(track=ONE, kind=ONE, n_frames=ONE, first_frame=ONE, last_frame=ONE),
                          ("track",), "one row per kept trajectory", column_codes={"kind": _CODES["kind"]}),
    "flow/grid_x": DatasetInfo(PX, ("grid_x",), "x of the grid nodes in frame a"),
    "flow/grid_y": DatasetInfo(PX, ("grid_y",), "y of the grid nodes in frame a"),
    "flow/displacement": DatasetInfo(PX, ("pair", "grid_y", "grid_x", "component"),
                                     "displacement of each node to the next frame; 0 where not valid", _DXY),
    "flow/valid": DatasetInfo(ONE, ("pair", "grid_y", "grid_x"), "node in contact and registered (bool)"),
    "strain/span_<s>/pairs": _PAIRS,
    "strain/span_<s>/edges": _EDGES,
    "strain/span_<s>/triangles": _TRIANGLES,
    "cumulative/pairs": _PAIRS,
    "cumulative/motion": DatasetInfo(_table_units(pair=ONE, id=ONE, x=PX, y=PX, dx=PX, dy=PX, sigma=PX, match=ONE),
                                     ("row",),
                                     "displacement of every skin point (track or flow grid node) from the reference "
                                     "frame (the group's reference_frame attribute) to frame_b of its pair, its "
                                     "predicted standard error and window match (as motion's)"),
    "cumulative/edges": _EDGES,
    "cumulative/triangles": _TRIANGLES,
}


def results_dataset_info(name: str) -> DatasetInfo:
    """How the results dataset ``name`` (``"motion"``, ``"strain/span_11/edges"``...) is described."""
    key = re.sub(r"^strain/span_\d+/", "strain/span_<s>/", name.strip("/"))
    if key not in RESULTS_DATASETS:
        raise KeyError(f"{name!r} is not a dataset of a results file (docs/results-format.md)")
    return RESULTS_DATASETS[key]


@dataclass
class SpanStrain:
    """Triangulation strain of every frame pair at one span (seed 5.3.1)."""

    span: int
    pairs: np.ndarray  # PAIR_DTYPE
    edges: np.ndarray  # EDGE_DTYPE
    triangles: np.ndarray  # TRIANGLE_DTYPE

    @property
    def ok(self) -> np.ndarray:
        """Pairs that gave a triangulation."""
        return self.pairs["status"] == PairStatus.OK


@dataclass
class CumulativeStrain:
    """Motion and triangulation strain of every frame relative to one reference frame (the first with measured
    points, normally 0): along the trajectories (features) or the skin points followed through the flow fields
    (flow). Pair ``i`` is (reference, frame_b); ``motion`` rows have the skin points' reference-frame positions."""

    reference_frame: int
    pairs: np.ndarray  # PAIR_DTYPE
    motion: np.ndarray  # MOTION_DTYPE
    edges: np.ndarray  # EDGE_DTYPE
    triangles: np.ndarray  # TRIANGLE_DTYPE

    def sample(self, frame: int) -> MotionSample | None:
        """The skin points' motion from the reference frame to ``frame``, or None when there is no such pair."""
        where = np.flatnonzero(self.pairs["frame_b"] == int(frame))
        if int(frame) == self.reference_frame:
            rows = self.motion[self.motion["pair"] == 0] if self.pairs.size else self.motion[:0]
            p = np.column_stack([rows["x"], rows["y"]])
            return MotionSample(self.reference_frame, self.reference_frame, p, np.zeros_like(p),
                                rows["id"].astype(np.int64))
        if where.size == 0:
            return None
        rows = self.motion[self.motion["pair"] == int(where[0])]
        names = rows.dtype.names or ()
        return MotionSample(self.reference_frame, int(frame), np.column_stack([rows["x"], rows["y"]]),
                            np.column_stack([rows["dx"], rows["dy"]]), rows["id"].astype(np.int64),
                            rows["sigma"].astype(np.float64) if "sigma" in names else None,
                            rows["match"].astype(np.float64) if "match" in names else None)


@dataclass(frozen=True)
class TactileMovieTable:
    """The tactile movie as stored (seed 5.4): see :class:`skinstretch.processing.display_mapping.TactileMovie`."""

    positions_um: np.ndarray  # (N, C, C) float32
    reset: np.ndarray  # (N, C, C) bool
    clipped: np.ndarray  # (N, C, C) bool
    stretch_change: np.ndarray  # (N, C, C-1) float32
    motion_axis: str  # "x" or "y"


@dataclass(frozen=True)
class FlowResults:
    """The dense method's grid and fields: ``displacement`` (N-1, GY, GX, 2) float32 px, 0 where not ``valid``."""

    grid_x: np.ndarray
    grid_y: np.ndarray
    displacement: np.ndarray
    valid: np.ndarray


@dataclass(frozen=True)
class MeshDensity:
    """Density of an analysis' measurement (``summary["density"]``; :attr:`Results.density` in Python), computed by
    :func:`skinstretch.experiments.analysis.density.mesh_density`.

    Attributes
    ----------
    method : str
    features_per_frame : float or None
        Features found per frame (mean; None for the flow method).
    trajectories_kept : int or None
        Trajectories at least the minimum length (None for the flow method).
    fraction_kept : float or None
        Of the features that stay in view for the window, the fraction in a kept trajectory (module doc; None for
        the flow method or when no feature stays in view).
    features_in_view : int or None
        Features that stay in view for the window (the denominator of ``fraction_kept``).
    window_frames : int or None
        The window: the minimum trajectory length.
    points_per_pair : float
        Points measured between consecutive frames (median over pairs).
    mesh_edge_mm : float or None
        Mean edge length of the consecutive pairs' strain triangulations (None: no triangulation).
    strain_pairs, strain_pairs_ok : dict
        Frame pairs and pairs with a strain triangulation, per span.
    too_sparse : bool
        The mesh is too sparse to map strain (``warning`` says why).
    warning : str or None
        Why the mesh is too sparse, or the fraction kept too low, when it is.
    """

    method: str
    features_per_frame: float | None
    trajectories_kept: int | None
    fraction_kept: float | None
    features_in_view: int | None
    window_frames: int | None
    points_per_pair: float
    mesh_edge_mm: float | None
    strain_pairs: dict[int, int] = field(default_factory=dict)
    strain_pairs_ok: dict[int, int] = field(default_factory=dict)
    too_sparse: bool = False
    warning: str | None = None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["strain_pairs"] = {str(k): v for k, v in self.strain_pairs.items()}
        d["strain_pairs_ok"] = {str(k): v for k, v in self.strain_pairs_ok.items()}
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "MeshDensity":
        """The inverse of :meth:`to_dict` (a results file's summary)."""
        d = dict(d)
        for name in ("strain_pairs", "strain_pairs_ok"):
            d[name] = {int(k): int(v) for k, v in (d.get(name) or {}).items()}
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in d.items() if k in known})

    def describe(self) -> str:
        """One line for people: features, trajectories, fraction kept, mesh edge."""
        parts = []
        if self.features_per_frame is not None:
            frac = "n/a" if self.fraction_kept is None else f"{100 * self.fraction_kept:.0f} %"
            parts.append(f"{self.features_per_frame:.1f} features/frame, {self.trajectories_kept} trajectories kept, "
                         f"{frac} of the features in view for {self.window_frames} frames kept")
        parts.append(f"{self.points_per_pair:g} points per frame pair")
        parts.append("no strain mesh" if self.mesh_edge_mm is None else f"mesh edge {self.mesh_edge_mm:.2f} mm")
        return ", ".join(parts)


# ----------------------------------------------------------------------------------------------------- writing


class ResultsWriter:
    """Write a results file as the analysis runs: tables are appended pair by pair, arrays written once known.

    ``path`` None writes into memory (an HDF5 file image, for analyses of frames held in memory); otherwise the file
    is written as ``path.partial`` and renamed by :meth:`finish` (a failed analysis leaves no results file).
    """

    def __init__(self, path: str | os.PathLike | None) -> None:
        self.path = None if path is None else Path(path)
        if self.path is None:
            self._tmp = None
            self._f = h5py.File(f"results-{id(self)}-{time.monotonic_ns()}.h5", "w", driver="core",
                                backing_store=False)
        else:
            self._tmp = self.path.with_name(self.path.name + ".partial")
            # room to close the file even if the disk fills meanwhile (HDF5 would crash at exit otherwise)
            self._reserve = SpaceReserve(self._tmp)
            try:
                self._f = h5py.File(self._tmp, "w")
            except BaseException:  # e.g. no room for its first bytes: HDF5 leaves an empty file
                self._reserve.release()
                self._tmp.unlink(missing_ok=True)
                raise
        f = self._f
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = FORMAT_VERSION
        f.attrs["created_unix"] = time.time()
        f.attrs["conventions"] = CONVENTIONS
        f.attrs["status_codes"] = json.dumps(_CODES["status"])
        f.attrs["kind_codes"] = json.dumps(_CODES["kind"])
        self._tables: dict[str, h5py.Dataset] = {}
        self._done = False

    @property
    def file(self) -> h5py.File:
        return self._f

    @property
    def scratch_dir(self) -> Path | None:
        """Where the analysis may keep scratch files: next to the results (None for results in memory)."""
        return None if self.path is None else self.path.parent

    def samples(self) -> StoredSamples:
        """The motion samples written so far (``motion_pairs`` and ``motion``), read back lazily."""
        return StoredSamples(lambda: nullcontext(self._f), pair_index(self._f["motion_pairs"]))

    def _table(self, name: str, dtype: np.dtype) -> h5py.Dataset:
        if name not in self._tables:
            ds = self._f.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype,
                                        chunks=(max(1, (1 << 16) // dtype.itemsize),), compression="gzip",
                                        compression_opts=1)
            describe_dataset(ds, results_dataset_info(name))
            self._tables[name] = ds
        return self._tables[name]

    def append(self, name: str, rows: np.ndarray) -> None:
        """Append ``rows`` (a structured array) to the table ``name`` (created on first use)."""
        ds = self._table(name, rows.dtype)
        n = ds.shape[0]
        ds.resize((n + rows.shape[0],))
        step = 1 << 16  # a block at a time: h5py converts a compound selection through a buffer of its size
        for i in range(0, rows.shape[0], step):
            ds[n + i : n + min(i + step, rows.shape[0])] = rows[i : i + step]

    def append_array(self, name: str, block: np.ndarray) -> None:
        """Append ``block`` along its first axis to the array ``name`` (created on first use, like :meth:`array`):
        per-frame arrays written a block of frames at a time."""
        if name not in self._tables:
            row_bytes = max(1, int(np.prod(block.shape[1:], dtype=np.int64)) * block.dtype.itemsize)
            ds = self._f.create_dataset(name, shape=(0, *block.shape[1:]), maxshape=(None, *block.shape[1:]),
                                        dtype=block.dtype, chunks=(max(1, (1 << 16) // row_bytes), *block.shape[1:]))
            describe_dataset(ds, results_dataset_info(name))
            self._tables[name] = ds
        ds = self._tables[name]
        n = ds.shape[0]
        ds.resize(n + block.shape[0], axis=0)
        ds[n:] = block

    def array(self, name: str, data: np.ndarray) -> None:
        """Write ``data`` as the dataset ``name``, described as :data:`RESULTS_DATASETS` says."""
        ds = self._f.create_dataset(name, data=data)
        describe_dataset(ds, results_dataset_info(name))

    def start_flow(self, grid_x: np.ndarray, grid_y: np.ndarray) -> None:
        g = self._f.require_group("flow")
        for name, arr in (("grid_x", grid_x), ("grid_y", grid_y)):
            g[name] = arr
            describe_dataset(g[name], results_dataset_info(f"flow/{name}"))
        gy, gx = grid_y.size, grid_x.size
        d = g.create_dataset("displacement", shape=(0, gy, gx, 2), maxshape=(None, gy, gx, 2), dtype=np.float32,
                             chunks=(1, gy, gx, 2), compression="gzip", compression_opts=1)
        describe_dataset(d, results_dataset_info("flow/displacement"))
        v = g.create_dataset("valid", shape=(0, gy, gx), maxshape=(None, gy, gx), dtype=bool, chunks=(1, gy, gx),
                             compression="gzip", compression_opts=1)
        describe_dataset(v, results_dataset_info("flow/valid"))

    def append_flow(self, displacement: np.ndarray, valid: np.ndarray) -> None:
        """One pair's field: displacement (GY, GX, 2) with NaN where not valid (stored as 0), valid (GY, GX)."""
        g = self._f["flow"]
        n = g["displacement"].shape[0]
        g["displacement"].resize(n + 1, axis=0)
        g["valid"].resize(n + 1, axis=0)
        g["displacement"][n] = np.nan_to_num(displacement, nan=0.0).astype(np.float32)
        g["valid"][n] = valid

    def finish(self, attrs: dict[str, Any]) -> "Results":
        """Write the root attributes, close (rename) the file and return it opened as :class:`Results`."""
        for k, v in attrs.items():
            self._f.attrs[k] = v
        self._done = True
        if self.path is None:
            self._f.flush()
            return Results(self._f, source_name="(in memory)")
        try:
            close_on_a_full_disk(self._f, self._tmp, reserve=self._reserve, lost="no results kept", keep=self)
        except BaseException:
            self._tmp.unlink(missing_ok=True)
            raise
        finally:
            self._reserve.release()
        os.replace(self._tmp, self.path)
        return read_results(self.path)

    def abort(self) -> None:
        """Drop what was written (the analysis failed)."""
        if self._done:
            return
        self._done = True
        if self._tmp is None:
            self._f.close()
            return
        try:
            close_on_a_full_disk(self._f, self._tmp, reserve=self._reserve, lost="no results kept", keep=self)
        except (DiskFullError, OSError, RuntimeError) as exc:  # the error that made us abort is the one to report
            log.warning("%s: %s", self._tmp, exc)
        finally:
            self._reserve.release()
            self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> "ResultsWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()


# ----------------------------------------------------------------------------------------------------- reading


def pair_index(ds: h5py.Dataset) -> np.ndarray:
    """The columns of a ``pairs`` table that locate each pair's rows (not its reasons: 96 bytes a pair)."""
    return ds.fields(["frame_a", "frame_b", "n_points"])[()]


def pair_row_offsets(n_points: np.ndarray) -> np.ndarray:
    """The first row of each pair in the ``motion`` table, and one past the last pair's rows: the pairs' rows follow
    one another in pair order, ``n_points`` each."""
    return np.concatenate([[0], np.cumsum(np.asarray(n_points, dtype=np.int64))])


class StoredSamples(Sequence):
    """The consecutive-pair motion samples of a results file (its ``motion`` table), read a block at a time, so the
    derived quantities can be computed from them without holding them all. ``open_file`` gives the open file;
    ``pairs`` holds each pair's ``frame_a``, ``frame_b`` and ``n_points``."""

    def __init__(self, open_file: Callable[[], Any], pairs: np.ndarray, *, block: int = 256) -> None:
        self._open = open_file
        self._pairs = pairs
        self._offsets = pair_row_offsets(pairs["n_points"])
        self._block = int(block)
        self._cache: tuple[int, list[MotionSample]] | None = None

    def __len__(self) -> int:
        return int(self._pairs.shape[0])

    def _load(self, b: int) -> list[MotionSample]:
        if self._cache is not None and self._cache[0] == b:
            return self._cache[1]
        lo, hi = b * self._block, min(len(self), (b + 1) * self._block)
        off, pairs = self._offsets, self._pairs
        with self._open() as f:
            rows = f["motion"][int(off[lo]) : int(off[hi])]
        base = int(off[lo])
        out = []
        for i in range(lo, hi):
            r = rows[int(off[i]) - base : int(off[i + 1]) - base]
            out.append(MotionSample(int(pairs["frame_a"][i]), int(pairs["frame_b"][i]),
                                    np.column_stack([r["x"], r["y"]]), np.column_stack([r["dx"], r["dy"]]),
                                    r["id"].astype(np.int64)))
        self._cache = (b, out)
        return out

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        k = int(k) + (len(self) if int(k) < 0 else 0)
        if not 0 <= k < len(self):
            raise IndexError(f"pair {k} out of range for {len(self)} pairs")
        return self._load(k // self._block)[k % self._block]

    def __iter__(self) -> Iterator[MotionSample]:
        for b in range(0, -(-len(self) // self._block)):
            yield from self._load(b)


class Results:
    """One analysis' results (``docs/results-format.md``), read from the file part by part as they are used.

    Scalars and small arrays are read when opened; tables (motion, strain, features, trajectories, flow fields) on
    first use, then kept. :meth:`samples` iterates the consecutive-pair motion without loading it all.
    """

    def __init__(self, source: str | os.PathLike | h5py.File, *, source_name: str | None = None) -> None:
        if isinstance(source, h5py.File):
            self._file: h5py.File | None = source
            self.path = Path(source_name or "(in memory)")
        else:
            self._file = None
            self.path = Path(source)
        with self.open() as f:
            self._check(f)
            a = f.attrs
            self.method = str(a["method"])
            self.session_path = str(a["session_path"])
            self.n_frames = int(a["n_frames"])
            self.image_shape = tuple(int(v) for v in a["image_shape"])
            self.px_per_mm = float(a["px_per_mm"])
            self.coordinates = str(a["coordinates"])
            self.timing: dict[str, float] = json.loads(str(a["timing_json"]))
            self.params: dict[str, Any] = json.loads(str(a["params_json"]))
            # the analysis plan executed (AnalysisPlan.to_dict); {} in results written before it was recorded
            self.plan: dict[str, Any] = json.loads(str(a.get("plan_json", "{}")))
            self.versions: dict[str, str] = json.loads(str(a["versions_json"]))
            self.window: dict[str, Any] = json.loads(str(a["window_json"]))
            self.summary: dict[str, Any] = json.loads(str(a.get("summary_json", "{}")))
            self.frame_flags: list[str] = [s.decode() for s in f["frame_flags"][()]]
            ft = f["fingertip"]
            self.fingertip = FingertipMotion(ft["displacement"][()], ft["n_points"][()], ft["valid"][()],
                                             ft["position"][()])
            p = f["profile"]
            self.profile_axis: str = str(p.attrs["axis"])
            self.profile = StretchProfile(p["position"][()], p["change"][()], p["valid"][()])
            self.spans: tuple[int, ...] = tuple(sorted(int(f["strain"][k].attrs["span"]) for k in f["strain"]))
            self.has_features = "features" in f
            self.has_trajectories = "trajectories" in f
            self.has_flow = "flow" in f
            self.has_movie = "tactile_movie" in f
            self.has_cumulative = "cumulative" in f

    # -- the file
    @contextmanager
    def open(self) -> Iterator[h5py.File]:
        """The underlying HDF5 file, open for reading (in memory, or reopened from the path each time)."""
        if self._file is not None:
            with nullcontext(self._file) as f:
                yield f
            return
        try:
            f = h5py.File(self.path, "r")
        except OSError as exc:
            raise SessionFileError(f"{self.path}: HDF5 file cannot be opened, truncated or corrupt ({exc})") from None
        with f:
            try:
                yield f
            except (KeyError, ValueError, TypeError) as exc:
                raise SessionFileError(f"{self.path}: results file is missing or has a damaged part ({exc})") from None

    def _check(self, f: h5py.File) -> None:
        fmt = f.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        if fmt != FORMAT_NAME:
            raise SessionFileError(f"{self.path}: not a skinstretch results file (format attribute {fmt!r})")
        version = int(f.attrs.get("format_version", -1))
        if version != FORMAT_VERSION:
            raise SessionFileError(f"{self.path}: results format version {version} is not supported (this skinstretch "
                                   f"reads {FORMAT_VERSION}); analyse the session again with skinstretch analyze")
        for part in ("frame_flags", "motion_pairs", "motion", "fingertip", "profile", "strain"):
            if part not in f:
                raise SessionFileError(f"{self.path}: results file is missing or has a damaged part ({part!r})")

    def _read(self, name: str) -> np.ndarray:
        with self.open() as f:
            return f[name][()]

    def dataset_info(self, name: str) -> DatasetInfo:
        """What dataset ``name`` holds ("motion", "strain/span_1/edges", "flow/displacement"...): its units, axis
        names, columns and code names, from its attributes; a file written before they were complete is described
        by :data:`RESULTS_DATASETS`, which is what its writer meant."""
        with self.open() as f:
            ds = f.get(name)
            if not isinstance(ds, h5py.Dataset):
                raise SessionFileError(f"{self.path}: no dataset {name!r}")
            info = read_dataset_info(ds)
        return info if info is not None else results_dataset_info(name)

    # -- per pair
    @cached_property
    def motion_pairs(self) -> np.ndarray:
        """PAIR_DTYPE: one row per consecutive pair."""
        return self._read("motion_pairs")

    @cached_property
    def motion(self) -> np.ndarray:
        """MOTION_DTYPE: every measured displacement, ``pair`` indexing :attr:`motion_pairs`."""
        return self._read("motion")

    def samples(self) -> StoredSamples:
        """The consecutive-pair motion as :class:`~skinstretch.processing.tracking.MotionSample` s, read lazily."""
        if "motion_pairs" in self.__dict__:
            return StoredSamples(self.open, self.motion_pairs)
        with self.open() as f:
            return StoredSamples(self.open, pair_index(f["motion_pairs"]))

    @cached_property
    def strain(self) -> dict[int, SpanStrain]:
        """Span -> triangulation strain tables."""
        out = {}
        with self.open() as f:
            for name in f["strain"]:
                h = f["strain"][name]
                span = int(h.attrs["span"])
                out[span] = SpanStrain(span, h["pairs"][()], h["edges"][()], h["triangles"][()])
        return dict(sorted(out.items()))

    @cached_property
    def cumulative(self) -> CumulativeStrain | None:
        """Motion and strain of every frame relative to the reference frame, or None (results written before it
        was measured)."""
        if not self.has_cumulative:
            return None
        with self.open() as f:
            g = f["cumulative"]
            return CumulativeStrain(int(g.attrs["reference_frame"]), g["pairs"][()], g["motion"][()],
                                    g["edges"][()], g["triangles"][()])

    # -- per frame
    @property
    def visibility_window(self) -> VisibilityWindow | None:
        if "x0" not in self.window:
            return None
        with self.open() as f:
            centers = f["window_centers"][()]
        w = self.window
        return VisibilityWindow(float(w["x0"]), float(w["y0"]), float(w["x1"]), float(w["y1"]), centers)

    @cached_property
    def movie(self) -> TactileMovieTable | None:
        """The tactile movie, or None when the analysis could not make one (``window`` says why)."""
        if not self.has_movie:
            return None
        with self.open() as f:
            t = f["tactile_movie"]
            return TactileMovieTable(t["positions_um"][()], t["reset"][()], t["clipped"][()],
                                     t["stretch_change"][()], str(t.attrs["motion_axis"]))

    @cached_property
    def features(self) -> np.ndarray | None:
        """(features method) every extracted feature (FEATURE_DTYPE), or None."""
        return self._read("features") if self.has_features else None

    @property
    def density(self) -> MeshDensity | None:
        """How dense the measurement is (:class:`MeshDensity`: features per frame, trajectories kept, fraction kept,
        mesh edge, whether the mesh is too sparse to map strain), or None for results written before it was reported."""
        d = self.summary.get("density")
        return MeshDensity.from_dict(d) if d else None

    @cached_property
    def trajectories(self) -> Trajectories | None:
        """(features method) the trajectories as a long table, or None."""
        if not self.has_trajectories:
            return None
        with self.open() as f:
            rows = f["trajectories"][()]
            tracks = f["tracks"][()]
        if "anchor_sigma" not in (rows.dtype.names or ()):  # written before the column: not estimated
            old, rows = rows, np.zeros(rows.shape, TRAJECTORY_DTYPE)
            for name in old.dtype.names:
                rows[name] = old[name]
            rows["anchor_sigma"] = np.inf
        return Trajectories(n_frames=self.n_frames, rows=rows.astype(TRAJECTORY_DTYPE, copy=False),
                            kind=tracks["kind"].astype(np.int8))

    @cached_property
    def tracks(self) -> np.ndarray | None:
        """(features method) TRACK_DTYPE: kind, length, first and last frame of each trajectory, or None."""
        return self._read("tracks") if self.has_trajectories else None

    @cached_property
    def flow(self) -> FlowResults | None:
        """(flow method) the grid and every pair's field, or None."""
        if not self.has_flow:
            return None
        with self.open() as f:
            g = f["flow"]
            return FlowResults(g["grid_x"][()], g["grid_y"][()], g["displacement"][()], g["valid"][()])

    # -- flat shortcuts (report, playback)
    @property
    def fingertip_displacement(self) -> np.ndarray:
        return self.fingertip.displacement

    @property
    def fingertip_valid(self) -> np.ndarray:
        return self.fingertip.valid

    @property
    def fingertip_position(self) -> np.ndarray:
        return self.fingertip.position

    @property
    def profile_position(self) -> np.ndarray:
        return self.profile.x

    @property
    def profile_change(self) -> np.ndarray:
        return self.profile.change

    @property
    def profile_valid(self) -> np.ndarray:
        return self.profile.valid

    @property
    def profile_axis_index(self) -> int:
        """0 (image x) or 1 (image y): :attr:`profile_axis` as an array index."""
        return AXIS_NAMES.index(self.profile_axis)

    @property
    def tactile_positions_um(self) -> np.ndarray | None:
        return None if self.movie is None else self.movie.positions_um

    @property
    def tactile_reset(self) -> np.ndarray | None:
        return None if self.movie is None else self.movie.reset

    @property
    def tactile_clipped(self) -> np.ndarray | None:
        return None if self.movie is None else self.movie.clipped

    @property
    def tactile_stretch_change(self) -> np.ndarray | None:
        return None if self.movie is None else self.movie.stretch_change

    # -- tables for users
    def to_dataframe(self, part: str, *, span: int = 1):
        """A pandas DataFrame of one part: ``"trajectories"``, ``"motion"``, ``"strain"`` (edges of ``span``),
        ``"triangles"`` (of ``span``, with each triangle's strain tensor), ``"cumulative"`` (the triangles of every
        frame relative to the reference frame), ``"profile"``, ``"fingertip"`` or ``"features"``."""
        import pandas as pd  # noqa: PLC0415 - only for users who ask for DataFrames

        if part == "trajectories":
            if self.trajectories is None:
                raise SessionFileError(f"{self.path}: {self.method} results have no trajectories")
            return pd.DataFrame(self.trajectories.rows)
        if part == "motion":
            return pd.DataFrame(self.motion)
        if part in ("strain", "triangles"):
            if span not in self.strain:
                raise SessionFileError(f"{self.path}: no strain at span {span} (spans {list(self.strain)})")
            s = self.strain[span]
            table = pd.DataFrame(s.edges if part == "strain" else s.triangles)
            pairs = pd.DataFrame({"pair": np.arange(s.pairs.size), "frame_a": s.pairs["frame_a"],
                                  "frame_b": s.pairs["frame_b"]})
            return table.merge(pairs, on="pair", how="left")
        if part == "cumulative":
            c = self.cumulative
            if c is None:
                raise SessionFileError(f"{self.path}: results written before the cumulative strain was measured; "
                                       "analyse the session again")
            pairs = pd.DataFrame({"pair": np.arange(c.pairs.size), "frame_a": c.pairs["frame_a"],
                                  "frame_b": c.pairs["frame_b"]})
            return pd.DataFrame(c.triangles).merge(pairs, on="pair", how="left")
        if part == "profile":
            return pd.DataFrame({f"position_{self.profile_axis}_px": self.profile.x, "change": self.profile.change,
                                 "valid": self.profile.valid})
        if part == "fingertip":
            d, p = self.fingertip.displacement, self.fingertip.position
            return pd.DataFrame({"frame": np.arange(self.n_frames), "x": p[:, 0], "y": p[:, 1],
                                 "dx_to_next": np.append(d[:, 0], np.nan), "dy_to_next": np.append(d[:, 1], np.nan),
                                 "valid_to_next": np.append(self.fingertip.valid, False)})
        if part == "features":
            if self.features is None:
                raise SessionFileError(f"{self.path}: {self.method} results have no features")
            return pd.DataFrame(self.features)
        raise SessionFileError(f"unknown results part {part!r} (trajectories, motion, strain, triangles, cumulative, "
                               "profile, fingertip, features)")

    def __repr__(self) -> str:
        return f"Results({str(self.path)!r}, method={self.method}, frames={self.n_frames})"


def held_results(outdir: str | os.PathLike) -> list[Path]:
    """The results files of an analysis already in ``outdir`` (``results.h5``, ``summary.json``)."""
    outdir = Path(outdir)
    return [outdir / name for name in (RESULTS_FILE, SUMMARY_FILE) if (outdir / name).exists()]


def check_results_dir(outdir: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Check, before anything is analysed, that an analysis can write into ``outdir``: a writable directory (or
    one that can be created) holding no results of an earlier analysis, unless ``overwrite``. Raises
    :class:`~skinstretch.experiments.output_paths.OutputPathError` in one line naming the directory and, for
    results already there, the ``overwrite`` argument (``--overwrite`` on the command line)."""
    outdir = check_output_dir(outdir)
    refuse_held_results(outdir, held_results(outdir), overwrite=overwrite)
    return outdir


def refuse_held_results(outdir: Path, held: Sequence[Path], *, overwrite: bool) -> None:
    """OutputPathError naming ``outdir``, the first of ``held`` (results already there) and the ``overwrite``
    argument, unless ``held`` is empty or ``overwrite``."""
    if held and not overwrite:
        first = held[0].relative_to(outdir) if held[0].is_relative_to(outdir) else held[0]
        raise OutputPathError(f"{outdir}: holds the results of an analysis already ({first})",
                              remedy=Remedy(("overwrite",), "to replace them", True))


def read_results(path: str | os.PathLike) -> Results:
    """Open a results file (or an analysis directory holding ``results.h5``), or raise SessionFileError saying why
    it cannot be read."""
    path = Path(path)
    if path.is_dir():
        path = path / RESULTS_FILE
    if not path.exists():
        raise SessionFileError(f"{path}: no such results file")
    return Results(path)


def pair_rows(frame_a: Sequence[int], frame_b: Sequence[int], n_points: Sequence[int], status: Sequence[int],
              reasons: Sequence[str]) -> np.ndarray:
    """A PAIR_DTYPE table."""
    out = np.zeros(len(frame_a), dtype=PAIR_DTYPE)
    out["frame_a"], out["frame_b"], out["n_points"], out["status"] = frame_a, frame_b, n_points, status
    out["reason"] = [r.encode()[:96] for r in reasons]
    return out

