"""Feature tracking over a sequence and feature trajectories (seed 5.1).

Matching (seed 5.1.1, :mod:`skinstretch.processing.feature_matching`): each feature of frame k-1 is looked for near
its expected position in frame k. The
expected displacement is the feature's previous displacement when it has one, otherwise the average of the
predictions (or, with a :class:`skinstretch.processing.global_motion.GlobalMotionEstimator`, the measured global motion).
Candidates are the features of the same kind inside a circular search window (0.3 mm); each candidate pair is
rated by eq. 5.1, ``C = (180 - theta) / 180 + (d_max - d) / d_max`` (the orientation term is zero for pores and
minutiae of unknown orientation), and pairs are finalised in decreasing confidence, each feature used once.

Trajectories (seed 5.1.2): matches are chained into trajectories; trajectories shorter than a minimum number of
frames (30) are rejected; positions are smoothed by a Gaussian kernel (eq. 5.2, 5.3). When a
:class:`skinstretch.processing.displacement_refinement.SubpixelRefiner` is given, each matched displacement is refined by local
image registration and a trajectory's positions are the running sum of its refined displacements, anchored to
the mean of its extracted positions: relative motion at a few hundredths of a pixel, absolute position to the
extraction's accuracy divided by the square root of the track length.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from pydantic import Field

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.feature_table import FEATURE_DTYPE, validate_features
from skinstretch.processing.parameters import parameters
from skinstretch.processing.feature_matching import (  # noqa: F401 - match_features: the public matching
    FeatureColumns, Matches, crowded_points, duplicate_starts, feature_columns, match_columns,
    match_features, merge_bridged,
)
from skinstretch.processing.global_motion import GlobalMotionEstimator, local_gradients, local_predictions
from skinstretch.processing.displacement_refinement import PreparedImage, SubpixelRefiner
from skinstretch.processing.neighbour_fusion import fuse_with_neighbours
from skinstretch.processing.measurement_uncertainty import MIN_MATCH
# smooth_positions stays importable from here, where it was defined before it moved
from skinstretch.processing.trajectory_smoothing import smooth_positions, smooth_track_rows  # noqa: F401
from skinstretch.processing.jit import njit


@parameters
class TrackingParams:
    """Options of feature matching and trajectory building (seed 5.1), in mm and frames (evidence: tuning log).

    Parameters
    ----------
    search_radius_mm, min_length_frames : float, int or None
        Radius of the circular search window (mm; seed 5.1.1: 0.3 mm); trajectories shorter than this are rejected
        (None: the seed's 30, half of a shorter clip in the analysis).
    smoothing_radius_frames, smoothing_sigma_frames : int, float
        Half-width R and sigma of eq. 5.3's Gaussian (seed Figure 53: R = 1, sigma 1); R = 0 (default): none.
    max_local_deviation_mm : float
        A refined displacement further than this (mm) from the median of its 7 nearest refined neighbours is rejected.
    max_bridge_deviation_spreads : float or None
        A bridged step further from its neighbours' than this many robust spreads ends the bridge (None: no bound).
    max_bridge_frames : int or None
        A point whose feature is lost is followed by registration alone for at most this many frames (None: while
        its registration holds; 0: no bridging).
    merge_radius_mm : float
        A feature this close (mm) to where registration put a tracked point is that point's landmark.
    fusion_radius_mm, fusion_model_sigma_mm : float or None, float
        Neighbours (mm) whose affine prediction is fused with a refined displacement (None: no fusion), and how far
        (mm a frame) a point's motion may depart from it.
    keyframe_interval_frames, keyframe_reference_frames : int or None, int
        Key-frame anchoring's interval (None: chained positions only) and how many frames a reference key frame serves.
    """

    search_radius_mm: float = Field(0.3, gt=0)
    min_length_frames: int | None = Field(None, ge=1)
    smoothing_radius_frames: int = Field(0, ge=0)
    smoothing_sigma_frames: float = Field(1.0, gt=0)
    max_local_deviation_mm: float = Field(0.008, gt=0)
    max_bridge_deviation_spreads: float | None = Field(10.0, gt=0)
    max_bridge_frames: int | None = Field(None, ge=0)
    merge_radius_mm: float = Field(0.1, gt=0)
    fusion_radius_mm: float | None = Field(1.5, gt=0)
    fusion_model_sigma_mm: float = Field(0.0002, gt=0)
    keyframe_interval_frames: int | None = Field(5, ge=2)
    keyframe_reference_frames: int = Field(40, ge=2)


def join_overlap_frames(params: TrackingParams) -> int:
    """Frames two trackers of one sequence must share for :meth:`FeatureTracker.continue_with` to join them: past
    them a tracker remembers nothing the other did not see (a point followed by registration alone is let go after
    a finite ``max_bridge_frames``). A point followed
    for as long as its registration holds may outlive any overlap: a join whose frames disagree is then refused and
    the caller tracks those frames itself."""
    bridge = params.max_bridge_frames
    return int(bridge or 0) + 2


#: Seed 5.1.2: trajectories shorter than 30 frames are rejected.
DEFAULT_MIN_LENGTH_FRAMES = 30


def min_length_for_clip(n_frames: int) -> int:
    """The minimum trajectory length when none is given: the seed's 30 frames, or half of a clip shorter than that
    (at least 2), which would otherwise keep no trajectory at all."""
    n = int(n_frames)
    return DEFAULT_MIN_LENGTH_FRAMES if n >= DEFAULT_MIN_LENGTH_FRAMES else max(2, n // 2)


@dataclass(frozen=True)
class MotionSample:
    """Displacements measured between two frames at points of the first: what stretch and mapping consume.

    Produced by :meth:`Trajectories.motion` (tracked features) and by :mod:`skinstretch.processing.flow` (dense grid).
    """

    frame_a: int
    frame_b: int
    points: np.ndarray  # (n, 2) x, y px in frame_a
    displacement: np.ndarray  # (n, 2) px from frame_a to frame_b
    ids: np.ndarray  # (n,) int64: track (or grid point) index, stable across pairs
    sigma: np.ndarray | None = None  # (n,) px: predicted standard error per axis of each displacement (None: none)
    match: np.ndarray | None = None  # (n,): each point's window match after the motion (None: not checked)
    doubt: str = ""  # why a self-check doubts the whole pair ("" when none does)

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass
class DenseTrajectories:
    """Trajectories as (frames, tracks) arrays (:meth:`Trajectories.dense`), for short sequences and plots.

    ``x, y`` (refined, chained, smoothed) and ``raw_x, raw_y`` (extracted) are NaN exactly where ``present`` is
    False; ``feature_index`` is -1 there; ``linked``/``refined`` mean what :class:`Trajectories` says.
    """

    x: np.ndarray
    y: np.ndarray
    present: np.ndarray
    raw_x: np.ndarray
    raw_y: np.ndarray
    feature_index: np.ndarray
    linked: np.ndarray
    refined: np.ndarray
    kind: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.present.shape[0])

    @property
    def n_tracks(self) -> int:
        return int(self.present.shape[1])

    @property
    def lengths(self) -> np.ndarray:
        return self.present.sum(axis=0)


#: Columns of the long trajectory table (:attr:`Trajectories.rows`, the results file's ``trajectories``).
TRAJECTORY_DTYPE = np.dtype(
    [
        ("frame", np.int32),
        ("track", np.int64),
        ("x", np.float64),
        ("y", np.float64),
        ("raw_x", np.float64),
        ("raw_y", np.float64),
        ("feature_index", np.int64),
        ("linked", np.bool_),
        ("refined", np.bool_),
        ("run", np.int32),
        ("anchor_sigma", np.float64),
    ]
)


@dataclass
class Trajectories:
    """Feature trajectories over a sequence (seed 5.1.2) as a long table: one row per track per frame it is present
    in, sorted by frame then track. Its size grows with the features seen, never with frames x tracks.

    Attributes
    ----------
    n_frames : int
    rows : TRAJECTORY_DTYPE array
        ``frame``, ``track``; ``x, y``: position px (refined and/or smoothed); ``raw_x, raw_y``: extracted position;
        ``feature_index``: row of the feature in the concatenated feature table of the sequence; ``linked``: the
        displacement from the track's previous frame was measured (consecutive match), as opposed to a start or a
        re-link across a gap; ``refined``: that displacement was refined to sub-pixel by image registration;
        ``run``: number of the linked run within the track (displacements are measured only within a run);
        ``anchor_sigma``: predicted standard error px (per axis) of the position relative to the run's first key
        frame from the key frames' registrations (:mod:`~skinstretch.processing.trajectory_anchoring`; 0 where
        chained only, inf where a key frame's registration could not be used); the chained steps since the last key
        frame are not in it.
    kind : (T,) int8
        Feature kind of each track.
    """

    n_frames: int
    rows: np.ndarray
    kind: np.ndarray

    @property
    def n_tracks(self) -> int:
        return int(self.kind.size)

    @property
    def lengths(self) -> np.ndarray:
        """Number of frames each track is present in."""
        return np.bincount(self.rows["track"], minlength=self.n_tracks)

    @cached_property
    def frame_offsets(self) -> np.ndarray:
        """(N + 1,) first row of each frame (rows of frame k: ``frame_offsets[k]:frame_offsets[k + 1]``)."""
        return np.searchsorted(self.rows["frame"], np.arange(self.n_frames + 1), side="left")

    def at(self, frame: int) -> np.ndarray:
        """The rows of ``frame`` (sorted by track)."""
        off = self.frame_offsets
        return self.rows[off[frame] : off[frame + 1]]

    def positions(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """(track indices, (n, 2) positions) of the tracks present in ``frame``."""
        r = self.at(frame)
        return r["track"].copy(), np.column_stack([r["x"], r["y"]])

    def motion(self, frame_a: int, frame_b: int) -> MotionSample:
        """Displacements from ``frame_a`` to ``frame_b`` of the tracks present in both, linked all the way."""
        n = self.n_frames
        if not (0 <= frame_a < n and 0 <= frame_b < n):
            raise InvalidInputError(f"frames ({frame_a}, {frame_b}) out of range for {n} frames")
        ra, rb = self.at(frame_a), self.at(frame_b)
        _, ia, ib = np.intersect1d(ra["track"], rb["track"], assume_unique=True, return_indices=True)
        same = ra["run"][ia] == rb["run"][ib]
        ia, ib = ia[same], ib[same]
        pa = np.column_stack([ra["x"][ia], ra["y"][ia]])
        pb = np.column_stack([rb["x"][ib], rb["y"][ib]])
        return MotionSample(int(frame_a), int(frame_b), pa, pb - pa, ra["track"][ia].astype(np.int64))

    def dense(self) -> DenseTrajectories:
        """The same trajectories as (frames, tracks) arrays (memory frames x tracks: short sequences only)."""
        n, t = self.n_frames, self.n_tracks
        fr, tr = self.rows["frame"], self.rows["track"]
        out = {name: np.full((n, t), np.nan) for name in ("x", "y", "raw_x", "raw_y")}
        for name, arr in out.items():
            arr[fr, tr] = self.rows[name]
        present = np.zeros((n, t), bool)
        present[fr, tr] = True
        fidx = np.full((n, t), -1, np.int64)
        fidx[fr, tr] = self.rows["feature_index"]
        linked = np.zeros((n, t), bool)
        linked[fr, tr] = self.rows["linked"]
        refined = np.zeros((n, t), bool)
        refined[fr, tr] = self.rows["refined"]
        return DenseTrajectories(present=present, feature_index=fidx, linked=linked, refined=refined,
                                 kind=self.kind, **out)


def step_consistency(points: np.ndarray, disp: np.ndarray, valid: np.ndarray, *, max_deviation_px: float,
                     bridge_spreads: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Which refined steps move like their neighbours: (close, alone), bool (n,) each.

    ``close``: within ``max_deviation_px`` of the median of the 7 nearest ``valid`` steps (skin moves smoothly: a
    step far from it is a registration failure). ``alone``, for steps measured by registration alone (bridged
    points): also within ``bridge_spreads`` robust spreads of those departures over the frame (1.4826 x their
    median over the valid steps; see ``TrackingParams.max_bridge_deviation_spreads``); None: ``close``.
    """
    med = local_predictions(points, points[valid], disp[valid], neighbours=7)
    deviation = np.hypot(*(disp - med).T)
    close = deviation <= max_deviation_px
    if bridge_spreads is None:
        return close, close
    return close, close & (deviation <= bridge_spreads * 1.4826 * np.median(deviation[valid]))


class FeatureTracker:
    """Streaming feature matcher: feed one frame's features (and optionally its image) at a time.

    Parameters
    ----------
    calibration : Calibration
    params : TrackingParams, optional
    refiner : SubpixelRefiner, optional
        Refine each matched displacement by local image registration (needs the images).
    motion_estimator : GlobalMotionEstimator, optional
        Predict displacements from the measured global motion and then from matched neighbours (two passes),
        instead of from each feature's previous displacement alone (needs the images).

    Examples
    --------
    >>> from skinstretch.processing.feature_table import make_features
    >>> cal = Calibration(px_per_mm=62.0)
    >>> tracker = FeatureTracker(calibration=cal, params=TrackingParams(min_length_frames=3))
    >>> for k in range(4):
    ...     _ = tracker.add_frame(make_features([10.0 + 2 * k, 80.0 + 2 * k], [20.0, 40.0], [0, 2], frame=k))
    >>> tr = tracker.finish()
    >>> tr.n_tracks, tr.lengths.tolist()
    (2, [4, 4])
    """

    def __init__(
        self,
        *,
        calibration: Calibration,
        params: TrackingParams | None = None,
        refiner: SubpixelRefiner | None = None,
        motion_estimator: GlobalMotionEstimator | None = None,
    ) -> None:
        self.calibration = calibration
        self.params = params or TrackingParams()
        self.refiner = refiner
        self.motion_estimator = motion_estimator
        self._radius = calibration.px(self.params.search_radius_mm)
        self._max_deviation = calibration.px(self.params.max_local_deviation_mm)
        self._merge_radius = calibration.px(self.params.merge_radius_mm)
        fusion = self.params.fusion_radius_mm
        self._fusion_radius = calibration.px(fusion) if fusion is not None else 0.0
        self._fusion_sigma = calibration.px(self.params.fusion_model_sigma_mm)
        self._n_frames = 0
        self._n_tracks = 0
        self._n_features = 0
        self._prev: FeatureColumns | None = None
        self._prev_frame: FrameImages | None = None
        self._prev_tracks = np.zeros(0, np.int64)
        self._prev_disp = np.zeros((0, 2))
        self._prev_age = np.zeros(0, np.int64)  # frames since each point of the previous frame was last detected
        self._prev_feature_row = np.zeros(0, np.int64)  # row of each point in its frame's features (-1: bridged)
        # per frame: (track ids, extracted xy (NaN for a point bridged by registration), offset of the frame's
        # features in the sequence's, disp from previous frame (NaN = not linked), refined); the frame's features
        # come first, in their table's order, then its bridged points
        self._frames: list[tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray]] = []
        self._track_kind: list[np.ndarray] = []
        self._released = False
        self._n_taken = 0  # frames handed out by take_frames
        self.global_shifts: list[np.ndarray] = []  # per pair, the prediction used for features without history
        self.pair_status: list[str] = []  # per pair: "ok", or why matching was weak

    @property
    def n_frames(self) -> int:
        return self._n_frames

    def prepare_image(self, image: np.ndarray) -> "FrameImages":
        """The per-frame image work of :meth:`add_frame` (registration image, coarse-motion image). It depends on
        this frame alone and is thread-safe, so the analysis runs it on its extraction threads, ahead of
        matching."""
        image = np.asarray(image)
        return FrameImages(
            refine=self.refiner.prepare(image) if self.refiner is not None else None,
            motion=self.motion_estimator.prepare(image) if self.motion_estimator is not None else None,
        )

    def add_frame(
        self, features: np.ndarray, *, image: np.ndarray | None = None, prepared: "FrameImages | None" = None
    ) -> Matches:
        """Match ``features`` (this frame) to the previous frame's; returns the matches between the two frames'
        features (rows of the two tables; empty for the first frame).

        ``image`` is needed with a refiner or a motion estimator, unless ``prepared`` (from :meth:`prepare_image`
        of the same image) is given instead.
        """
        if self._released:
            raise InvalidInputError("this tracker's records were released by finish(release=True)")
        validate_features(features)
        needs_image = self.refiner is not None or self.motion_estimator is not None
        if needs_image and prepared is None:
            if image is None:
                raise InvalidInputError("image is required when the tracker has a refiner or a motion estimator")
            prepared = self.prepare_image(image)
        cols = feature_columns(features)
        n = cols.xy.shape[0]
        disp = np.full((n, 2), np.nan)
        refined = np.zeros(n, bool)
        tracks = np.full(n, -1, np.int64)
        matches = Matches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        bridged = np.zeros(0, np.int64)  # points of the previous frame continued into this one by registration
        bridged_disp = np.zeros((0, 2))
        if self._prev is not None:
            prev = self._prev
            known = np.all(np.isfinite(self._prev_disp), axis=1)
            shift = self._prediction_shift(known, prepared)
            pred = np.where(known[:, None], self._prev_disp, shift)
            if self.motion_estimator is not None and self._prev_frame is not None:
                # A previous displacement disagreeing with the measured global motion is stale (direction change).
                stale = np.hypot(*(pred - shift).T) > self._radius / 2
                pred[stale] = shift
            matches = match_columns(prev, cols, pred, self._radius)
            if self.motion_estimator is not None and len(matches) >= 3:
                # Second pass: predict from matched neighbours (local structure, sticking and slipping regions).
                d1 = cols.xy[matches.curr_index] - prev.xy[matches.prev_index]
                pred = local_predictions(prev.xy, prev.xy[matches.prev_index], d1, fallback=shift)
                matches = match_columns(prev, cols, pred, self._radius)
            pi, ci = matches.prev_index, matches.curr_index
            d = cols.xy[ci] - prev.xy[pi]
            matched_prev = np.zeros(prev.xy.shape[0], bool)
            matched_prev[pi] = True
            if self.refiner is not None and self._prev_frame is not None:
                # Points left unmatched, seen at most max_bridge_frames ago, are looked for by registration alone.
                limit = self.params.max_bridge_frames
                young = self._prev_age < limit if limit is not None else np.ones(prev.xy.shape[0], bool)
                candidates = np.flatnonzero(~matched_prev & young)
                if pi.size or candidates.size:
                    rf = self._refine(prev, pi, ci, cols, d, candidates, pred[candidates], prepared)
                    bridged, bridged_disp = rf.bridged, rf.bridged_disp
                    keep = ~rf.detached  # a detached match: the registration followed the point away from its feature
                    matches = Matches(pi[keep], ci[keep], matches.confidence[keep])
                    pi, ci = matches.prev_index, matches.curr_index
                    d = rf.disp[keep]
                    refined[ci] = rf.ok[keep]
            disp[ci] = d
            tracks[ci] = self._prev_tracks[pi]
            self.global_shifts.append(shift)
            self.pair_status.append("ok" if len(matches) >= 3 else "fewer than 3 matches")
            if bridged.size and n:
                bridged, bridged_disp = merge_bridged(prev.xy, self._prev_tracks, bridged, bridged_disp, cols.xy,
                                                      tracks, disp, refined, matched_prev, radius=self._merge_radius)
            rows = self._prev_feature_row[matches.prev_index]
            matches = Matches(rows, matches.curr_index, matches.confidence)
        bridged_xy = self._prev.xy[bridged] + bridged_disp if bridged.size else np.zeros((0, 2))
        untrack = np.zeros(n, bool)
        if self.refiner is not None and bridged.size + n >= 2:
            untrack, drop = crowded_points(cols.xy, tracks, bridged_xy, self._prev_tracks[bridged],
                                           radius=self._merge_radius / 2)
            if drop.any():
                bridged, bridged_disp, bridged_xy = bridged[~drop], bridged_disp[~drop], bridged_xy[~drop]
            tracks[untrack] = -1
            disp[untrack] = np.nan
            refined[untrack] = False
        new = (tracks < 0) & ~untrack
        if self.refiner is not None:  # without registration the seed's matching is left as it is
            new &= ~duplicate_starts(cols.xy, tracks, bridged_xy, radius=self._merge_radius)
        tracks[new] = np.arange(self._n_tracks, self._n_tracks + int(new.sum()))
        self._n_tracks += int(new.sum())
        self._track_kind.append(cols.kind[new])
        # The record of this frame: its features (a duplicate of a tracked point has track -1), then the points
        # bridged into it (a measured position, no feature: the extracted position is NaN there).
        tracked = np.flatnonzero(tracks >= 0)
        nb = bridged.size
        raw = cols.xy
        rec_tracks, rec_disp, rec_refined = tracks, disp, refined
        if nb:
            raw = np.concatenate([cols.xy, np.full((nb, 2), np.nan)])
            rec_tracks = np.concatenate([tracks, self._prev_tracks[bridged]])
            rec_disp = np.concatenate([disp, bridged_disp])
            rec_refined = np.concatenate([refined, np.ones(nb, bool)])
        self._frames.append((rec_tracks, raw, self._n_features, rec_disp, rec_refined))
        # The points the next frame is matched to: the tracked features, then the bridged points.
        p = self._prev
        self._prev = FeatureColumns(
            np.concatenate([cols.xy[tracked], bridged_xy]),
            np.concatenate([cols.kind[tracked], p.kind[bridged] if nb else np.zeros(0, np.int8)]),
            np.concatenate([cols.orientation[tracked], p.orientation[bridged] if nb else np.zeros(0)]),
            np.concatenate([cols.known[tracked], p.known[bridged] if nb else np.zeros(0, bool)]),
        )
        self._prev_feature_row = np.concatenate([tracked, np.full(nb, -1, np.int64)])
        self._prev_tracks = np.concatenate([tracks[tracked], rec_tracks[n:]])
        self._prev_disp = np.concatenate([disp[tracked], bridged_disp])
        self._prev_age = np.concatenate([np.zeros(tracked.size, np.int64),
                                         self._prev_age[bridged] + 1 if nb else np.zeros(0, np.int64)])
        self._prev_frame = prepared if needs_image else None
        self._n_features += n
        self._n_frames += 1
        return matches

    def _refine(self, prev: FeatureColumns, pi, ci, cols: FeatureColumns, d, candidates, candidate_pred, prepared) -> "_Refinement":
        """Refine the displacements ``d`` of the matched points ``pi`` of ``prev`` (to features ``ci`` of ``cols``)
        and look for the unmatched ``candidates`` by registration alone.

        Matched displacements are registered from the matched features first (the seed of a sub-pixel step). Those
        that fail, and the candidates, are then registered from the motion of their refined neighbours (the median
        of the 6 nearest), which does not depend on where a jittery or wrong detection put the feature: a match
        whose registration ends further than ``merge_radius_mm`` from its feature is detached from it (the skin
        point is followed, the feature is free), one that ends near it is refined. A point found by registration
        alone has no feature to confirm it, so it must pass the local consistency test against at least 3 refined
        neighbours (a match carries the test when there are 7)."""
        m = pi.size
        a, b = self._prev_frame.refine, prepared.refine
        if m:
            r1 = self.refiner.refine(a, b, prev.xy[pi], d)
            dd, ok, win = r1.displacement.copy(), r1.refined.copy(), r1.window_px.copy()
        else:
            dd, ok, win = np.zeros((0, 2)), np.zeros(0, bool), np.zeros(0, np.int64)
        good = int(ok.sum())
        retry = np.flatnonzero(~ok) if good >= 3 else np.zeros(0, np.int64)
        rows = np.concatenate([pi[retry], candidates])
        init = np.concatenate([d[retry], candidate_pred])
        if rows.size and good >= 3:
            init = local_predictions(prev.xy[rows], prev.xy[pi][ok], dd[ok], fallback=np.median(dd[ok], axis=0))
        elif candidates.size and m >= 3:
            init = local_predictions(prev.xy[rows], prev.xy[pi], d, fallback=np.median(d, axis=0))
        detached = np.zeros(m, bool)
        found = np.zeros(candidates.size, bool)
        cand_disp = np.zeros((candidates.size, 2))
        cand_win = np.full(candidates.size, self.refiner.window_px, np.int64)
        if rows.size:
            r2 = self.refiner.refine(a, b, prev.xy[rows], init)
            nr = retry.size
            again, again_d = r2.refined[:nr], r2.displacement[:nr]
            near = np.hypot(*(prev.xy[pi[retry]] + again_d - cols.xy[ci[retry]]).T) <= self._merge_radius
            dd[retry[again]] = again_d[again]
            win[retry[again]] = r2.window_px[:nr][again]
            ok[retry[again & near]] = True
            detached[retry[again & ~near]] = True
            found, cand_disp, cand_win = r2.refined[nr:].copy(), r2.displacement[nr:], r2.window_px[nr:]
        # Local consistency: skin moves smoothly, so a refined displacement far from the median of its nearest
        # refined neighbours is a registration failure (contact edge, lost texture, a neighbouring ridge).
        points = np.concatenate([prev.xy[pi], prev.xy[candidates]])
        disp = np.concatenate([dd, cand_disp])
        valid = np.concatenate([ok | detached, found])
        n_ok = int(valid.sum())
        if n_ok >= 3:
            spreads = self.params.max_bridge_deviation_spreads if n_ok >= 7 else None
            close, alone = step_consistency(points, disp, valid, max_deviation_px=self._max_deviation,
                                            bridge_spreads=spreads)
            if n_ok >= 7:
                ok &= close[:m]
            detached &= alone[:m]
            found &= alone[m:]
        else:
            detached[:] = False
            found[:] = False
        ok &= ~detached
        # The skin deforming inside the registration window biases each step the same way (see
        # SubpixelRefiner.deformation_bias): removed with the displacement gradient at each point.
        good = np.concatenate([ok | detached, found])
        if int(good.sum()) >= 3:
            sel = np.flatnonzero(good)
            windows = np.concatenate([win, cand_win])[sel]
            cov, match = self.refiner.covariance_and_match(a, b, points[sel], disp[sel], windows)
            # A step whose windows do not look alike after it (another ridge, texture the registration cannot
            # follow) is not measured: its trajectory restarts there rather than jump (MIN_MATCH, as the results'
            # uncertainty judges it).
            astray = match < MIN_MATCH
            if astray.any():
                out = sel[astray]
                mine = out[out < m]
                ok[mine] = detached[mine] = False
                dd[mine] = disp[mine] = d[mine]  # the feature's own displacement, as for a failed registration
                found[out[out >= m] - m] = False
                sel, windows, cov = sel[~astray], windows[~astray], cov[~astray]
            if self._fusion_radius <= 0:
                cov = None
        if int(good.sum()) >= 3 and sel.size >= 3:
            grads = local_gradients(points[sel], disp[sel])  # the neighbours' fit
            bias = self.refiner.deformation_bias(a, points[sel], grads, windows)
            # A correction as large as the consistency bound comes from a window with texture in one direction
            # only (parallel ridges, no landmark), where it is ill-determined: left alone.
            bias[np.hypot(*bias.T) > self._max_deviation] = 0.0
            disp[sel] -= bias
            if cov is not None:  # the motion along a window's ridges from its neighbours' (neighbour_fusion)
                disp[sel] = fuse_with_neighbours(points[sel], disp[sel], cov, gradient=grads,
                                                 radius_px=self._fusion_radius,
                                                 model_sigma_px=self._fusion_sigma)[0]
            dd, cand_disp = disp[:m], disp[m:]
        bridged = np.concatenate([candidates[found], pi[detached]])
        bridged_disp = np.concatenate([cand_disp[found], dd[detached]])
        return _Refinement(dd, ok, detached, bridged, bridged_disp)

    def continue_with(self, other: "FeatureTracker", *, overlap: int) -> bool:
        """Append the frames that ``other`` tracked after an overlap with this tracker, if they are exactly the
        ones this tracker would have produced; return whether it did.

        ``other`` has the same parameters and was fed this tracker's last ``overlap + 1`` frames (the same
        features and images), then the frames that follow. A tracker's state before a frame depends only on
        the last :func:`join_overlap_frames` frames it saw (previous displacements, points followed by
        registration), or on what those frames hold (a point followed for longer is
        in them).
        When ``other`` agrees with this tracker on all of them, bit for bit (the same matches up to track
        numbering, the same displacements and refinement flags), its later frames are those this tracker would have
        produced: they are appended, tracks renumbered, and this tracker continues from
        ``other``'s state. When they do not agree nothing changes and False is returned: the caller feeds those
        frames to this tracker itself. This is what lets chunks of a sequence be tracked in parallel with the
        result of one sequential pass (:mod:`skinstretch.experiments.analysis.measure`).
        """
        window = join_overlap_frames(self.params)
        if int(overlap) < window or other._n_frames <= overlap or self._n_frames < overlap + 1:
            raise InvalidInputError(
                f"overlap must be at least {window} frames (join_overlap_frames) and shorter than both trackers' "
                f"frames, got overlap {overlap} for {self._n_frames} and {other._n_frames} frames"
            )
        if other.params != self.params or (other.refiner is None) != (self.refiner is None):
            raise InvalidInputError("the other tracker was built with different parameters")
        offset = self._n_frames - 1 - overlap  # this tracker's frame = offset + other's frame
        mine, theirs = [], []
        for i in range(overlap - window + 1, overlap + 1):
            ta, xa, _, da, ra = self._frames[offset + i]
            tb, xb, _, db, rb = other._frames[i]
            if not (np.array_equal(xa, xb, equal_nan=True) and np.array_equal(da, db, equal_nan=True)
                    and np.array_equal(ra, rb) and np.array_equal(ta < 0, tb < 0)):
                return False
            mine.append(ta[ta >= 0])
            theirs.append(tb[tb >= 0])
        pairs = np.unique(np.stack([np.concatenate(theirs), np.concatenate(mine)], axis=1), axis=0)
        if np.unique(pairs[:, 0]).size != pairs.shape[0] or np.unique(pairs[:, 1]).size != pairs.shape[0]:
            return False  # the two trackers split or joined the same features into different tracks
        n_before = sum(k.size for k in other._track_kind[: overlap + 1])  # other's tracks started by the overlap
        lut = np.full(other._n_tracks, -1, np.int64)
        lut[pairs[:, 0]] = pairs[:, 1]
        lut[n_before:] = self._n_tracks + np.arange(other._n_tracks - n_before)
        later = [other._frames[i][0] for i in range(overlap + 1, other._n_frames)]
        if any(np.any(lut[t[t >= 0]] < 0) for t in later):
            return False  # a track from before the compared frames reappears: cannot be numbered here
        for i in range(overlap + 1, other._n_frames):
            t, xy, _, d, r = other._frames[i]
            self._frames.append((np.where(t >= 0, lut[t], -1), xy, self._n_features, d, r))
            self._n_features += int(np.isfinite(xy[:, 0]).sum())
        self._track_kind.extend(other._track_kind[overlap + 1 :])
        self._n_tracks += other._n_tracks - n_before
        self._n_frames += other._n_frames - overlap - 1
        self.global_shifts.extend(other.global_shifts[overlap:])
        self.pair_status.extend(other.pair_status[overlap:])
        self._prev = other._prev
        self._prev_tracks = lut[other._prev_tracks]
        self._prev_disp = other._prev_disp
        self._prev_age = other._prev_age
        self._prev_feature_row = other._prev_feature_row
        self._prev_frame = other._prev_frame
        return True

    def _prediction_shift(self, known: np.ndarray, prepared: "FrameImages | None") -> np.ndarray:
        if self.motion_estimator is not None and self._prev_frame is not None:
            gm = self.motion_estimator.estimate_prepared(self._prev_frame.motion, prepared.motion)
            if gm.reliable:
                return gm.shift
        # Seed 5.1.1: features without a previous position take the average of the predicted displacements.
        if np.any(known):
            return np.mean(self._prev_disp[known], axis=0)
        return np.zeros(2)

    def finish(self, *, release: bool = False) -> Trajectories:
        """Assemble, filter (minimum length) and smooth the trajectories of every frame added so far.

        ``release``: free each frame's records as they are copied into the table (the tracker cannot be used
        afterwards; what a long analysis wants, so that records and table are not both held).

        ``params.min_length_frames`` None means the seed's 30 frames (the analysis adapts it to a short clip)."""
        if self._n_frames == 0:
            raise InsufficientDataError("no frames were added to the tracker")
        if self._released or self._n_taken:
            raise InvalidInputError("this tracker's records were released by finish(release=True) or take_frames")
        n, t = self._n_frames, self._n_tracks
        min_length = self.params.min_length_frames
        min_length = DEFAULT_MIN_LENGTH_FRAMES if min_length is None else int(min_length)
        # Features with track -1 (a skin point detected twice) belong to no trajectory; a point bridged by
        # registration (no feature) belongs to its track.
        in_track = [rec[0] >= 0 for rec in self._frames]
        all_tracks = np.concatenate([rec[0][m] for rec, m in zip(self._frames, in_track)]).astype(np.int64)
        keep_track = np.bincount(all_tracks, minlength=t) >= min_length
        del all_tracks
        new_id = np.cumsum(keep_track) - 1
        kind = np.concatenate(self._track_kind) if self._track_kind else np.zeros(0, np.int8)
        # The table is filled frame by frame with only the kept tracks' rows (memory: the rows, once).
        kept_rows = [np.flatnonzero(keep_track[rec[0]] & m) for rec, m in zip(self._frames, in_track)]
        del in_track
        rows = np.zeros(sum(k.size for k in kept_rows), dtype=TRAJECTORY_DTYPE)
        dx = np.empty(rows.size)
        dy = np.empty(rows.size)
        i = 0
        for k, sel in enumerate(kept_rows):
            tracks, xy, offset, disp, refined = self._frames[k]
            if release:
                self._frames[k] = None
            ids = new_id[tracks[sel]]
            order = np.argsort(ids, kind="stable")
            sel, ids = sel[order], ids[order]
            r = rows[i : i + sel.size]
            r["frame"], r["track"] = k, ids
            r["raw_x"], r["raw_y"] = xy[sel, 0], xy[sel, 1]
            r["feature_index"] = np.where(np.isfinite(xy[sel, 0]), offset + sel, -1)
            d = disp[sel]
            linked = np.all(np.isfinite(d), axis=1)
            if self.refiner is not None:
                # A step the refinement rejected is only as good as the extraction (~1 px): the trajectory keeps
                # its identity but its positions restart there, so no measured displacement spans that step.
                linked &= refined[sel]
            r["linked"], r["refined"] = linked, refined[sel] & linked
            dx[i : i + sel.size], dy[i : i + sel.size] = d[:, 0], d[:, 1]
            i += sel.size
        del kept_rows
        if release:
            self._frames, self._released = [], True
        n_kept = int(keep_track.sum())
        pos, run = _chain_tracks(rows["track"], rows["raw_x"], rows["raw_y"], dx, dy, rows["linked"], n_kept)
        del dx, dy
        radius = int(self.params.smoothing_radius_frames)
        if radius > 0 and n >= 2:
            sigma = float(self.params.smoothing_sigma_frames)
            weights = np.array([float(np.exp(-(i * i) / (2.0 * sigma**2))) for i in range(-radius, radius + 1)])
            offsets = np.searchsorted(rows["frame"], np.arange(n + 1), side="left")
            pos = smooth_track_rows(rows["track"], rows["frame"], run, pos, offsets, weights)
        rows["x"], rows["y"], rows["run"] = pos[:, 0], pos[:, 1], run
        return Trajectories(n_frames=n, rows=rows, kind=kind[keep_track].astype(np.int8))

    def take_frames(self, *, last: bool = False) -> list["TrackedFrame"]:
        """Hand out the frames that matching will not read again, oldest first, and forget them: every frame but
        the last :func:`join_overlap_frames` (what :meth:`continue_with` compares), or every frame when the sequence is
        over (``last``; the tracker then takes no more frames). A long analysis stores them as they come and builds
        the trajectories itself, so the tracker's memory does not grow; :meth:`finish` cannot be used afterwards.
        """
        if self._released:
            raise InvalidInputError("this tracker's records were released by finish(release=True) or take_frames")
        end = self._n_frames if last else max(0, self._n_frames - join_overlap_frames(self.params))
        out = []
        for k in range(self._n_taken, end):
            tracks, xy, offset, disp, refined = self._frames[k]
            new_kinds = self._track_kind[k]
            self._frames[k] = self._track_kind[k] = None
            rows = np.flatnonzero(tracks >= 0)  # as in finish: a skin point detected twice belongs to no track
            order = rows[np.argsort(tracks[rows], kind="stable")]
            linked = np.all(np.isfinite(disp), axis=1)
            if self.refiner is not None:
                linked &= refined  # as in finish: a rejected refinement restarts the positions
            feature_index = np.where(np.isfinite(xy[:, 0]), offset + np.arange(tracks.size), -1)  # -1: bridged
            out.append(TrackedFrame(k, tracks[order], xy[order], feature_index[order], disp[order], linked[order],
                                    (refined & linked)[order], new_kinds))
        self._n_taken = max(self._n_taken, end)
        self._released = last
        return out


