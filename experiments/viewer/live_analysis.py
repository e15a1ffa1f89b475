"""Online features and strain of a session while it is being recorded, for the live view.

The recorder never waits on this: it runs in the viewer's process and reads the session file in HDF5 SWMR mode,
like any other reader. It takes the frames in order while it is at most MAX_LAG_FRAMES behind the newest the
recorder has flushed, and otherwise jumps to the newest, skipping the ones it had no time for (lossy by design): it
never falls further behind the recording, and its rate is what the machine can spare.

Per analysed frame: features extracted (seed 4; on the frame halved where its ridges stay well resolved,
:class:`~skinstretch.processing.extraction.ReducedFeatureExtractor`), matched to the previously analysed frame with
the global-motion prediction (seed 5.1.1), refined to sub-pixel by local registration at full resolution, and the
Delaunay triangulation of the matched points measured between the two frames (seed 5.3.1). The glass-shading step
and the tactile movie need the whole sequence: they come with the analysis after the trial (``skinstretch analyze``
or the runner's worker), which the viewer picks up when its results appear.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from skinstretch.drivers.errors import SessionFileError
from skinstretch.experiments.viewer.session_data import (
    TAIL_FRAMES,
    FeatureMarks,
    FrameOverlays,
    Mesh,
    SessionSource,
    convex_hull,
    nice_scale,
)
from skinstretch.processing.displacement_refinement import SubpixelParams, SubpixelRefiner
from skinstretch.processing.errors import InsufficientDataError, SkinstretchError
from skinstretch.processing.extraction import ReducedFeatureExtractor
from skinstretch.processing.global_motion import GlobalMotionEstimator, local_predictions
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.stretch import triangulation_strain
from skinstretch.processing.tracking import FeatureTracker, MotionSample, TrackingParams

log = logging.getLogger(__name__)

__all__ = ["LiveAnalyzer", "LiveStats", "warm_up"]

MAX_EDGE_MM = 2.0  # the analysis' default (AnalysisParams.max_edge_mm): long hull slivers left out
MAX_LAG_FRAMES = 4  # frames analysed in order while at most this many behind the newest; beyond, it skips ahead
SCALE_WINDOW_FRAMES = 60  # the colour scale covers the strains of the last analysed frames (a few seconds)


@dataclass
class LiveStats:
    """What the live analysis did: frames analysed and skipped, its rate, and per-frame analysis time."""

    analysed: int
    skipped: int
    frames_per_s: float
    last_frame: int
    analysis_ms_p95: float
    error: str


class LiveAnalyzer:
    """Analyse the newest frame of a session being recorded, over and over, on a thread of its own.

    Parameters
    ----------
    source : SessionSource
        The session, opened in SWMR mode.
    keep_frames : int
        Overlays of this many most recent analysed frames are kept for stepping back.
    poll_s : float
        Wait between looks at the file when no new frame is there.
    """

    def __init__(self, source: SessionSource, *, keep_frames: int = 900, poll_s: float = 0.005) -> None:
        self.source = source
        cal = Calibration(px_per_mm=float(source.session.calibration.px_per_mm))
        self._cal = cal
        self._extractor = ReducedFeatureExtractor(calibration=cal)
        self._tracker = FeatureTracker(
            # no bridging while recording (the analysis bridges: it has the time)
            calibration=cal, params=TrackingParams(max_bridge_frames=0),
            motion_estimator=GlobalMotionEstimator(downsample=cal.resolvable_reduction(4)),
        )
        # One window: the analysis' wider second window for imprecise points costs a sixth of a live frame.
        self._refiner = SubpixelRefiner(calibration=cal, params=SubpixelParams(wide_window_mm=None))
        self._max_edge_px = cal.px(MAX_EDGE_MM)
        self._max_deviation_px = cal.px(TrackingParams().max_local_deviation_mm)
        self._keep = int(keep_frames)
        self._poll = float(poll_s)
        self._overlays: OrderedDict[int, FrameOverlays] = OrderedDict()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-analysis", daemon=True)
        self._history: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=TAIL_FRAMES + 1)  # (tracks, xy)
        self._prev: tuple[int, np.ndarray, np.ndarray, object] | None = None  # frame, xy, tracks, prepared image
        self._prev_tracks = np.zeros(0, np.int64)
        self._n_tracks = 0
        self._recent_changes: deque[np.ndarray] = deque(maxlen=SCALE_WINDOW_FRAMES)
        self._analysed = 0
        self._skipped = 0
        self._last = -1
        self._t_first: float | None = None
        self._durations: deque[float] = deque(maxlen=600)
        self._p95 = (-1, 0.0)  # (version, analysis ms p95) of the last stats()
        self._error = ""
        self.version = 0  # bumped after every analysed frame (the server's event stream watches it)

    # -- control
    def start(self) -> "LiveAnalyzer":
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    # -- results
    def overlays(self, frame: int) -> FrameOverlays | None:
        with self._lock:
            return self._overlays.get(frame)

    def latest(self) -> FrameOverlays | None:
        with self._lock:
            return next(reversed(self._overlays.values()), None) if self._overlays else None

    def stats(self) -> LiveStats:
        """What it did so far (the viewer's event stream asks 100 times a second: the percentile is computed once
        per analysed frame)."""
        with self._lock:
            if self._p95[0] != self.version:
                dur = np.asarray(self._durations)
                self._p95 = (self.version, float(np.percentile(dur, 95) * 1e3) if dur.size else 0.0)
            span = (time.monotonic() - self._t_first) if self._t_first is not None else 0.0
            return LiveStats(
                analysed=self._analysed, skipped=self._skipped,
                frames_per_s=(self._analysed - 1) / span if span > 0 and self._analysed > 1 else 0.0,
                last_frame=self._last, analysis_ms_p95=self._p95[1], error=self._error,
            )

    # -- the loop
    def _run(self) -> None:
        """Two stages on two threads: while this one links frame k to the frame before (matching, refinement,
        strain), the other extracts the next frame (:func:`_next_frame`), so a frame costs the longer stage, not
        both."""
        with ThreadPoolExecutor(1, thread_name_prefix="live-extraction") as pool:
            ahead: tuple[int, Future] | None = None  # the next frame to link, being extracted
            while not self._stop.is_set():
                try:
                    if ahead is None:
                        k = _next_frame(self._last, self.source.n_frames() - 1)
                        if k is None:
                            if self.source.status() != "recording":
                                break  # the recording ended and its last frame is analysed
                            self._stop.wait(self._poll)
                            continue
                        ahead = (k, pool.submit(self._extract, k))
                    k, job = ahead
                    frame = job.result()
                    after = _next_frame(k, self.source.n_frames() - 1)
                    ahead = (after, pool.submit(self._extract, after)) if after is not None else None
                    if self._last >= 0:
                        self._skipped += k - self._last - 1
                    self._link(k, frame)
                except (SessionFileError, SkinstretchError, OSError) as exc:
                    self._error = f"{type(exc).__name__}: {exc}"
                    log.warning("live analysis stopped: %s", self._error)
                    break
            if ahead is not None:
                ahead[1].cancel()

    def analyse_frame(self, k: int) -> FrameOverlays:
        """Analyse frame ``k`` against the previously analysed frame and keep its overlays."""
        return self._link(k, self._extract(k))

    def _extract(self, k: int) -> "_ExtractedFrame":
        """What depends on frame ``k`` alone (thread-safe): its features and prepared images."""
        t0 = time.perf_counter()
        image = self.source.frame(k)
        res = self._extractor.extract(image, frame_index=k)
        return _ExtractedFrame(t0, self.source.timestamp(k), res, self._tracker.prepare_image(image),
                               self._refiner.prepare(image, gradient=False))

    def _link(self, k: int, frame: "_ExtractedFrame") -> FrameOverlays:
        """Frame ``k`` (:meth:`_extract`) matched to the previously analysed frame, its overlays kept; the frames
        must come in increasing order."""
        t0 = time.perf_counter()
        exposure, res, prepared, refine_image = frame.exposure, frame.result, frame.prepared, frame.refine_image
        feats = res.features if res.ok else res.features[:0]
        matches = self._tracker.add_frame(feats, prepared=prepared)
        xy = np.column_stack([feats["x"], feats["y"]]).astype(np.float64)
        tracks = np.full(xy.shape[0], -1, np.int64)
        notes = ["live analysis: newest frame against the previous analysed one; glass shading not removed, "
                 "tactile movie after the trial's analysis"]
        if res.flags:
            notes.append("frame flagged: " + ", ".join(sorted(res.flags)))
        matches_seg = arrows = np.zeros((0, 4))
        ci = np.zeros(0, np.int64)
        mesh = None
        if self._prev is not None and len(matches):
            pk, pxy, ptracks, pref = self._prev
            pi, ci = matches.prev_index, matches.curr_index
            tracks[ci] = ptracks[pi]
            r = self._refiner.refine(pref, refine_image, pxy[pi], xy[ci] - pxy[pi])
            ok = r.refined.copy()
            if ok.sum() >= 7:
                # As the analysis does: a refined displacement far from the median of its 7 nearest refined
                # neighbours is a registration failure (skin moves smoothly); so is an unrefined one.
                med = local_predictions(pxy[pi], pxy[pi][ok], r.displacement[ok], neighbours=7)
                ok &= np.hypot(*(r.displacement - med).T) <= self._max_deviation_px
            pi, ci, d = pi[ok], ci[ok], r.displacement[ok]
            matches_seg = np.column_stack([pxy[pi], xy[ci]])
            arrows = np.column_stack([pxy[pi] + d, d])
            try:
                s = triangulation_strain(MotionSample(pk, k, pxy[pi], d, tracks[ci]), max_edge_px=self._max_edge_px)
                ends = s.points + _displacement_of(s.ids, tracks[ci], d)
                tri = s.triangles
                mesh_xy = np.column_stack([ends[tri[:, 0]], ends[tri[:, 1]], ends[tri[:, 2]]])
                mesh = Mesh(1, pk, k, mesh_xy, s.ids[tri], s.area_change, s.flipped, "frame_b")
                self._recent_changes.append(s.area_change[~s.flipped])
            except InsufficientDataError as exc:
                notes.append(f"no strain: {exc}")
        new = tracks < 0
        tracks[new] = np.arange(self._n_tracks, self._n_tracks + int(new.sum()))
        self._n_tracks += int(new.sum())
        self._history.append((tracks, xy))
        tails = self._tails(tracks)
        overlays = FrameOverlays(
            frame=k, source="live",
            features=FeatureMarks(feats["id"].astype(np.int64), tracks, feats["kind"].astype(np.int8), xy[:, 0],
                                  xy[:, 1], feats["quality"].astype(np.float32)),
            matches=matches_seg, arrows=arrows, tails=tails, mesh=mesh, outline=convex_hull(xy), window=None,
            tactile_um=None, tactile_reset=None, tactile_clipped=None, truth=None,
            strain_scale=nice_scale(np.concatenate(self._recent_changes)) if self._recent_changes else 0.01,
            notes=notes, arrow_ids=tracks[ci] if arrows.size else np.zeros(0, np.int64),
            exposure_time=exposure, analysed_time=time.time(),
        )
        self._prev = (k, xy, tracks, refine_image)
        with self._lock:
            self._overlays[k] = overlays
            while len(self._overlays) > self._keep:
                self._overlays.popitem(last=False)
            self._analysed += 1
            self._last = k
            if self._t_first is None:
                self._t_first = time.monotonic()
            self._durations.append(time.perf_counter() - t0 + frame.seconds)
            self.version += 1
        return overlays

    def _tails(self, tracks: np.ndarray) -> list[np.ndarray]:
        """Polylines of the current tracks through the last analysed frames (oldest point first)."""
        ids = np.concatenate([h[0] for h in self._history])
        xy = np.concatenate([h[1] for h in self._history])
        keep = np.isin(ids, tracks)
        ids, xy = ids[keep], xy[keep]
        order = np.argsort(ids, kind="stable")  # stable: each track's points stay in frame order
        ids, xy = ids[order], xy[order]
        bounds = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1], True]).tolist() if ids.size else [0]
        return [xy[a:b] for a, b in zip(bounds[:-1], bounds[1:]) if b - a >= 2]  # slices: np.split costs 10x


@dataclass
class _ExtractedFrame:
    """One frame's own work for :meth:`LiveAnalyzer._link`: when it started, its exposure time, the extraction's
    result and the tracker's and refiner's prepared images."""

    started: float
    exposure: float
    result: object  # ExtractionResult
    prepared: object  # the tracker's FrameImages
    refine_image: object  # the refiner's PreparedImage
    seconds: float = 0.0

    def __post_init__(self) -> None:
        self.seconds = time.perf_counter() - self.started


def _next_frame(previous: int, newest: int) -> int | None:
    """The frame to analyse after ``previous`` (-1: none yet) when ``newest`` is the newest recorded: the next one
    while at most MAX_LAG_FRAMES behind the newest (the recorder makes frames visible a few at a time, at each
    flush: taking only the newest skipped frames there was time for), else the newest; None when there is none."""
    if newest <= previous:
        return None
    if previous < 0 or newest - (previous + 1) > MAX_LAG_FRAMES:
        return newest
    return previous + 1


def _displacement_of(ids: np.ndarray, sample_ids: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Displacement of each of ``ids`` (rows of ``d`` are ``sample_ids``)."""
    order = np.argsort(sample_ids)
    return d[order[np.searchsorted(sample_ids[order], ids)]]


