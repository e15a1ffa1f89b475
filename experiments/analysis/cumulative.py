"""Motion and strain of every frame relative to one reference frame (DIC's "reference image"), from what the
analysis stored: along the trajectories (features) or along skin points followed through the flow fields (flow).

The reference is the first frame with at least 3 measured points (normally frame 0). Features: the tracks present
in it, each followed for as long as it stays linked (one ``run``). Flow: every ``stride``-th valid node of its field,
each carried by the consecutive fields in turn (bilinear, as :func:`~.derive.chain_flows`), dropped once it reaches
an invalid node. Both read the results file being written one frame or field at a time, so memory holds one
frame's points, not the session's.
"""

from __future__ import annotations

from collections.abc import Iterator

import h5py
import numpy as np

from skinstretch.experiments.analysis.derive import rectified_sample
from skinstretch.experiments.results_file import pair_index, pair_row_offsets
from skinstretch.processing.flow import FlowField
from skinstretch.processing.tracking import MotionSample

__all__ = ["feature_cumulative_samples", "flow_cumulative_samples"]

_MIN_POINTS = 3


def _frame_offsets(frames: np.ndarray, n_frames: int) -> np.ndarray:
    return np.searchsorted(frames, np.arange(n_frames + 1))


def feature_cumulative_samples(f: h5py.File, *, n_frames: int, keyframe_interval: int | None = None
                               ) -> Iterator[MotionSample]:
    """(reference, k) for every frame k after the reference, from the stored ``trajectories`` (sorted by frame,
    positions already on the skin when the session has a mapping); nothing when no frame has 3 tracks.

    Each point's sigma: its trajectory's key-frame anchoring error (``anchor_sigma``, at k and at the reference)
    and, in quadrature, the chained steps' predicted errors (the ``motion`` table's consecutive sigmas) over the
    key-frame interval around k, whose chain the anchoring's line only approximates; without key frames
    (``keyframe_interval`` None: the trajectories are chained) every step since the reference."""
    if "trajectories" not in f:
        return
    ds = f["trajectories"]
    frames = ds.fields("frame")[()]
    if frames.size and np.any(np.diff(frames) < 0):  # pragma: no cover - the writer appends frames in order
        raise ValueError("trajectories are not sorted by frame")
    off = _frame_offsets(frames, n_frames)
    counts = np.diff(off)
    ref = int(np.argmax(counts >= _MIN_POINTS)) if np.any(counts >= _MIN_POINTS) else -1
    if ref < 0:
        return
    r0 = ds[int(off[ref]) : int(off[ref + 1])]
    p0 = np.column_stack([r0["x"], r0["y"]])
    anchor0 = _anchor_variance(r0)
    steps = _StepVariances(f, r0["track"], ref=ref, n_frames=n_frames, interval=keyframe_interval)
    for k in range(ref + 1, n_frames):
        rk = ds[int(off[k]) : int(off[k + 1])] if off[k + 1] > off[k] else r0[:0]
        _, ia, ib = np.intersect1d(r0["track"], rk["track"], assume_unique=True, return_indices=True)
        same = r0["run"][ia] == rk["run"][ib]
        ia, ib = ia[same], ib[same]
        pk = np.column_stack([rk["x"][ib], rk["y"][ib]])
        var = anchor0[ia] + _anchor_variance(rk)[ib] + steps.at(k)[ia]
        yield MotionSample(ref, k, p0[ia], pk - p0[ia], r0["track"][ia].astype(np.int64), np.sqrt(var))


def _anchor_variance(rows: np.ndarray) -> np.ndarray:
    if "anchor_sigma" not in (rows.dtype.names or ()):  # results written before the column: not estimated
        return np.full(rows.shape, np.inf)
    return rows["anchor_sigma"].astype(np.float64) ** 2


