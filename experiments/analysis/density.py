"""How dense the measured motion is, for the summary of an analysis: features per frame, trajectories kept, the
fraction of the features that stay in view kept as trajectories, and the size of the strain mesh.

Fraction kept (one definition, :func:`fraction_kept`, for the analysis' report and for ``skinstretch evaluate`` /
the accuracy bench): of the features found in a frame whose skin point stays in view for the window (at least the
minimum trajectory length, in consecutive frames around that frame), the fraction that belongs to a kept
trajectory. A feature whose skin point leaves the view before the window is full does not count; one that stays
and is not kept (a short track, a second detection of one skin point) counts against. Where the skin point goes:

* the analysis (:func:`mesh_density`, no truth) follows it through the motion it measured (the median displacement
  of the nearest measured points, pair after pair) and calls it in view inside the Delaunay triangulation of what
  it measured in the frame, its features and the motion table's points (edges longer than the strain's
  ``max_edge_mm`` left out): features alone leave the region empty in a frame where extraction found few or none,
  and would count every feature not kept as leaving the view. Kept features are followed the same way (at most
  :data:`_KEPT_FOLLOWED` of them, evenly sampled): taken as in view unfollowed, they overstated the fraction;
* ``skinstretch evaluate`` (:func:`skinstretch.experiments.evaluation.trajectories.evaluate_trajectories`) follows
  it through the simulator's exact field, in view where feature recall is scored.

A mesh too sparse to map strain is said, in the summary (``too_sparse`` and ``warning``) and in the log: fewer
than half of the consecutive pairs give a strain triangulation, fewer than :data:`MIN_POINTS_PER_PAIR` points in a
typical pair, or a mean edge longer than :data:`MAX_MEAN_EDGE_MM` (the STReSS display's contactors are 1 mm
apart). A fraction kept under :data:`MIN_FRACTION_KEPT` is warned about too. All is read from the results file.

Hand-written: following points through a measured motion and testing them against a triangulated region is
specific to this analysis' tables (scipy's k-d tree and the strain mesh's own Delaunay do the geometry).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import cv2
import h5py
import numpy as np
from scipy.spatial import cKDTree

from skinstretch.experiments.results_file import MeshDensity, PairStatus, pair_index, pair_row_offsets
from skinstretch.processing.delaunay import triangulate_points
from skinstretch.processing.global_motion import local_predictions

__all__ = ["MeshDensity", "FractionKept", "SkinPointMotion", "mesh_density", "fraction_kept", "MeasuredMotion",
           "MIN_POINTS_PER_PAIR", "MAX_MEAN_EDGE_MM", "MIN_OK_PAIR_FRACTION", "MIN_FRACTION_KEPT"]

log = logging.getLogger(__name__)

#: Fewer measured points than this in the median consecutive pair: too sparse to map strain.
MIN_POINTS_PER_PAIR = 10
#: A mean strain-mesh edge longer than this (mm): too coarse to map strain under a 1 mm display.
MAX_MEAN_EDGE_MM = 1.5
#: Fewer consecutive pairs with a strain triangulation than this fraction: too sparse.
MIN_OK_PAIR_FRACTION = 0.5
#: A fraction kept below this is warned about (issue 16: at least 80 % of the features that stay in view).
MIN_FRACTION_KEPT = 0.8

_BLOCK = 1 << 20  # rows read at a time
_REACH_MM = 1.0  # a point further than this from every measured point of a pair is not followed through it
_KEPT_FOLLOWED = 4000  # kept features followed at most (the rest sampled): their fraction in view to +/-0.01


@dataclass(frozen=True)
class FractionKept:
    """What :func:`fraction_kept` found.

    Attributes
    ----------
    window_frames : int
        The window: a feature counts when its skin point stays in view this many consecutive frames around its
        frame (the minimum trajectory length).
    n_features : int
        Features found (every frame).
    n_in_view : int
        Of those, the ones whose skin point stays in view for the window.
    n_kept : int
        Of those, the ones in a kept trajectory.
    fraction : float or None
        ``n_kept / n_in_view`` (None when no feature stays in view).
    """

    window_frames: int
    n_features: int
    n_in_view: int
    n_kept: int
    fraction: float | None


class SkinPointMotion(Protocol):
    """Where skin points go (:func:`fraction_kept`): the measured motion or the simulator's truth."""

    def move(self, points: np.ndarray, frame_from: int, frame_to: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions in ``frame_to`` (a neighbouring frame) of the skin points at ``points`` in ``frame_from``, and
        whether each could be followed."""

    def in_view(self, points: np.ndarray, frame: int) -> np.ndarray:
        """Whether each of ``points`` (positions in ``frame``) is in view there."""


def fraction_kept(n_frames: int, window: int, features_of: Callable[[int], tuple[np.ndarray, np.ndarray]],
                  motion: SkinPointMotion) -> FractionKept:
    """The fraction kept (module doc) of a sequence of ``n_frames``.

    ``features_of(k)`` gives frame k's features: positions (n, 2) and whether each belongs to a kept trajectory.
    Each feature's skin point is followed forward and backward through ``motion`` until it leaves the view or the
    window is reached (points of all frames at once, one step at a time).
    """
    window = max(int(window), 1)
    counts = [0, 0, 0]  # features, in view, kept
    need = window - 1
    # Per frame: rows followed, and frames in view after (forward) and before (backward) the feature's own frame.
    followed: dict[int, np.ndarray] = {}
    ahead: dict[int, np.ndarray] = {}
    behind: dict[int, np.ndarray] = {}
    own_view: dict[int, np.ndarray] = {}
    kept_of: dict[int, np.ndarray] = {}
    for direction, out in ((1, ahead), (-1, behind)):
        frames = range(n_frames) if direction > 0 else range(n_frames - 1, -1, -1)
        live_xy = np.zeros((0, 2))
        live_frame = np.zeros(0, np.int64)
        live_row = np.zeros(0, np.int64)
        live_age = np.zeros(0, np.int64)
        for k in frames:
            if live_xy.shape[0]:
                xy, ok = motion.move(live_xy, k - direction, k)
                ok &= motion.in_view(np.where(ok[:, None], xy, 0.0), k)
                live_age = live_age + ok
                done = ~ok | (live_age >= need)
                for f in np.unique(live_frame[done]):
                    sel = done & (live_frame == f)
                    out[int(f)][live_row[sel]] = live_age[sel]
                keep = ~done
                live_xy, live_frame, live_row, live_age = xy[keep], live_frame[keep], live_row[keep], live_age[keep]
            if direction > 0:
                xy, kept = features_of(k)
                xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
                kept = np.asarray(kept, dtype=bool).reshape(-1)
                rows = np.arange(kept.size)
                counts[0] += kept.size
                kept_of[k] = kept
                followed[k] = rows
                own_view[k] = motion.in_view(xy[rows], k) if rows.size else np.zeros(0, bool)
                rows_xy = xy[rows]
            else:
                rows = followed[k]
                xy, _ = features_of(k)
                rows_xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)[rows]
            out[k] = np.zeros(kept_of[k].size, np.int64)
            start = own_view[k] if need > 0 else np.zeros(rows.size, bool)
            live_xy = np.concatenate([live_xy, rows_xy[start]])
            live_frame = np.concatenate([live_frame, np.full(int(start.sum()), k, np.int64)])
            live_row = np.concatenate([live_row, rows[start]])
            live_age = np.concatenate([live_age, np.zeros(int(start.sum()), np.int64)])
        for f in np.unique(live_frame):
            sel = live_frame == f
            out[int(f)][live_row[sel]] = live_age[sel]
    for k in range(n_frames):
        kept, rows = kept_of[k], followed[k]
        stays = np.zeros(kept.size, bool)
        run = ahead[k][rows] + behind[k][rows] + 1
        stays[rows] = own_view[k] & (run >= window)
        counts[1] += int(stays.sum())
        counts[2] += int((stays & kept).sum())
    n_features, n_in_view, n_kept = counts
    return FractionKept(window, n_features, n_in_view, n_kept, n_kept / n_in_view if n_in_view else None)


class _FrameRows:
    """Rows of a table grouped by frame (``offsets``: first row of each frame), read from the file a block of
    frames at a time and kept until another block is asked for (the passes go through the frames in order)."""

    def __init__(self, dataset: h5py.Dataset, offsets: np.ndarray, *, block_frames: int = 64) -> None:
        self._d, self._off, self._n = dataset, offsets, int(block_frames)
        self._block = (-1, None)

    def __call__(self, k: int) -> np.ndarray:
        b = int(k) // self._n
        if self._block[0] != b:
            lo = b * self._n
            hi = min(lo + self._n, self._off.size - 1)
            self._block = (b, self._d[self._off[lo] : self._off[hi]])
        base = self._off[b * self._n]
        return self._block[1][self._off[k] - base : self._off[k + 1] - base]


class MeasuredMotion:
    """The analysis' own :class:`SkinPointMotion`, from a results file being written: a skin point moves by the
    median displacement of the 6 nearest points measured between the two frames (none within 1 mm: it is not
    followed), and is in view inside the Delaunay triangulation of the frame's measured points (:meth:`measured_points`;
    triangles with an edge longer than ``max_edge_px`` left out)."""

    def __init__(self, f: h5py.File, *, feature_offsets: np.ndarray, px_per_mm: float, max_edge_px: float) -> None:
        self._features = _FrameRows(f["features"], feature_offsets) if "features" in f else None
        pairs = pair_index(f["motion_pairs"]) if "motion_pairs" in f else None
        self._pairs = pair_row_offsets(pairs["n_points"] if pairs is not None else np.zeros(0, np.int64))
        self._motion = _FrameRows(f["motion"], self._pairs) if "motion" in f else None
        self._pair_of = {int(a): i for i, a in enumerate(pairs["frame_a"])} if pairs is not None else {}
        self._reach = _REACH_MM * float(px_per_mm)
        self._max_edge = float(max_edge_px)
        # Each frame's region as bits: fraction_kept's forward and backward passes both ask for every frame's.
        self._regions: dict[int, Any] = {}
        self._region_bytes = 0

    def move(self, points, frame_from, frame_to):
        first = min(frame_from, frame_to)
        i = self._pair_of.get(int(first))
        ok = np.zeros(points.shape[0], bool)
        if i is None or self._pairs[i + 1] - self._pairs[i] < 3:
            return points, ok
        rows = self._motion(i)
        src = np.column_stack([rows["x"], rows["y"]])
        d = np.column_stack([rows["dx"], rows["dy"]])
        if frame_to < frame_from:
            src, d = src + d, -d
        ok = cKDTree(src).query(points, distance_upper_bound=self._reach)[0] <= self._reach
        return points + local_predictions(points, src, d), ok

    def measured_points(self, frame: int) -> np.ndarray:
        """(n, 2) where the analysis measured something in ``frame``: its features and the points of the motion
        table there (a pair's points in its first frame, moved into its second)."""
        parts = []
        if self._features is not None:
            rows = self._features(frame)
            parts.append(np.column_stack([rows["x"], rows["y"]]))
        for i, moved in ((self._pair_of.get(int(frame)), False), (self._pair_of.get(int(frame) - 1), True)):
            if i is not None and self._motion is not None and self._pairs[i + 1] > self._pairs[i]:
                rows = self._motion(i)
                xy = np.column_stack([rows["x"], rows["y"]])
                parts.append(xy + np.column_stack([rows["dx"], rows["dy"]]) if moved else xy)
        return np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 2))

    def in_view(self, points, frame):
        region = self._regions.get(frame, False)
        if region is False:
            region = _region(self.measured_points(frame), self._max_edge)
            if region is not None:
                region = (np.packbits(region[0], axis=1), region[0].shape, region[1])
            if self._region_bytes < _REGION_CACHE_BYTES:  # beyond it (long sessions) drawn again when asked for
                self._regions[frame] = region
                self._region_bytes += region[0].nbytes if region is not None else 0
        return _in_region(region, points)