@dataclass(frozen=True)
class TrackedFrame:
    """One frame's tracked features as :meth:`FeatureTracker.take_frames` hands them out, sorted by track.

    ``linked``: the displacement from the previous frame chains this row to the track's previous position (a
    consecutive match whose refinement, when there is one, was kept); ``new_track_kinds``: the kinds of the tracks
    that start in this frame, whose numbers follow those of every earlier frame's.
    """

    frame: int
    track: np.ndarray  # (n,) int64, increasing
    xy: np.ndarray  # (n, 2) extracted positions px, NaN for a point bridged by registration
    feature_index: np.ndarray  # (n,) row in the sequence's concatenated feature table, -1 for a bridged point
    displacement: np.ndarray  # (n, 2) px from the previous frame, NaN where not matched
    linked: np.ndarray  # (n,) bool
    refined: np.ndarray  # (n,) bool
    new_track_kinds: np.ndarray  # (m,) int8


@dataclass(frozen=True)
class FrameImages:
    """One frame's images as :meth:`FeatureTracker.add_frame` uses them (see :meth:`FeatureTracker.prepare_image`):
    the refiner's registration image and the motion estimator's coarse image (None without them)."""

    refine: PreparedImage | None
    motion: np.ndarray | None


@dataclass(frozen=True)
class _Refinement:
    """What :meth:`FeatureTracker._refine` found: per match its displacement, whether it was refined (and passed the
    consistency test) and whether it was detached from its feature; the previous frame's points found by
    registration alone (bridged) and their displacements."""

    disp: np.ndarray
    ok: np.ndarray
    detached: np.ndarray
    bridged: np.ndarray
    bridged_disp: np.ndarray


