"""What the viewer shows, read from a session file and its analysis results: the ONE adapter between the viewer and
the results file.

Everything the viewer needs from ``results.h5`` goes through :func:`load_results_index` (built on
:func:`skinstretch.experiments.results_file.read_results`), which turns the stored tables into per-frame indexes;
:meth:`ResultsIndex.overlays` then cuts one frame's overlays out of them. When the results layout changes (for
example trajectories stored as a long table), this file is the one to adapt.

A session still being recorded is read in SWMR mode through :class:`SessionSource`; it has no results yet, and
its overlays come from the live analysis (:mod:`skinstretch.experiments.viewer.live_analysis`) instead. Every file
is opened as :func:`~skinstretch.drivers.session_file.open_session` opens it for ``analyze`` (refused in one line
when truncated or corrupt) and without a file lock, so the viewer never makes the recorder's writes fail.

Coordinates are image pixels, x = column, y = row; strains are fractions (the page shows %).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import orjson

from skinstretch.drivers.errors import SessionFileError
from skinstretch.drivers.session_file import Session, held_for_writing, open_hdf5_for_reading, open_session
from skinstretch.experiments.results_file import read_results

log = logging.getLogger(__name__)

__all__ = [
    "FeatureMarks",
    "FrameOverlays",
    "Mesh",
    "ResultsIndex",
    "SessionSource",
    "TruthMarks",
    "ViewTarget",
    "find_view_target",
    "load_results_index",
    "nice_scale",
]

#: What the viewer's strain map can show: the triangles' area change, the edges' length change, the Green-Lagrange
#: components and the principal strains (docs/viewer.md); numeric triangle columns beyond these (an uncertainty)
#: are offered as well, under their own names.
MAP_QUANTITIES = ("area", "edge", "exx", "eyy", "exy", "e1", "e2")
#: The span that stands for the cumulative strain (from the reference frame) in the page's span selector.
CUMULATIVE = 0
_NOT_MAPPED = frozenset({"pair", "id_a", "id_b", "id_c", "x0", "y0", "x1", "y1", "x2", "y2", "area", "change",
                         "flipped", "tensor_status", "angle_deg"})

RESULTS_FILE = "results.h5"
SESSION_FILE = "session.h5"
ANALYSIS_DIR = "analysis"
TAIL_FRAMES = 12  # frames of trajectory drawn behind each feature


# ------------------------------------------------------------------------------------------- typed overlays


@dataclass
class FeatureMarks:
    """Features of one frame: ids (feature row), track index (-1 when untracked), kind, position, quality."""

    id: np.ndarray
    track: np.ndarray
    kind: np.ndarray
    x: np.ndarray
    y: np.ndarray
    quality: np.ndarray

    @staticmethod
    def empty() -> "FeatureMarks":
        z = np.zeros(0)
        return FeatureMarks(z.astype(np.int64), z.astype(np.int64), z.astype(np.int8), z, z, z.astype(np.float32))


@dataclass
class Mesh:
    """Delaunay triangles of one frame pair: vertex positions (m, 6) x0 y0 x1 y1 x2 y2, their track ids (m, 3),
    relative area change (fraction) and whether the triangle flipped (orientation change: not a strain)."""

    span: int
    frame_a: int
    frame_b: int
    xy: np.ndarray
    ids: np.ndarray
    change: np.ndarray
    flipped: np.ndarray
    drawn_at: str  # which frame's positions the vertices are drawn at: "frame_b" or "frame_a"
    #: Every quantity a map can show per triangle (MAP_QUANTITIES and any further numeric column, e.g. an
    #: uncertainty), fractions; "area" is ``change``.
    values: dict[str, np.ndarray] = field(default_factory=dict)
    edge_xy: np.ndarray | None = None  # (e, 4) x0 y0 x1 y1, drawn where the vertices are
    edge_change: np.ndarray | None = None  # (e,) L_b / L_a - 1


@dataclass
class TruthMarks:
    """True features of a simulated session in this frame and the previous one (px), visible in this frame."""

    id: np.ndarray
    kind: np.ndarray
    x: np.ndarray
    y: np.ndarray
    prev_x: np.ndarray
    prev_y: np.ndarray


@dataclass
class FrameOverlays:
    """Everything drawn over one frame. Arrays of segments are (n, 4): x0, y0, x1, y1 (from the earlier frame)."""

    frame: int
    source: str  # "results", "live" or "none"
    features: FeatureMarks
    matches: np.ndarray
    arrows: np.ndarray  # x, y (this frame), dx, dy (displacement from the previous frame to this one)
    tails: list[np.ndarray]  # one (k, 2) polyline per track, oldest first
    mesh: Mesh | None
    outline: np.ndarray  # (k, 2) hull of the measured points of this frame
    window: tuple[float, float, float, float] | None  # x0, y0, x1, y1 in this frame
    tactile_um: np.ndarray | None  # (10, 10)
    tactile_reset: np.ndarray | None
    tactile_clipped: np.ndarray | None
    truth: TruthMarks | None
    strain_scale: float  # fraction; the colour scale runs from -strain_scale to +strain_scale
    notes: list[str] = field(default_factory=list)
    arrow_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # track (or grid node) per arrow
    arrow_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))  # predicted standard error per arrow, px
    exposure_time: float | None = None  # host time stamp (s, Unix) of the frame (live view latency)
    analysed_time: float | None = None
    _json: bytes | None = field(default=None, init=False, repr=False, compare=False)

    def to_json(self) -> dict[str, Any]:
        """JSON-able form for the page (numbers rounded to what a screen can show)."""
        return orjson.loads(self.to_json_bytes())

    def to_json_bytes(self) -> bytes:
        """The page's JSON of these overlays, encoded once (every page drawing a live frame fetches the same)."""
        if self._json is None:
            self._json = orjson.dumps(self._payload(), option=orjson.OPT_SERIALIZE_NUMPY)
        return self._json

    def _payload(self) -> dict[str, Any]:
        # Arrays stay numpy (orjson writes them without a Python float per number: ~10x faster than json).
        f = self.features
        mesh = None
        if self.mesh is not None:
            m = self.mesh
            mesh = {
                "span": m.span, "frame_a": m.frame_a, "frame_b": m.frame_b, "drawn_at": m.drawn_at,
                "xy": _round(m.xy, 2), "ids": _ints(m.ids).ravel(),
                "change": _round(m.change, 5), "flipped": np.asarray(m.flipped, bool),
                "values": {k: _round(v, 6) for k, v in m.values.items()},
                "edge_xy": _round(m.edge_xy, 2) if m.edge_xy is not None else None,
                "edge_change": _round(m.edge_change, 6) if m.edge_change is not None else None,
            }
        truth = None
        if self.truth is not None:
            t = self.truth
            truth = {"id": _ints(t.id), "kind": _ints(t.kind), "x": _round(t.x, 3), "y": _round(t.y, 3),
                     "prev_x": _round(t.prev_x, 3), "prev_y": _round(t.prev_y, 3)}
        return {
            "frame": int(self.frame),
            "source": self.source,
            "features": {"id": _ints(f.id), "track": _ints(f.track), "kind": _ints(f.kind),
                         "x": _round(f.x, 3), "y": _round(f.y, 3), "quality": _round(f.quality, 3)},
            "matches": _round(self.matches, 2),
            "arrows": _round(self.arrows, 3),
            "arrow_ids": _ints(self.arrow_ids),
            "arrow_sigma": _round(np.nan_to_num(self.arrow_sigma, nan=-1.0, posinf=1e9), 4),  # -1 none, 1e9 inf
            "tails": _round_polylines(self.tails, 1),
            "mesh": mesh,
            "outline": _round(self.outline, 1),
            "window": [float(v) for v in self.window] if self.window is not None else None,
            "tactile_um": _round(self.tactile_um, 2) if self.tactile_um is not None else None,
            "tactile_reset": np.asarray(self.tactile_reset, bool) if self.tactile_reset is not None else None,
            "tactile_clipped": np.asarray(self.tactile_clipped, bool) if self.tactile_clipped is not None else None,
            "truth": truth,
            "strain_scale": float(self.strain_scale),
            "notes": list(self.notes),
            "exposure_time": self.exposure_time,
            "analysed_time": self.analysed_time,
        }