class _SyntheticPrint:
    """A stand-in for a session source: frames of a made-up print (parallel ridges with a dozen minutiae, each a
    phase vortex) sliding 1.5 px a frame inside an elliptic contact, at 62 px/mm."""

    PX_PER_MM = 62.0

    def __init__(self, shape: tuple[int, int] = (242, 320)) -> None:
        h, w = shape
        y, x = np.mgrid[0:h, 0:w].astype(np.float64)
        rng = np.random.default_rng(1)
        vortices = zip(rng.uniform(0.2 * w, 0.8 * w, 12), rng.uniform(0.2 * h, 0.8 * h, 12))
        self._x, self._y, self._vortices = x, y, list(vortices)
        self.session = type("SyntheticSession", (), {"calibration": Calibration(px_per_mm=self.PX_PER_MM)})()

    def frame(self, k: int) -> np.ndarray:
        x, y = self._x - 1.5 * k, self._y
        phase = 2 * np.pi * x / (0.45 * self.PX_PER_MM)
        for i, (cx, cy) in enumerate(self._vortices):
            phase += (1 if i % 2 else -1) * np.arctan2(y - cy, x - cx)
        h, w = x.shape
        inside = ((self._x - w / 2) / (0.45 * w)) ** 2 + ((y - h / 2) / (0.45 * h)) ** 2 < 1
        return np.where(inside, 140 + 80 * np.cos(phase), 230).astype(np.uint8)

    def timestamp(self, k: int) -> float:
        return k / 60.0


def warm_up(frames: int = 3) -> float:
    """Run the live analysis on a few made-up frames so its compiled kernels are loaded (numba's cache) before a
    recording's first frame arrives; returns the seconds it took.

    Loading them costs the first analysed frame ~0.5 s, a tenth of a 5 s trial's live rate on a 2-core machine.
    """
    t0 = time.perf_counter()
    analyzer = LiveAnalyzer(_SyntheticPrint())
    for k in range(frames):
        analyzer.analyse_frame(k)
    return time.perf_counter() - t0