class _StepVariances:
    """For the reference frame's tracks: the summed predicted variance (px^2) of their consecutive steps over the
    key-frame interval holding frame k (from the reference where there are no key frames), read from the ``motion``
    table an interval at a time; inf where a step of the track was not measured."""

    def __init__(self, f: h5py.File, tracks: np.ndarray, *, ref: int, n_frames: int, interval: int | None) -> None:
        self._f, self._tracks, self._ref, self._n = f, np.asarray(tracks, np.int64), ref, n_frames
        self._interval = interval
        self._ok = "motion" in f and "motion_pairs" in f
        if self._ok:
            pairs = pair_index(f["motion_pairs"])
            self._pair_of = {int(a): i for i, (a, b) in enumerate(zip(pairs["frame_a"], pairs["frame_b"]))
                             if int(b) == int(a) + 1}
            self._rows = pair_row_offsets(pairs["n_points"])
        self._span = (-1, -1)
        self._sum = np.zeros(self._tracks.size)
        self._walk = np.zeros(self._tracks.size)  # without key frames: every step since the reference

    def at(self, k: int) -> np.ndarray:
        if not self._ok:
            return np.full(self._tracks.size, np.inf)
        if self._interval is None:
            self._walk = self._walk + self._steps(k - 1, k)
            return self._walk
        lo = max(self._ref, (k - 1) // self._interval * self._interval)  # the key frames on either side of k
        hi = min(self._n - 1, ((k - 1) // self._interval + 1) * self._interval)
        if (lo, hi) != self._span:
            self._span, self._sum = (lo, hi), self._steps(lo, hi)
        return self._sum

    def _steps(self, lo: int, hi: int) -> np.ndarray:
        """The summed variances of the steps lo -> lo + 1 ... hi - 1 -> hi of the reference's tracks."""
        pairs = [self._pair_of.get(a) for a in range(lo, hi)]
        if not pairs or None in pairs:
            return np.full(self._tracks.size, np.inf if pairs else 0.0)
        base = int(self._rows[min(pairs)])
        block = self._f["motion"][base : int(self._rows[max(pairs) + 1])]  # one read for the interval
        total = np.zeros(self._tracks.size)
        for p in pairs:
            rows = block[int(self._rows[p]) - base : int(self._rows[p + 1]) - base]
            sigma = np.full(self._tracks.size, np.inf)
            _, it, ir = np.intersect1d(self._tracks, rows["id"], assume_unique=True, return_indices=True)
            sigma[it] = rows["sigma"][ir]
            total += sigma ** 2
        return total


def flow_cumulative_samples(f: h5py.File, *, stride: int = 1, mapping=None, px_per_mm: float = 1.0
                            ) -> Iterator[MotionSample]:
    """(reference, k) for every frame k after the reference, following the skin points through the stored
    consecutive fields (``flow/displacement``, ``flow/valid``); rectified to the skin with ``mapping``."""
    if "flow" not in f:
        return
    g = f["flow"]
    gx, gy = g["grid_x"][()], g["grid_y"][()]
    disp, valid = g["displacement"], g["valid"]
    n_pairs = disp.shape[0]

    def field(k: int) -> FlowField:
        v = valid[k]
        d = np.where(v[..., None], disp[k].astype(np.float64), np.nan)
        return FlowField(k, k + 1, gx, gy, d, v, np.zeros(2), 0)

    ref = next((k for k in range(n_pairs) if int(valid[k][::stride, ::stride].sum()) >= _MIN_POINTS), -1)
    if ref < 0:
        return
    first = field(ref).motion(stride=stride)
    p0, ids = first.points, first.ids
    p = p0 + first.displacement
    yield rectified_sample(MotionSample(ref, ref + 1, p0, p - p0, ids), mapping, px_per_mm)
    for k in range(ref + 1, n_pairs):
        d, ok = field(k).sample(p)
        p = np.where(ok[:, None], p + np.nan_to_num(d), np.nan)
        keep = ok & np.all(np.isfinite(p), axis=1)
        p0, p, ids = p0[keep], p[keep], ids[keep]
        yield rectified_sample(MotionSample(ref, k + 1, p0, p - p0, ids), mapping, px_per_mm)