_REGION_PX = 2.0  # the in-view region is drawn at this resolution
_REGION_CACHE_BYTES = 32 << 20  # regions kept for fraction_kept's second pass (about 10 kB a 640x484 frame)


def _region(xy: np.ndarray, max_edge: float):
    """The triangles of the Delaunay triangulation of ``xy`` without an edge longer than ``max_edge``, drawn as a
    mask (one cell every :data:`_REGION_PX` pixels) and the mask's origin; None without a triangle."""
    xy = np.ascontiguousarray(xy[np.all(np.isfinite(xy), axis=1)], dtype=np.float64)
    simplices = triangulate_points(xy)  # ours: ~10x quicker than Qhull on a frame's features; duplicates skipped
    if simplices.shape[0] == 0:  # fewer than 3 distinct points, or collinear
        return None
    p = xy[simplices]
    longest = np.max(np.hypot(*(p - np.roll(p, 1, axis=1)).transpose(2, 0, 1)), axis=1)
    p = p[longest <= max_edge]
    if p.shape[0] == 0:
        return None
    origin = xy.min(axis=0)
    size = np.ceil((xy.max(axis=0) - origin) / _REGION_PX).astype(int) + 2
    mask = np.zeros((size[1], size[0]), np.uint8)
    corners = np.round((p - origin) / _REGION_PX).astype(np.int32)
    cv2.fillPoly(mask, corners, 1)
    return mask, origin