def _round(a: np.ndarray, digits: int) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    return np.ascontiguousarray(np.where(np.isfinite(a), np.round(a, digits), 0.0))


def _round_polylines(lines: list[np.ndarray], digits: int) -> list[np.ndarray]:
    """:func:`_round` of every polyline at once (a live frame has hundreds of short tails)."""
    if not lines:
        return []
    rounded = _round(np.concatenate([np.asarray(t, np.float64).reshape(-1, 2) for t in lines]), digits)
    ends = np.cumsum([0] + [len(t) for t in lines]).tolist()
    return [rounded[a:b] for a, b in zip(ends[:-1], ends[1:])]


def _ints(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.int64)


def empty_overlays(frame: int, note: str, *, source: str = "none", strain_scale: float = 0.02) -> FrameOverlays:
    """Overlays of a frame that has none, saying why."""
    return FrameOverlays(
        frame=frame, source=source, features=FeatureMarks.empty(), matches=np.zeros((0, 4)), arrows=np.zeros((0, 4)),
        tails=[], mesh=None, outline=np.zeros((0, 2)), window=None, tactile_um=None, tactile_reset=None,
        tactile_clipped=None, truth=None, strain_scale=strain_scale, notes=[note],
    )


def nice_scale(values: np.ndarray, *, percentile: float = 98.0, floor: float = 0.001) -> float:
    """A round colour-scale limit (fraction) covering ``percentile`` % of ``|values|``: 1, 2 or 5 times a power of
    ten, never below ``floor`` (0.1 %) so that a still finger does not paint noise at full colour."""
    v = np.abs(np.asarray(values, dtype=np.float64))
    v = v[np.isfinite(v)]
    top = float(np.percentile(v, percentile)) if v.size else floor
    top = max(top, floor)
    exponent = np.floor(np.log10(top))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10**exponent >= top * (1 - 1e-9):
            return float(m * 10**exponent)
    return float(10 ** (exponent + 1))  # pragma: no cover - the loop always returns


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise hull of (n, 2) points (OpenCV), empty for fewer than 3."""
    import cv2  # noqa: PLC0415

    pts = np.asarray(points, dtype=np.float32).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if pts.shape[0] < 3:
        return np.zeros((0, 2))
    return cv2.convexHull(pts).reshape(-1, 2).astype(np.float64)


# ----------------------------------------------------------------------------------------------- sessions


class SessionSource:
    """A session file opened for the viewer: frames on demand, follows a recording in SWMR mode.

    Reads are serialised by a lock (h5py handles are not safe to share between threads).
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._lock = threading.Lock()
        self._session: Session = open_session(self.path)
        self._opened_as = self._on_disk()
        self._truth = None
        self._truth_loaded = False

    def _on_disk(self) -> tuple[int, int]:
        st = self.path.stat()
        return st.st_mtime_ns, st.st_size

    @property
    def session(self) -> Session:
        return self._session

    def n_frames(self) -> int:
        with self._lock:
            return self._session.n_frames

    def status(self) -> str:
        """'recording', 'complete' or 'failed', read again from the file (a recorder changes it at the end)."""
        with self._lock:
            return self._session.refresh_status()

    def frame(self, index: int) -> np.ndarray:
        with self._lock:
            return self._session.frame(index)

    def timestamp(self, index: int) -> float:
        with self._lock:
            return self._session.timestamp(index)

    def truth(self):
        """The simulated session's truth, or None (a recording gets its truth after it is closed: see
        :meth:`reopen_if_changed`)."""
        if not self._truth_loaded:
            with self._lock:
                if self._session.has_truth:
                    self._truth = self._session.truth
                    self._truth_loaded = True
                elif self._session.complete:
                    self._truth_loaded = True
        return self._truth

    def reopen_if_changed(self, *, wait_s: float = 2.0) -> bool:
        """Open the file again when it changed on disk since it was opened (its recorder closed it, a ground truth
        was attached), so that what was written is seen; True when it did. Not while another program holds it
        open for writing (it would refuse the reader): False, and the caller asks again later. A writer that
        takes it between that check and the opening is waited for up to ``wait_s``."""
        if self._on_disk() == self._opened_as or held_for_writing(self.path):
            return False
        with self._lock:
            self._session.close()
            deadline = time.monotonic() + wait_s
            while True:
                try:
                    self._session = open_session(self.path)
                    break
                except SessionFileError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)
            self._opened_as = self._on_disk()
            self._truth, self._truth_loaded = None, False
        return True

    def describe(self) -> dict[str, Any]:
        s = self._session
        return {
            "path_name": self.path.name,
            "trial_dir": self.path.parent.name,
            "width": int(s.camera_mode.width),
            "height": int(s.camera_mode.height),
            "fps": float(s.camera_mode.fps),
            "px_per_mm": float(s.calibration.px_per_mm),
            "metadata": {k: s.metadata.get(k) for k in ("trial", "surface", "scene", "protocol", "direction")
                         if k in s.metadata},
        }

    def close(self) -> None:
        with self._lock:
            self._session.close()


