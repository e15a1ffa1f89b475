"""The trajectories of a session of any length, built with bounded memory (seed 5.1.2).

:meth:`FeatureTracker.finish <skinstretch.processing.tracking.FeatureTracker.finish>` builds the trajectory table
from every frame's records at once, which a long session cannot hold (a feature may stay in view for the whole
session, so no track ends early enough to be finished on the way). :class:`TrajectoryStore` builds the same table
in two passes, holding only a few numbers per track and per linked run:

1. as the tracker hands out its frames (:meth:`~skinstretch.processing.tracking.FeatureTracker.take_frames`), each
   row's position relative to the start of its linked run (the running sum of its measured displacements) is
   computed and the row written to a scratch file; each run keeps the sum of its rows' offsets from their extracted
   positions (rows bridged by registration, without one, do not count), each track its length;
2. if asked (:meth:`TrajectoryStore.anchor`), the kept runs' positions at every key frame are read back and their
   chained drift measured against a direct registration
   (:class:`~skinstretch.processing.trajectory_anchoring.KeyframeAnchoring`);
3. at the end, the scratch rows are read back a block of frames at a time: tracks shorter than the minimum length
   dropped, the kept ones numbered in order, each run anchored to the mean of its extracted positions (its drift
   corrected first, when measured) and, if asked, smoothed
   (:func:`~skinstretch.processing.trajectory_smoothing.smooth_positions` over the block and its margins).

Without key frames the numbers are those of ``finish`` to the bit: the same operations in the same order on each
track (the tests check it). Hand-written: no library chains per-track running sums out of core.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.tracking import DEFAULT_MIN_LENGTH_FRAMES, TRAJECTORY_DTYPE, TrackedFrame, TrackingParams
from skinstretch.processing.trajectory_anchoring import KeyframeAnchoring, KeyframeCorrections
from skinstretch.processing.trajectory_smoothing import smooth_positions

__all__ = ["TrajectoryStore", "TrajectoryBlock", "BLOCK_FRAMES"]

#: Frames of final rows built at a time in the second pass.
BLOCK_FRAMES = 256

#: A row as the first pass leaves it: ``lx, ly`` its position relative to its run's start, ``group`` its run's
#: number in the store (runs of every track, in the order they start).
_SCRATCH_DTYPE = np.dtype(
    [("frame", np.int32), ("track", np.int64), ("lx", np.float64), ("ly", np.float64), ("raw_x", np.float64),
     ("raw_y", np.float64), ("feature_index", np.int64), ("linked", np.bool_), ("refined", np.bool_),
     ("run", np.int32), ("group", np.int64)]
)


class _Columns:
    """Arrays of one length that grow by doubling (per-track and per-run state)."""

    def __init__(self, **dtypes: np.dtype) -> None:
        self.size = 0
        self._arrays = {name: np.zeros(64, dtype) for name, dtype in dtypes.items()}

    def __getattr__(self, name: str) -> np.ndarray:
        try:
            return self.__dict__["_arrays"][name]
        except KeyError:
            raise AttributeError(name) from None

    def grow(self, n: int) -> None:
        """Make room for ``n`` more entries (zeros) and count them."""
        need = self.size + int(n)
        cap = next(iter(self._arrays.values())).shape[0]
        if need > cap:
            cap = max(need, 2 * cap)
            for name, a in self._arrays.items():
                b = np.zeros(cap, a.dtype)
                b[: self.size] = a[: self.size]
                self._arrays[name] = b
        self.size = need


@dataclass(frozen=True)
class TrajectoryBlock:
    """Final rows (TRAJECTORY_DTYPE, as :class:`~skinstretch.processing.tracking.Trajectories` holds them) of frames
    ``first`` to ``stop - 1``, sorted by frame then track."""

    first: int
    stop: int
    rows: np.ndarray


class TrajectoryStore:
    """Trajectories built from the frames a tracker hands out (module docstring), with bounded memory.

    ``params`` are the tracker's (its minimum length and smoothing); ``scratch_dir`` where the first pass writes
    (an unnamed temporary file, gone when the store is closed or the process ends; None: the system's).
    """

    def __init__(self, *, n_frames: int, params: TrackingParams, scratch_dir: str | os.PathLike | None = None) -> None:
        self.n_frames = int(n_frames)
        min_length = params.min_length_frames
        self.min_length = DEFAULT_MIN_LENGTH_FRAMES if min_length is None else int(min_length)
        self.smoothing_radius = int(params.smoothing_radius_frames)
        self.smoothing_sigma = float(params.smoothing_sigma_frames)
        self._file = tempfile.TemporaryFile(dir=None if scratch_dir is None else Path(scratch_dir),
                                            prefix="skinstretch-trajectories-")
        self._frame_rows = np.zeros(self.n_frames + 1, np.int64)  # rows of frame k: [k] .. [k + 1] (cumulated)
        self._next_frame = 0
        # per track: kind, length, first/last frame, running sums (cx, cy) and their value at the current run's
        # start (sx, sy), runs so far, current run's group
        self._tracks = _Columns(kind=np.int8, length=np.int32, first=np.int32, last=np.int32, cx=np.float64,
                                cy=np.float64, sx=np.float64, sy=np.float64, runs=np.int32, group=np.int64)
        # per run: sums of (extracted - relative) positions, rows
        self._groups = _Columns(sum_x=np.float64, sum_y=np.float64, rows=np.int64)
        self._corrections: KeyframeCorrections | None = None  # key-frame drift corrections, when measured
        self._recentre = np.zeros((0, 2))  # per run: mean correction over its extracted rows

    # -- first pass
    def add(self, frames: Sequence[TrackedFrame]) -> None:
        """Store the frames handed out by the tracker (in frame order, each once)."""
        parts = [self._chain(fr) for fr in frames]
        if parts:
            self._file.write(np.concatenate(parts).tobytes())

    def _chain(self, fr: TrackedFrame) -> np.ndarray:
        """One frame's rows, relative to their runs' starts; the tracks' and runs' sums updated (the operations of
        ``FeatureTracker.finish``'s chaining, a frame at a time: a track has at most one row per frame)."""
        k = int(fr.frame)
        if k != self._next_frame:
            raise InvalidInputError(f"frames must be stored in order: got frame {k}, expected {self._next_frame}")
        tr, gr = self._tracks, self._groups
        t = fr.track
        first_new = tr.size
        tr.grow(fr.new_track_kinds.size)
        tr.kind[first_new : tr.size], tr.first[first_new : tr.size] = fr.new_track_kinds, k
        if t.size and int(t.max()) >= tr.size:
            raise InvalidInputError(f"frame {k} holds track {int(t.max())}, started in no frame stored")
        lk = fr.linked
        tl, ts = t[lk], t[~lk]
        tr.cx[tl] += fr.displacement[lk, 0]
        tr.cy[tl] += fr.displacement[lk, 1]
        g0 = gr.size
        gr.grow(ts.size)
        tr.runs[ts] += 1
        tr.group[ts] = np.arange(g0, gr.size)
        tr.sx[ts], tr.sy[ts] = tr.cx[ts], tr.cy[ts]
        lx, ly = tr.cx[t] - tr.sx[t], tr.cy[t] - tr.sy[t]
        g = tr.group[t]
        seen = np.isfinite(fr.xy[:, 0])  # a point bridged by registration (no extracted position) does not anchor
        np.add.at(gr.sum_x, g[seen], fr.xy[seen, 0] - lx[seen])
        np.add.at(gr.sum_y, g[seen], fr.xy[seen, 1] - ly[seen])
        np.add.at(gr.rows, g[seen], 1)
        tr.length[t] += 1
        tr.last[t] = k
        rows = np.empty(t.size, _SCRATCH_DTYPE)
        rows["frame"], rows["track"], rows["lx"], rows["ly"] = k, t, lx, ly
        rows["raw_x"], rows["raw_y"], rows["feature_index"] = fr.xy[:, 0], fr.xy[:, 1], fr.feature_index
        rows["linked"], rows["refined"], rows["run"], rows["group"] = lk, fr.refined, tr.runs[t], g
        self._frame_rows[k + 1] = self._frame_rows[k] + t.size
        self._next_frame = k + 1
        return rows

    # -- second pass
    @property
    def kept(self) -> np.ndarray:
        """(tracks,) bool: the tracks long enough to keep."""
        return self._tracks.length[: self._tracks.size] >= self.min_length

    @property
    def kinds(self) -> np.ndarray:
        """Feature kind of each kept track, in the kept tracks' numbering."""
        return self._tracks.kind[: self._tracks.size][self.kept]

    def track_table(self) -> dict[str, np.ndarray]:
        """Kind, length, first and last frame of each kept track (the results' ``tracks`` table columns)."""
        keep, tr = self.kept, self._tracks
        n = tr.size
        return {"kind": tr.kind[:n][keep], "n_frames": tr.length[:n][keep], "first_frame": tr.first[:n][keep],
                "last_frame": tr.last[:n][keep]}

    def _offsets(self) -> tuple[np.ndarray, np.ndarray]:
        """Per run: the mean of its extracted positions less its chained ones (its anchor), x and y."""
        gr = self._groups
        return gr.sum_x[: gr.size] / gr.rows[: gr.size], gr.sum_y[: gr.size] / gr.rows[: gr.size]

    def anchor(self, anchoring: KeyframeAnchoring) -> None:
        """Measure the kept runs' drift at every key frame (``anchoring.interval``, and the last frame) and correct
        it in :meth:`blocks`: each run's positions gain the interpolated correction and lose its mean over the run's
        extracted rows, so the run stays anchored to its extracted positions."""
        n = self.n_frames
        if self._next_frame != n:
            raise InsufficientDataError(f"{self._next_frame} of {n} frames were stored: the trajectories are not done")
        self._file.flush()
        keep = self.kept
        off_x, off_y = self._offsets()
        keys = list(range(0, n, anchoring.interval))
        for k in keys + ([n - 1] if n > 1 and keys[-1] != n - 1 else []):
            s = self._read(k, k + 1)
            s = s[keep[s["track"]]]
            anchoring.add(k, s["group"], np.column_stack([s["lx"] + off_x[s["group"]], s["ly"] + off_y[s["group"]]]),
                          final=k == n - 1)
        corrections = anchoring.corrections()
        gr = self._groups
        total = np.zeros((gr.size, 2))
        for b0 in range(0, n, BLOCK_FRAMES):
            s = self._read(b0, min(n, b0 + BLOCK_FRAMES))
            s = s[keep[s["track"]] & np.isfinite(s["raw_x"])]
            c = corrections.at(s["group"], s["frame"])
            np.add.at(total, s["group"], c)
        self._corrections = corrections
        self._recentre = total / np.maximum(gr.rows[: gr.size], 1)[:, None]

    def blocks(self, block_frames: int | None = None) -> Iterator[TrajectoryBlock]:
        """The final trajectory rows, ``block_frames`` frames at a time (None: :data:`BLOCK_FRAMES`), in frame order
        (every frame stored first)."""
        block_frames = BLOCK_FRAMES if block_frames is None else int(block_frames)
        n = self.n_frames
        if self._next_frame != n:
            raise InsufficientDataError(f"{self._next_frame} of {n} frames were stored: the trajectories are not done")
        self._file.flush()
        keep = self.kept
        new_id = np.cumsum(keep) - 1
        off_x, off_y = self._offsets()
        if self._corrections is not None:
            off_x, off_y = off_x - self._recentre[:, 0], off_y - self._recentre[:, 1]
        radius = self.smoothing_radius if n >= 2 else 0
        for b0 in range(0, n, block_frames):
            b1 = min(n, b0 + block_frames)
            lo, hi = max(0, b0 - radius), min(n, b1 + radius)
            s = self._read(lo, hi)
            s = s[keep[s["track"]]]
            x, y = s["lx"] + off_x[s["group"]], s["ly"] + off_y[s["group"]]
            anchor_var = np.zeros(s.size)
            if self._corrections is not None:
                c = self._corrections.at(s["group"], s["frame"])
                x, y = x + c[:, 0], y + c[:, 1]
                anchor_var = self._corrections.variance_at(s["group"], s["frame"])
            if radius > 0:
                x, y = self._smooth(s, x, y, lo, hi)
            inner = (s["frame"] >= b0) & (s["frame"] < b1)
            s, x, y, anchor_var = s[inner], x[inner], y[inner], anchor_var[inner]
            rows = np.zeros(s.size, TRAJECTORY_DTYPE)
            rows["frame"], rows["track"], rows["x"], rows["y"] = s["frame"], new_id[s["track"]], x, y
            rows["anchor_sigma"] = np.sqrt(anchor_var)
            for name in ("raw_x", "raw_y", "feature_index", "linked", "refined", "run"):
                rows[name] = s[name]
            yield TrajectoryBlock(b0, b1, rows)

    def _read(self, lo: int, hi: int) -> np.ndarray:
        start, stop = self._frame_rows[lo], self._frame_rows[hi]
        self._file.seek(int(start) * _SCRATCH_DTYPE.itemsize)
        return np.fromfile(self._file, dtype=_SCRATCH_DTYPE, count=int(stop - start))

    def _smooth(self, s: np.ndarray, x: np.ndarray, y: np.ndarray, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 5.2-5.3 within each linked run, over frames lo..hi - 1 as (frames, tracks) arrays."""
        tracks, col = np.unique(s["track"], return_inverse=True)
        f = s["frame"] - lo
        shape = (hi - lo, tracks.size)
        pos = np.zeros((*shape, 2))
        present = np.zeros(shape, bool)
        linked = np.zeros(shape, bool)
        pos[f, col, 0], pos[f, col, 1] = x, y
        present[f, col], linked[f, col] = True, s["linked"]
        out = smooth_positions(pos, present, linked, radius_frames=self.smoothing_radius,
                               sigma_frames=self.smoothing_sigma)
        return out[f, col, 0], out[f, col, 1]

    # -- life
    def close(self) -> None:
        """Drop the scratch file."""
        self._file.close()

    def __enter__(self) -> "TrajectoryStore":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