def _in_region(region, points: np.ndarray) -> np.ndarray:
    """Whether each of ``points`` lies in ``region``: (mask's rows as np.packbits, mask's shape, origin) or None."""
    out = np.zeros(points.shape[0], bool)
    if region is None or points.shape[0] == 0:
        return out
    bits, shape, origin = region
    c = np.round((points[:, 0] - origin[0]) / _REGION_PX).astype(np.int64)
    r = np.round((points[:, 1] - origin[1]) / _REGION_PX).astype(np.int64)
    inside = (c >= 0) & (r >= 0) & (c < shape[1]) & (r < shape[0])
    ri, ci = r[inside], c[inside]
    out[inside] = (bits[ri, ci >> 3] >> (7 - (ci & 7))) & 1 > 0
    return out


def _frame_offsets(features: h5py.Dataset, n_frames: int) -> np.ndarray:
    """(n_frames + 1,) first row of each frame in a feature table written in frame order."""
    counts = np.zeros(n_frames, np.int64)
    for a in range(0, features.shape[0], _BLOCK):
        fr = np.asarray(features.fields("frame")[a : a + _BLOCK], dtype=np.int64)
        counts += np.bincount(fr[(fr >= 0) & (fr < n_frames)], minlength=n_frames)
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def kept_features(f: h5py.File, n_features: int) -> np.ndarray:
    """Whether each row of the results' feature table belongs to a kept trajectory."""
    kept = np.zeros(n_features, bool)
    if "trajectories" in f:
        t = f["trajectories"]
        for a in range(0, t.shape[0], _BLOCK):
            fi = np.asarray(t.fields("feature_index")[a : a + _BLOCK], dtype=np.int64)
            kept[fi[(fi >= 0) & (fi < n_features)]] = True
    return kept