# ------------------------------------------------------------------------------------------------ results


@dataclass
class _PerFrame:
    """Row offsets of a table sorted by a frame (or pair) column: rows of key k are order[start[k]:start[k+1]]."""

    order: np.ndarray
    start: np.ndarray

    @staticmethod
    def build(keys: np.ndarray, n: int) -> "_PerFrame":
        keys = np.asarray(keys, dtype=np.int64)
        order = np.argsort(keys, kind="stable")
        start = np.searchsorted(keys[order], np.arange(n + 1))
        return _PerFrame(order, start)

    def rows(self, k: int) -> np.ndarray:
        if not 0 <= k < self.start.size - 1:
            return self.order[:0]
        return self.order[self.start[k] : self.start[k + 1]]


@dataclass
class ResultsIndex:
    """The analysis results of one session, indexed per frame for the viewer."""

    path: Path
    method: str
    n_frames: int
    coordinates: str
    spans: list[int]
    strain_scale: dict[int, float]
    motion_axis: int
    has_tactile: bool
    window: dict[str, Any]
    notes: list[str]  # what the analysis said about the whole clip (its summary's notes)
    warnings: list[str]  # the summary's warnings: self-checks that failed, a large predicted error
    _features: np.ndarray | None
    _features_by_frame: _PerFrame | None
    _feature_track: np.ndarray | None  # feature row -> track
    _track_x: np.ndarray | None  # (N, T)
    _track_y: np.ndarray | None
    _track_present: np.ndarray | None
    _track_linked: np.ndarray | None
    _motion: np.ndarray
    _motion_by_pair: _PerFrame
    _triangles: dict[int, np.ndarray]
    _triangles_by_pair: dict[int, _PerFrame]
    _pair_frames: dict[int, tuple[np.ndarray, np.ndarray]]  # span -> (frame_a, frame_b) per pair row
    _window_centers: np.ndarray | None
    _tactile: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    #: span (CUMULATIVE: from the reference frame) -> quantity -> colour-scale limit (fraction)
    map_scales: dict[int, dict[str, float]] = field(default_factory=dict)
    reference_frame: int = -1  # of the cumulative strain; -1 without one
    _edges: dict[int, np.ndarray] = field(default_factory=dict)
    _edges_by_pair: dict[int, _PerFrame] = field(default_factory=dict)
    _cumulative_motion: np.ndarray | None = None
    _cumulative_motion_by_pair: _PerFrame | None = None
    _results: Any = None  # the Results (the gauge reads its cumulative motion)
    plan: list[tuple[str, str]] = field(default_factory=list)  # the analysis plan as rows (plan_rows)

    def describe(self) -> dict[str, Any]:
        return {
            "method": self.method,
            "coordinates": self.coordinates,
            "spans": self.spans,
            "strain_scale": {str(k): v for k, v in self.strain_scale.items()},
            "map_scales": {str(k): v for k, v in self.map_scales.items()},
            "map_quantities": self.map_quantities(),
            "reference_frame": self.reference_frame,
            "has_gauge": self.reference_frame >= 0,
            "motion_axis": self.motion_axis,
            "has_tactile": self.has_tactile,
            "window": self.window,
            "notes": list(self.notes),
            "warnings": list(self.warnings),
            "plan": [list(row) for row in self.plan],
        }

    def map_quantities(self) -> list[str]:
        """The quantities the page's map selector offers: MAP_QUANTITIES the results hold, then extra columns."""
        names: list[str] = []
        for scales in self.map_scales.values():
            names += [q for q in scales if q not in names]
        return [q for q in MAP_QUANTITIES if q in names] + [q for q in names if q not in MAP_QUANTITIES]

    def gauge(self, *, frame: int, x: float, y: float, x2: float | None = None, y2: float | None = None,
              radius_mm: float | None = None):
        """The gauge (or with ``x2``, ``y2`` the extensometer) at a point clicked on ``frame``, located in the
        reference frame first (:func:`skinstretch.experiments.probe.reference_position`)."""
        from skinstretch.experiments.probe import probe, reference_position  # noqa: PLC0415

        at = reference_position(self._results, (x, y), frame=frame, radius_mm=radius_mm)
        to = None if x2 is None or y2 is None else reference_position(self._results, (x2, y2), frame=frame,
                                                                        radius_mm=radius_mm)
        return probe(self._results, at=at, to=to, radius_mm=radius_mm)

    # -- one frame
    def overlays(self, k: int, *, span: int = 1, truth=None) -> FrameOverlays:
        """The overlays of frame ``k``: its features, their matches and displacements from frame k-1, trajectory
        tails, the mesh of the pair (k - span, k) coloured by its area change, window and tactile frame."""
        notes: list[str] = []
        if not 0 <= k < self.n_frames:
            return empty_overlays(k, f"frame {k} is beyond the {self.n_frames} analysed frames", source="results",
                                  strain_scale=self.strain_scale.get(span, 0.02))
        features = self._frame_features(k)
        matches, tails = self._matches_and_tails(k)
        arrows, arrow_ids, arrow_sigma = self._arrows(k)
        if k == 0:
            notes.append("frame 0: no previous frame, so no matches, displacements or strain")
        mesh = self._mesh(k, span)
        if span == CUMULATIVE:
            if self.reference_frame < 0:
                notes.append("no cumulative strain in these results (analysed before it was stored, or no frame "
                             "had 3 measured points)")
            elif mesh is None and k != self.reference_frame:
                notes.append(f"no cumulative strain from frame {self.reference_frame} to {k}")
        elif mesh is None and k >= span:
            notes.append(f"no strain for frames {k - span}->{k} (see the results' pair status)")
        elif mesh is None and span >= self.n_frames:
            notes.append(f"no strain over {span} frames: the {self.n_frames}-frame session has no pair that far apart")
        elif mesh is None and k > 0:
            notes.append(f"strain over {span} frames starts at frame {span}")
        if self.method == "flow":
            notes.append("flow method: displacements on a grid, no features or trajectories")
        pts = np.column_stack([features.x, features.y]) if features.x.size else arrows[:, :2]
        window = self._window(k)
        tm = self._tactile
        return FrameOverlays(
            frame=k, source="results", features=features, matches=matches, arrows=arrows, tails=tails, mesh=mesh,
            outline=convex_hull(pts), window=window,
            tactile_um=tm[0][k] if tm is not None else None,
            tactile_reset=tm[1][k] if tm is not None else None,
            tactile_clipped=tm[2][k] if tm is not None else None,
            truth=truth_marks(truth, k), strain_scale=self.strain_scale.get(span, 0.02), notes=notes,
            arrow_ids=arrow_ids, arrow_sigma=arrow_sigma,
        )

    def _frame_features(self, k: int) -> FeatureMarks:
        if self._features is None or self._features_by_frame is None:
            return FeatureMarks.empty()
        rows = self._features_by_frame.rows(k)
        f = self._features[rows]
        track = self._feature_track[rows] if self._feature_track is not None else np.full(rows.size, -1)
        return FeatureMarks(f["id"].astype(np.int64), track.astype(np.int64), f["kind"].astype(np.int8),
                            f["x"].astype(np.float64), f["y"].astype(np.float64), f["quality"].astype(np.float32))

    def _matches_and_tails(self, k: int) -> tuple[np.ndarray, list[np.ndarray]]:
        if self._track_x is None:
            return np.zeros((0, 4)), []
        present = self._track_present[k]
        tails: list[np.ndarray] = []
        matches = np.zeros((0, 4))
        if k > 0:
            linked = np.flatnonzero(present & self._track_linked[k] & self._track_present[k - 1])
            matches = np.column_stack([self._track_x[k - 1, linked], self._track_y[k - 1, linked],
                                       self._track_x[k, linked], self._track_y[k, linked]])
        lo = max(0, k - TAIL_FRAMES)
        if k > lo:
            tracks = np.flatnonzero(present)
            xs = self._track_x[lo : k + 1, tracks]
            ys = self._track_y[lo : k + 1, tracks]
            for j in range(tracks.size):
                ok = np.isfinite(xs[:, j]) & np.isfinite(ys[:, j])
                if ok.sum() >= 2:
                    tails.append(np.column_stack([xs[ok, j], ys[ok, j]]))
        return matches, tails

    def _arrows(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if k == 0:
            return np.zeros((0, 4)), np.zeros(0, np.int64), np.zeros(0)
        m = self._motion[self._motion_by_pair.rows(k - 1)]
        xy = np.column_stack([m["x"] + m["dx"], m["y"] + m["dy"], m["dx"], m["dy"]]).astype(np.float64)
        sigma = m["sigma"] if "sigma" in (m.dtype.names or ()) else np.full(m.shape[0], np.nan)
        return xy, m["id"].astype(np.int64), np.asarray(sigma, np.float64)

    def _pair_row(self, k: int, span: int) -> int:
        """The row of the pair (k - span, k), or of the cumulative pair (reference, k); -1 when there is none."""
        if span not in self._pair_frames:
            return -1
        fa, fb = self._pair_frames[span]
        if span == CUMULATIVE:
            i = int(np.searchsorted(fb, k))
            return i if i < fb.size and fb[i] == k else -1
        pair = k - span  # pair rows are indexed by their first frame
        return pair if 0 <= pair < fa.size and fa[pair] == k - span and fb[pair] == k else -1

    def _positions_at(self, k: int, span: int, pair: int, ids: np.ndarray) -> np.ndarray | None:
        """Where the points ``ids`` (any shape) are in frame k, (..., 2); None when one of them is not known."""
        if self._track_x is not None:
            # Features: ids are track indices, so the vertices can be drawn where they are now.
            p = np.stack([self._track_x[k][ids], self._track_y[k][ids]], axis=-1)
            return p if np.isfinite(p).all() else None
        if span == 1:
            m = self._motion[self._motion_by_pair.rows(pair)]
        elif span == CUMULATIVE and self._cumulative_motion is not None:
            m = self._cumulative_motion[self._cumulative_motion_by_pair.rows(pair)]
        else:
            return None
        order = np.argsort(m["id"], kind="stable")
        sorted_ids = m["id"][order]
        j = np.searchsorted(sorted_ids, ids)
        j = np.minimum(j, max(sorted_ids.size - 1, 0))
        if sorted_ids.size == 0 or not np.all(sorted_ids[j] == ids):
            return None
        rows = order[j]
        return np.stack([(m["x"] + m["dx"])[rows], (m["y"] + m["dy"])[rows]], axis=-1)

    def _mesh(self, k: int, span: int) -> Mesh | None:
        if span not in self._triangles:
            return None
        pair = self._pair_row(k, span)
        if pair < 0:
            return None
        t = self._triangles[span][self._triangles_by_pair[span].rows(pair)]
        if t.size == 0:
            return None
        fa = int(self._pair_frames[span][0][pair])
        ids = np.column_stack([t["id_a"], t["id_b"], t["id_c"]]).astype(np.int64)
        xy = np.column_stack([t["x0"], t["y0"], t["x1"], t["y1"], t["x2"], t["y2"]]).astype(np.float64)
        drawn_at = "frame_a"
        moved = self._positions_at(k, span, pair, ids)
        if moved is not None:
            xy, drawn_at = moved.reshape(-1, 6), "frame_b"
        values = {"area": t["change"].astype(np.float64)}
        for name in t.dtype.names:
            if name not in _NOT_MAPPED and t.dtype[name].kind == "f":
                values[name] = t[name].astype(np.float64)
        edge_xy = edge_change = None
        if span in self._edges:
            e = self._edges[span][self._edges_by_pair[span].rows(pair)]
            edge_change = e["change"].astype(np.float64)
            edge_xy = np.column_stack([e["xa"], e["ya"], e["xb"], e["yb"]]).astype(np.float64)
            if drawn_at == "frame_b":
                ends = self._positions_at(k, span, pair, np.column_stack([e["id_a"], e["id_b"]]).astype(np.int64))
                if ends is not None:
                    edge_xy = ends.reshape(-1, 4)
        return Mesh(span, fa, k, xy, ids, t["change"].astype(np.float64), t["flipped"].astype(bool), drawn_at,
                    values, edge_xy, edge_change)

    def _window(self, k: int) -> tuple[float, float, float, float] | None:
        w = self.window
        if self._window_centers is None or "x0" not in w:
            return None
        cx, cy = self._window_centers[k]
        hw, hh = (w["x1"] - w["x0"]) / 2, (w["y1"] - w["y0"]) / 2
        return (float(cx - hw), float(cy - hh), float(cx + hw), float(cy + hh))


def truth_marks(truth, k: int) -> TruthMarks | None:
    """True features visible in frame ``k`` (and where they were in frame k-1), or None without truth."""
    if truth is None:
        return None
    fx = np.asarray(truth.feature_x)
    if not 0 <= k < fx.shape[0]:
        return None
    vis = np.asarray(truth.feature_visible)[k]
    j = np.flatnonzero(vis)
    prev = max(k - 1, 0)
    return TruthMarks(
        id=np.asarray(truth.feature_id)[j].astype(np.int64), kind=np.asarray(truth.feature_kind)[j].astype(np.int8),
        x=fx[k, j], y=np.asarray(truth.feature_y)[k, j], prev_x=fx[prev, j], prev_y=np.asarray(truth.feature_y)[prev, j],
    )


def load_results_index(path: Path) -> ResultsIndex:
    """Read a results file (``read_results``) and index it per frame for the viewer."""
    from skinstretch.experiments.analysis.plan import plan_rows  # noqa: PLC0415 - the analysis' modules, when read

    r = read_results(path)
    n = int(r.n_frames)
    feats = r.features
    by_frame = feature_track = None
    tx = ty = tpresent = tlinked = None
    if feats is not None:
        by_frame = _PerFrame.build(feats["frame"], n)
    if r.trajectories is not None:
        tr = r.trajectories.dense()
        tx, ty = np.asarray(tr.x, np.float64), np.asarray(tr.y, np.float64)
        tpresent, tlinked = np.asarray(tr.present, bool), np.asarray(tr.linked, bool)
        if feats is not None:
            fi = np.asarray(tr.feature_index, np.int64)
            feature_track = np.full(feats.shape[0], -1, np.int64)
            where = fi >= 0
            feature_track[fi[where]] = np.nonzero(where)[1]
    triangles, tri_by_pair, pair_frames, scale = {}, {}, {}, {}
    edges, edges_by_pair, map_scales = {}, {}, {}
    tables = dict(sorted(r.strain.items()))
    cumulative = r.cumulative
    if cumulative is not None and cumulative.reference_frame >= 0:
        tables[CUMULATIVE] = cumulative
    for span, s in tables.items():
        triangles[span] = s.triangles
        tri_by_pair[span] = _PerFrame.build(s.triangles["pair"], s.pairs.size)
        edges[span] = s.edges
        edges_by_pair[span] = _PerFrame.build(s.edges["pair"], s.pairs.size)
        pair_frames[span] = (np.asarray(s.pairs["frame_a"], np.int64), np.asarray(s.pairs["frame_b"], np.int64))
        ok = ~np.asarray(s.triangles["flipped"], bool)
        scale[span] = nice_scale(np.asarray(s.triangles["change"])[ok])
        map_scales[span] = _map_scales(s.triangles[ok], s.edges["change"])
    tactile = None
    tactile = None
    if r.tactile_positions_um is not None:
        tactile = (np.asarray(r.tactile_positions_um, np.float64), np.asarray(r.tactile_reset, bool),
                   np.asarray(r.tactile_clipped, bool))
    return ResultsIndex(
        path=Path(path), method=r.method, n_frames=n, coordinates=r.coordinates, spans=sorted(r.strain),
        strain_scale=scale, map_scales=map_scales, motion_axis=r.profile_axis_index, has_tactile=tactile is not None,
        window=dict(r.window),
        notes=[str(n) for n in (r.summary.get("notes") or [])],
        warnings=[str(w) for w in (r.summary.get("warnings") or [])],
        _features=feats, _features_by_frame=by_frame, _feature_track=feature_track, _track_x=tx, _track_y=ty,
        _track_present=tpresent, _track_linked=tlinked, _motion=r.motion,
        _motion_by_pair=_PerFrame.build(r.motion["pair"], max(n - 1, 0)), _triangles=triangles,
        _triangles_by_pair=tri_by_pair, _pair_frames=pair_frames, _window_centers=r.visibility_window.centers if r.visibility_window else None, _tactile=tactile,
        reference_frame=cumulative.reference_frame if cumulative is not None else -1, _edges=edges,
        _edges_by_pair=edges_by_pair, _cumulative_motion=cumulative.motion if cumulative is not None else None,
        _cumulative_motion_by_pair=_PerFrame.build(cumulative.motion["pair"], cumulative.pairs.size)
        if cumulative is not None else None, _results=r, plan=plan_rows(r.summary.get("plan") or {}),
    )


def _map_scales(triangles: np.ndarray, edge_change: np.ndarray) -> dict[str, float]:
    """Each map quantity's colour-scale limit over the whole session (one scale for every frame)."""
    out = {"area": nice_scale(triangles["change"]), "edge": nice_scale(edge_change)}
    ok = triangles["tensor_status"] == 0 if "tensor_status" in triangles.dtype.names else slice(None)
    for name in triangles.dtype.names:
        if name not in _NOT_MAPPED and triangles.dtype[name].kind == "f":
            out[name] = nice_scale(triangles[name][ok])
    return out


# ------------------------------------------------------------------------------------------ what to show


@dataclass(frozen=True)
class ViewTarget:
    """What ``skinstretch view`` was pointed at: one session (with its results if any), or a data directory whose
    newest trial is followed (live view while recording)."""

    session: Path | None
    results: Path | None
    directory: Path | None  # set when following the newest trial of a data directory

    @property
    def follows_directory(self) -> bool:
        return self.directory is not None


def _h5_format(path: Path) -> str:
    with open_hdf5_for_reading(path) as f:  # refused in one line, as analyze refuses it
        fmt = f.attrs.get("format", "")
    return fmt.decode() if isinstance(fmt, bytes) else str(fmt)


def _results_beside(session: Path) -> Path | None:
    cand = session.parent / ANALYSIS_DIR / RESULTS_FILE
    return cand if cand.exists() else None


def _session_of_results(results: Path) -> Path:
    with open_hdf5_for_reading(results) as f:
        raw = f.attrs.get("session_path", "")
    sp = Path(raw.decode() if isinstance(raw, bytes) else str(raw))
    if not sp.exists():
        # Moved together: the runner layout keeps the session one level up from analysis/.
        alt = results.parent.parent / SESSION_FILE
        if alt.exists():
            return alt
        raise SessionFileError(f"{results}: its session {sp} is not there (moved or deleted)")
    return sp


def find_view_target(path: str | Path) -> ViewTarget:
    """Resolve what the user pointed ``view`` at: a session file, a results file, an analysis output directory,
    a trial directory (session.h5 [+ analysis/]) or a data directory to follow; SessionFileError otherwise."""
    p = Path(path)
    if not p.exists():
        raise SessionFileError(f"{p}: no such file or directory")
    if p.is_file():
        fmt = _h5_format(p)
        if fmt == "skinstretch-results":
            return ViewTarget(_session_of_results(p), p, None)
        if fmt == "skinstretch-session":
            return ViewTarget(p, _results_beside(p), None)
        raise SessionFileError(f"{p}: neither a skinstretch session nor a results file (format {fmt!r})")
    if (p / RESULTS_FILE).exists():
        res = p / RESULTS_FILE
        return ViewTarget(_session_of_results(res), res, None)
    if (p / SESSION_FILE).exists():
        return ViewTarget(p / SESSION_FILE, _results_beside(p / SESSION_FILE), None)
    return ViewTarget(None, None, p)


def newest_trial_session(directory: Path) -> Path | None:
    """The session file of the trial most recently started under ``directory`` (recursively), or None."""
    found = [q for q in directory.rglob(SESSION_FILE) if q.is_file()]
    if not found:
        return None
    return max(found, key=lambda q: (q.stat().st_mtime_ns, str(q)))


def trial_sessions(directory: Path) -> dict[str, Path]:
    """Trial name (path relative to ``directory`` of its folder) -> session file, for every trial under it."""
    out = {}
    for q in sorted(directory.rglob(SESSION_FILE)):
        if q.is_file():
            out[str(q.parent.relative_to(directory))] = q
    return out