@njit(nogil=True)
def _chain_tracks(track, raw_x, raw_y, dx, dy, linked, n_tracks):
    """Positions as the running sum of measured displacements within each linked run, anchored to the mean of
    the run's extracted positions (equal to the extracted positions when displacements are raw differences); rows
    without one (NaN: bridged by registration) do not anchor, and every run starts at an extracted position.

    Rows in frame order (any order within a frame). Each track keeps its running sum from its first row (a start
    adds nothing), and a run's offset is the sum of its residuals in frame order over its size: the same
    operations in the same order as a cumulative sum over (frames, tracks) arrays, so the same numbers to the bit.
    Returns (positions (M, 2), run number of each row within its track)."""
    m = track.shape[0]
    cx = np.zeros(n_tracks)
    cy = np.zeros(n_tracks)
    sx = np.zeros(n_tracks)
    sy = np.zeros(n_tracks)
    runs = np.zeros(n_tracks, np.int32)
    current = np.full(n_tracks, -1, np.int64)
    n_starts = 0
    for i in range(m):
        if not linked[i]:
            n_starts += 1
    sums = np.zeros((n_starts, 2))
    counts = np.zeros(n_starts, np.int64)
    group = np.empty(m, np.int64)
    run = np.empty(m, np.int32)
    pos = np.empty((m, 2))
    g_next = 0
    for i in range(m):
        t = track[i]
        if linked[i]:
            cx[t] += dx[i]
            cy[t] += dy[i]
        else:  # a start: a new run, whose local positions count from here
            runs[t] += 1
            current[t] = g_next
            g_next += 1
            sx[t] = cx[t]
            sy[t] = cy[t]
        lx = cx[t] - sx[t]
        ly = cy[t] - sy[t]
        g = current[t]
        pos[i, 0] = lx
        pos[i, 1] = ly
        run[i] = runs[t]
        group[i] = g
        if raw_x[i] == raw_x[i]:  # a bridged point (no extracted position, NaN) does not anchor its run
            sums[g, 0] += raw_x[i] - lx
            sums[g, 1] += raw_y[i] - ly
            counts[g] += 1
    for i in range(m):
        g = group[i]
        pos[i, 0] += sums[g, 0] / counts[g]
        pos[i, 1] += sums[g, 1] / counts[g]
    return pos, run


def concatenate_features(tables: list[np.ndarray]) -> np.ndarray:
    """The concatenated feature table that :attr:`Trajectories.feature_index` points into (frame set per table)."""
    if not tables:
        return np.zeros(0, dtype=FEATURE_DTYPE)
    for k, t in enumerate(tables):  # the cheap checks per table, the value checks once on the whole
        if not isinstance(t, np.ndarray) or t.dtype != FEATURE_DTYPE or t.ndim != 1:
            raise InvalidInputError(
                f"feature table {k} must be a 1-D structured array of FEATURE_DTYPE, got {getattr(t, 'dtype', type(t))}"
            )
    out = validate_features(np.concatenate(tables))
    sizes = [t.shape[0] for t in tables]
    out["frame"] = np.repeat(np.arange(len(tables), dtype=np.int32), sizes)
    out["id"] = np.arange(out.shape[0])
    return out