def _mean_in_blocks(dset: h5py.Dataset, name: str) -> float | None:
    n = dset.shape[0]
    if n == 0:
        return None
    total = 0.0
    for a in range(0, n, _BLOCK):
        total += float(np.sum(np.asarray(dset.fields(name)[a : a + _BLOCK], dtype=np.float64)))
    return total / n


def mesh_density(f: h5py.File, *, method: str, n_frames: int, px_per_mm: float, spans, max_edge_px: float,
                 window: int | None) -> MeshDensity:
    """The :class:`MeshDensity` of the results file ``f`` (open, complete up to its derived parts); ``window`` is the
    minimum trajectory length of the features method. Logs the warning when there is one."""
    features_per_frame = trajectories_kept = fraction = in_view = None
    if method == "features" and "features" in f:
        n_features = int(f["features"].shape[0])
        features_per_frame = n_features / max(int(n_frames), 1)
        trajectories_kept = int(f["tracks"].shape[0]) if "tracks" in f else 0
        offsets = _frame_offsets(f["features"], n_frames)
        kept = kept_features(f, n_features)
        motion = MeasuredMotion(f, feature_offsets=offsets, px_per_mm=px_per_mm, max_edge_px=max_edge_px)
        rows_of = _FrameRows(f["features"], offsets)

        # Kept features are followed like the others (taking them as in view because they were measured overstates
        # the fraction wherever the view's edge is uncertain), every stride-th one of them, counted stride times.
        stride = max(1, -(-int(kept.sum()) // _KEPT_FOLLOWED))
        followed = ~kept | (np.cumsum(kept) % stride == 0)

        def features_of(k: int):
            rows, sel = rows_of(k), followed[offsets[k] : offsets[k + 1]]
            return np.column_stack([rows["x"], rows["y"]])[sel], kept[offsets[k] : offsets[k + 1]][sel]

        fk = fraction_kept(n_frames, int(window or 1), features_of, motion)
        n_kept = stride * fk.n_kept
        in_view = n_kept + fk.n_in_view - fk.n_kept
        fraction = n_kept / in_view if in_view else None
    points = np.asarray(f["motion_pairs"].fields("n_points")[()], dtype=np.float64) if "motion_pairs" in f else \
        np.zeros(0)
    points_per_pair = float(np.median(points)) if points.size else 0.0
    pairs, pairs_ok = {}, {}
    for span in spans:
        g = f"strain/span_{int(span)}/pairs"
        status = np.asarray(f[g].fields("status")[()]) if g in f else np.zeros(0, np.int8)
        pairs[int(span)] = int(status.size)
        pairs_ok[int(span)] = int(np.count_nonzero(status == PairStatus.OK))
    edge_px = _mean_in_blocks(f["strain/span_1/edges"], "length") if "strain/span_1/edges" in f else None
    edge_mm = edge_px / px_per_mm if edge_px is not None else None
    reasons = []
    n_pairs, n_ok = pairs.get(1, max(n_frames - 1, 0)), pairs_ok.get(1, 0)
    if n_pairs and n_ok < MIN_OK_PAIR_FRACTION * n_pairs:
        reasons.append(f"only {n_ok} of {n_pairs} consecutive frame pairs give a strain triangulation")
    if points_per_pair < MIN_POINTS_PER_PAIR:
        reasons.append(f"{points_per_pair:g} points measured per frame pair (median; at least {MIN_POINTS_PER_PAIR} "
                       "needed)")
    if edge_mm is not None and edge_mm > MAX_MEAN_EDGE_MM:
        reasons.append(f"mean mesh edge {edge_mm:.2f} mm (coarser than {MAX_MEAN_EDGE_MM} mm)")
    messages = []
    if reasons:
        messages.append("the strain mesh is too sparse to map strain: " + "; ".join(reasons))
    if fraction is not None and fraction < MIN_FRACTION_KEPT:
        messages.append(f"only {100 * fraction:.0f} % of the features that stay in view for {window} frames are kept "
                        f"as trajectories (at least {100 * MIN_FRACTION_KEPT:.0f} % expected)")
    density = MeshDensity(method, features_per_frame, trajectories_kept, fraction, in_view,
                          int(window) if method == "features" and window else None, points_per_pair, edge_mm, pairs,
                          pairs_ok, bool(reasons), None)
    if messages:
        density = MeshDensity(**{**asdict(density), "warning": "; ".join(messages) + f" ({density.describe()})"})
        log.warning("%s", density.warning)
    return density
