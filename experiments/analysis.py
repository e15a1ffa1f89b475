"""The analyze pipeline: one session file -> results (seed chapters 4-5), by features or by dense flow.

``analyze_session(session_path, outdir, method=..., params=..., progress=...)`` reads the session, measures
motion between consecutive frames (tracked features refined to sub-pixel, or the dense flow grid), then derives
everything else from those per-pair :class:`~skinstretch.processing.tracking.MotionSample` s: fingertip motion and the
visibility window (seed 5.2), triangulation strain at each span (5.3.1), the stretch profile along the sliding
direction (5.3.2, Figure 94) and the tactile movie (5.4). It writes ``OUTDIR/results.h5`` and
``OUTDIR/summary.json`` (see ``docs/results-format.md``) and returns the results path.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from collections import abc
from typing import Any, Sequence

import numpy as np

from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.json_encoding import json_default, json_safe
from skinstretch.experiments.provenance import software_versions
from skinstretch.progress import progress_bar
from skinstretch.experiments.results_file import (
    EDGE_DTYPE,
    MOTION_DTYPE,
    PAIR_DTYPE,
    TRIANGLE_DTYPE,
    Results,
    SpanStrain,
    write_results,
)
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.display_mapping import DisplayMappingParams, tactile_movie
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.fingertip import fingertip_motion, visibility_window
from skinstretch.processing.flow import DenseFlow, FlowField, FlowParams
from skinstretch.processing.stretch import horizontal_stretch_profile, mean_profile, triangulation_strains
from skinstretch.processing.displacement_refinement import SubpixelParams
from skinstretch.processing.tracking import MotionSample, TrackingParams, concatenate_features

METHODS = ("features", "flow")


@dataclass(frozen=True)
class AnalysisParams:
    """Options of the whole pipeline (each stage keeps its own small parameter object).

    ``spans`` are the frame spans of the triangulation strain (seed 6.3.2: 1 and 11). ``max_edge_mm`` drops long
    hull slivers; ``profile_strip_mm`` is the strip width w of Figure 62 and ``profile_step_mm`` the spacing of
    profile positions. ``flow_stride`` subsamples the flow grid for triangulation (edges ~0.8 mm, like the
    feature triangulation's ~48 px, seed 6.3.3). ``workers`` is the parallelism of the measurement: with
    ``processes`` (default) the features are extracted and tracked in chunks of frames on that many worker
    processes (:mod:`skinstretch.experiments.analysis_pool`; the same result as one sequential pass, started once per process,
    about a second); otherwise ``workers`` threads extract features ahead of the tracker.

    ``glass_shading`` removes brightness patterns that stay on the prism while the skin slides
    (:mod:`skinstretch.processing.glass_shading`: partial contact and slope lighting over a ridge or a valley bias every motion
    estimate towards zero there): True / False, or None (default) for "when the session's surface is not flat"
    (its metadata ``surface``). ``glass_shading_smooth_mm`` smooths its per-pixel maps across the shape and
    ``glass_shading_along_shape_mm`` along it (the axis of least shading variation); a sequence whose skin moved
    less than ``glass_shading_min_motion`` (temporal over spatial contrast) is left as it is.
    """

    tracking: TrackingParams = field(default_factory=lambda: TrackingParams(smoothing_radius_frames=0, max_gap_frames=3))
    subpixel: SubpixelParams | None = field(default_factory=SubpixelParams)
    robust_matching: bool = True
    flow: FlowParams = field(default_factory=FlowParams)
    display: DisplayMappingParams = field(default_factory=DisplayMappingParams)
    spans: tuple[int, ...] = (1, 11)
    max_edge_mm: float = 2.0
    profile_strip_mm: float = 1.0
    profile_step_mm: float = 0.25
    flow_stride: int = 4
    workers: int = 2
    processes: bool = True
    extraction: Any = None  # skinstretch.processing.extraction.ExtractionParams (None = its defaults)
    glass_shading: bool | None = None
    glass_shading_smooth_mm: float = 0.025
    glass_shading_along_shape_mm: float = 0.13
    glass_shading_min_motion: float = 1.1

    def __post_init__(self) -> None:
        if not self.spans or any(int(s) < 1 for s in self.spans):
            raise InvalidInputError(f"spans must be positive frame counts, got {self.spans!r}")
        for name in ("max_edge_mm", "profile_strip_mm", "profile_step_mm", "glass_shading_smooth_mm",
                     "glass_shading_along_shape_mm"):
            if not getattr(self, name) > 0:
                raise InvalidInputError(f"{name} must be positive, got {getattr(self, name)!r}")
        if int(self.flow_stride) < 1:
            raise InvalidInputError(f"flow_stride must be >= 1, got {self.flow_stride!r}")

    def to_dict(self) -> dict[str, Any]:
        d = {}
        for k, v in self.__dict__.items():
            if hasattr(v, "__dataclass_fields__"):
                d[k] = {kk: (vv.value if hasattr(vv, "value") else vv) for kk, vv in asdict(v).items()}
            else:
                d[k] = v
        return d


@dataclass
class MotionMeasurement:
    """What a method measured: per consecutive pair samples, and per span the samples of every pair."""

    samples: list[MotionSample]
    span_samples: dict[int, list[MotionSample | str]]  # a str says why that pair has no sample
    frame_flags: list[str]
    features: np.ndarray | None = None
    trajectories: dict[str, np.ndarray] | None = None
    flow_fields: list[FlowField] | None = None
    timing: dict[str, float] = field(default_factory=dict)
    parallel: str = ""  # how the measurement ran (threads or worker processes), for the results' params


def _mapping_of(session) -> Any:
    if not session.mapping_json:
        return None
    from skinstretch.processing.geometric_calibration import mapping_from_dict

    return mapping_from_dict(json.loads(session.mapping_json))


def _rectify(xy: np.ndarray, mapping, px_per_mm: float) -> np.ndarray:
    """Image px -> skin px (mapping's mm times px_per_mm), so strains are on the skin (seed 3.4)."""
    if mapping is None:
        return xy
    return np.asarray(mapping.image_to_surface(xy), dtype=np.float64) * px_per_mm


def measure_features(
    frames: Sequence[np.ndarray],
    *,
    calibration: Calibration,
    params: AnalysisParams,
    mapping=None,
    progress: bool = False,
) -> MotionMeasurement:
    """Extract, match, refine and chain features (seed 4, 5.1) and return their per-pair motion.

    With ``params.processes`` and ``workers >= 2`` the frames are tracked in chunks on worker processes
    (:mod:`skinstretch.experiments.analysis_pool`, the same result as one sequential pass); otherwise, or if the processes
    cannot run, on threads of this process.
    """
    from skinstretch.experiments import analysis_pool  # noqa: PLC0415

    n = len(frames)
    workers = max(1, int(params.workers))
    tracker = None
    parallel = f"threads ({workers})"
    overlap = int(params.tracking.max_gap_frames) + 2  # the least FeatureTracker.continue_with accepts
    first = np.asarray(frames[0]) if n else None
    # Worker processes take 2-D uint8 frames (shared as one block); anything else is checked on threads.
    plain = first is not None and first.ndim == 2 and first.dtype == np.uint8
    plan = analysis_pool.chunk_plan(n, workers=workers, overlap=overlap) if params.processes and plain else None
    if plan is not None:
        raw, shading, good = frames, None, None
        if isinstance(frames, _ShadedFrames):
            raw, shading, good = frames._frames, frames._shading, frames._good
        bar = progress_bar(n, enabled=progress, desc="features")
        try:
            pt = analysis_pool.track_in_processes(
                raw, calibration=calibration, params=params, workers=workers, plan=plan, overlap=overlap,
                shading=shading, good=good, read_frame=lambda k: np.asarray(frames[k]),
                on_frames=lambda done: bar.update(done - bar.n),
            )
            tracker, tables, flags, timing = pt.tracker, pt.tables, pt.flags, pt.timing
            parallel = f"processes ({workers}): {pt.n_chunks} chunks, {pt.n_retracked} re-tracked at their join"
        except analysis_pool.ProcessPoolFailed as exc:
            parallel = f"threads ({workers}): worker processes failed ({exc})"
        finally:
            bar.close()
    if tracker is None:
        tracker, tables, flags, timing = _track_on_threads(
            frames, calibration=calibration, params=params, workers=workers, progress=progress
        )
    t0 = time.perf_counter()
    tr = tracker.finish()
    if mapping is not None:
        for a, b in (("x", "y"), ("raw_x", "raw_y")):
            xy = np.stack([getattr(tr, a), getattr(tr, b)], axis=-1)
            ok = np.all(np.isfinite(xy), axis=-1)
            out = np.full(xy.shape, np.nan)
            out[ok] = _rectify(xy[ok], mapping, calibration.px_per_mm)
            setattr(tr, a, out[..., 0])
            setattr(tr, b, out[..., 1])
    samples = [tr.motion(k, k + 1) for k in range(n - 1)]
    span_samples = {int(s): samples if int(s) == 1 else [tr.motion(k, k + s) for k in range(n - s)]
                    for s in params.spans}
    timing["tracking_s"] += time.perf_counter() - t0
    trajectories = {
        name: getattr(tr, name)
        for name in ("x", "y", "present", "raw_x", "raw_y", "feature_index", "linked", "refined", "kind")
    }
    return MotionMeasurement(
        samples=samples,
        span_samples=span_samples,
        frame_flags=flags,
        features=concatenate_features(tables),
        trajectories=trajectories,
        # image_prep_s: the tracker's per-frame image work, done on the extraction threads (or in the workers).
        timing=timing,
        parallel=parallel,
    )


def _track_on_threads(frames, *, calibration: Calibration, params: AnalysisParams, workers: int, progress: bool):
    """Extraction of the next frames, and the tracker's per-frame image work (registration and coarse-motion
    images), on ``workers`` threads (OpenCV releases the GIL) while this thread matches and refines: frames are
    consumed strictly in order, at most 2 * workers ahead."""
    from skinstretch.experiments.analysis_pool import make_extractor, make_tracker  # noqa: PLC0415

    n = len(frames)
    extractor = make_extractor(calibration, params)
    tracker = make_tracker(calibration, params)
    tables, flags = [], []
    t_extract = t_prepare = t_track = 0.0
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: dict[int, Any] = {}

        def timed_extract(k: int):
            t0 = time.perf_counter()
            image = np.asarray(frames[k])
            res = extractor.extract(image, frame_index=k)
            t1 = time.perf_counter()
            prepared = tracker.prepare_image(image)
            return res, prepared, t1 - t0, time.perf_counter() - t1

        ahead = 2 * workers
        for k in range(min(ahead, n)):
            pending[k] = pool.submit(timed_extract, k)
        bar = progress_bar(n, enabled=progress, desc="features")
        for k in range(n):
            res, prepared, dt, dt_prepare = pending.pop(k).result()
            if k + ahead < n:
                pending[k + ahead] = pool.submit(timed_extract, k + ahead)
            t1 = time.perf_counter()
            feats = res.features if res.ok else res.features[:0]
            tracker.add_frame(feats, prepared=prepared)
            t_track += time.perf_counter() - t1
            t_extract += dt
            t_prepare += dt_prepare
            tables.append(feats)
            flags.append(",".join(sorted(res.flags)))
            bar.update(1)
        bar.close()
    return tracker, tables, flags, {"extraction_s": t_extract, "image_prep_s": t_prepare, "tracking_s": t_track}


def measure_flow(
    frames: Sequence[np.ndarray],
    *,
    calibration: Calibration,
    params: AnalysisParams,
    mapping=None,
    progress: bool = False,
) -> MotionMeasurement:
    """Dense flow between consecutive frames; longer spans chain the fields along the skin points."""
    n = len(frames)
    flow = DenseFlow(calibration=calibration, params=params.flow)
    flags = [""] * n
    t0 = time.perf_counter()
    bar = progress_bar(max(n - 1, 0), enabled=progress, desc="flow")
    try:
        # Each frame prepared once, runs of pairs on params.workers threads (same fields as pair by pair).
        fields = flow.compute_sequence(frames, threads=max(1, int(params.workers)),
                                       on_field=lambda _f: bar.update(1))
    finally:
        bar.close()
    for f in fields:
        if f.status != "ok" and not any(f.frame_flags):
            flags[f.frame_a] = f.status
        for k, refused in zip((f.frame_a, f.frame_b), f.frame_flags):  # the texture gate names each frame's reason
            flags[k] = refused or flags[k]
    t_flow = time.perf_counter() - t0
    t0 = time.perf_counter()
    samples = [_rectified_sample(f.motion(), mapping, calibration) for f in fields]
    span_samples: dict[int, list[MotionSample | str]] = {}
    for s in params.spans:
        out: list[MotionSample | str] = []
        for k in range(n - s):
            out.append(_rectified_sample(chain_flows(fields[k : k + s], stride=params.flow_stride), mapping, calibration))
        span_samples[int(s)] = out
    return MotionMeasurement(
        samples=samples,
        span_samples=span_samples,
        frame_flags=flags,
        flow_fields=fields,
        timing={"flow_s": t_flow, "chaining_s": time.perf_counter() - t0},
    )


def chain_flows(fields: Sequence[FlowField], *, stride: int = 1) -> MotionSample:
    """Displacement from the first field's frame to the last field's second frame, following skin points
    (every ``stride``-th node of the first grid) through each field in turn; points lost on the way drop out."""
    if not fields:
        raise InvalidInputError("chain_flows needs at least one field")
    first = fields[0].motion(stride=stride)
    p0 = first.points
    p = p0 + first.displacement
    ids = first.ids
    for f in fields[1:]:
        d, ok = f.sample(p)
        p, p0, ids = p[ok] + d[ok], p0[ok], ids[ok]
    return MotionSample(fields[0].frame_a, fields[-1].frame_b, p0, p - p0, ids)


def _rectified_sample(s: MotionSample, mapping, cal: Calibration) -> MotionSample:
    if mapping is None or len(s) == 0:
        return s
    pa = _rectify(s.points, mapping, cal.px_per_mm)
    pb = _rectify(s.points + s.displacement, mapping, cal.px_per_mm)
    return MotionSample(s.frame_a, s.frame_b, pa, pb - pa, s.ids)


def span_strain(samples: Sequence[MotionSample | str], *, span: int, max_edge_px: float) -> SpanStrain:
    """Triangulation strain of every pair of one span (one compiled call for all of them, see
    :func:`~skinstretch.processing.stretch.triangulation_strains`); pairs that cannot give one carry the reason."""
    pairs = np.zeros(len(samples), dtype=PAIR_DTYPE)
    measured = [i for i, s in enumerate(samples) if not isinstance(s, str)]
    for i, s in enumerate(samples):
        if isinstance(s, str):
            pairs[i] = (i, i + span, 0, s.encode()[:96])
    b = triangulation_strains([samples[i] for i in measured], max_edge_px=max_edge_px)
    where = np.asarray(measured, dtype=np.int64)
    pairs["frame_a"][where], pairs["frame_b"][where], pairs["n_points"][where] = b.frame_a, b.frame_b, b.n_points
    pairs["status"][where] = [b"ok" if r is None else r.encode()[:96] for r in map(b.failure, range(where.size))]
    # The edge and triangle tables are filled field by field over the batch's flat arrays.
    edges = np.zeros(b.edges.shape[0], dtype=EDGE_DTYPE)
    edges["pair"] = np.repeat(where, np.diff(b.edge_offsets))
    edges["id_a"], edges["id_b"] = b.ids[b.edges].T
    edges["xa"], edges["ya"], edges["xb"], edges["yb"] = b.points[b.edges].reshape(-1, 4).T
    edges["length"], edges["change"] = b.edge_length, b.edge_change
    tris = np.zeros(b.triangles.shape[0], dtype=TRIANGLE_DTYPE)
    tris["pair"] = np.repeat(where, np.diff(b.triangle_offsets))
    tris["id_a"], tris["id_b"], tris["id_c"] = b.ids[b.triangles].T
    xy = b.points[b.triangles].reshape(-1, 6)  # x0, y0, x1, y1, x2, y2
    for j in range(3):
        tris[f"x{j}"], tris[f"y{j}"] = xy[:, 2 * j], xy[:, 2 * j + 1]
    tris["area"], tris["change"], tris["flipped"] = b.area, b.area_change, b.flipped
    return SpanStrain(span, pairs, edges, tris)


def sliding_axis(fingertip_position: np.ndarray) -> int:
    """0 (x) or 1 (y): the axis along which the fingertip travelled furthest (the profile's axis)."""
    travel = np.ptp(fingertip_position, axis=0) if fingertip_position.shape[0] else np.zeros(2)
    return int(np.argmax(travel))


def stretch_profile(
    samples: Sequence[MotionSample],
    fingertip_displacement: np.ndarray,
    *,
    axis: int,
    positions: np.ndarray,
    strip_px: float,
):
    """Seed Figure 94: the change in stretch along ``axis`` averaged over every consecutive pair.

    A position is kept when at least a quarter of the pairs measured it, so a few pairs cannot make the average
    where the skin is seldom seen (the edge of the contact area, a dark band without features).
    """
    profiles = []
    for k, s in enumerate(samples):
        if axis == 1:
            s = MotionSample(s.frame_a, s.frame_b, s.points[:, ::-1], s.displacement[:, ::-1], s.ids)
            ft = fingertip_displacement[k][::-1]
        else:
            ft = fingertip_displacement[k]
        profiles.append(
            horizontal_stretch_profile(s, fingertip_displacement=ft, x_positions=positions, strip_width_px=strip_px)
        )
    return mean_profile(profiles, min_pairs=max(1, len(profiles) // 4))


def derive(
    m: MotionMeasurement,
    *,
    n_frames: int,
    image_shape: tuple[int, int],
    calibration: Calibration,
    params: AnalysisParams,
    profile_axis: int | None = None,
) -> dict[str, Any]:
    """Everything computed from the measured motion (seed 5.2-5.4)."""
    out: dict[str, Any] = {}
    spans = [int(s) for s in params.spans]

    def strain(span: int) -> SpanStrain:
        return span_strain(m.span_samples[span], span=span, max_edge_px=calibration.px(params.max_edge_mm))

    # The spans on threads, each one compiled call that releases the GIL, while this thread does the rest.
    with ThreadPoolExecutor(max_workers=max(1, min(len(spans), int(params.workers)))) as pool:
        strains = pool.map(strain, spans)
        ft = fingertip_motion(m.samples, n_frames=n_frames)
        out["fingertip"] = ft
        try:
            win = visibility_window(ft, image_shape=image_shape)
            out["window"] = win
        except InsufficientDataError as exc:
            win = None
            out["window_status"] = str(exc)
        axis = sliding_axis(ft.position) if profile_axis is None else int(profile_axis)
        length = image_shape[1] if axis == 0 else image_shape[0]
        step = calibration.px(params.profile_step_mm)
        positions = np.arange(step, length - step / 2, step)
        out["profile_axis"] = axis
        out["profile"] = stretch_profile(
            m.samples, ft.displacement, axis=axis, positions=positions,
            strip_px=calibration.px(params.profile_strip_mm),
        )
        if win is not None:
            out["movie"] = tactile_movie(
                m.samples, fingertip=ft, window=win, calibration=calibration, image_shape=image_shape,
                params=params.display, motion_axis=axis,
            )
        out["strain"] = dict(zip(spans, strains))
    return out


def without_glass_shading(frames, *, calibration: Calibration, params: AnalysisParams, surface: str | None):
    """Frames with the glass-fixed shading removed when asked (see :class:`AnalysisParams`), and what was done.

    All-black and saturated frames are left out of the statistics and passed on untouched (extraction flags them).
    A sequence in which the skin barely moved is passed on untouched, and the status says why.
    """
    from skinstretch.processing.extraction import ExtractionParams, frame_flags  # noqa: PLC0415
    from skinstretch.processing.glass_shading import glass_shading  # noqa: PLC0415

    use = params.glass_shading if params.glass_shading is not None else surface not in (None, "", "flat")
    if not use:
        return frames, "off" if params.glass_shading is False else f"off (surface {surface or 'unknown'})"
    checks = params.extraction or ExtractionParams()
    good = [k for k, f in enumerate(frames) if not frame_flags(f, checks)]
    try:  # InsufficientDataError: fewer than 2 usable frames, or skin that barely moved
        shading = glass_shading(
            frames,
            use=good,
            smooth_px=calibration.px(params.glass_shading_smooth_mm),
            along_shape_px=calibration.px(params.glass_shading_along_shape_mm),
            min_motion_ratio=params.glass_shading_min_motion,
        )
    except InsufficientDataError as exc:
        return frames, f"not applied: {exc}"
    return _ShadedFrames(frames, shading, good), f"applied (motion ratio {shading.motion_ratio:.2f})"


class _ShadedFrames(abc.Sequence):
    """The frames with the glass-fixed shading removed as each is read, in the thread that reads it: the analysis'
    extraction (or flow) threads, in parallel, instead of a serial pass over the sequence before them. Frames left
    out of the statistics (all black, saturated) are passed on untouched."""

    def __init__(self, frames: Sequence[np.ndarray], shading, good: Sequence[int]) -> None:
        self._frames = frames
        self._shading = shading
        self._good = np.zeros(len(frames), dtype=bool)
        self._good[list(good)] = True

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, k):
        from skinstretch.processing.glass_shading import remove_glass_shading  # noqa: PLC0415

        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        k = int(k)
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(f"frame {k} out of range for {len(self)} frames")
        frame = self._frames[k]
        return remove_glass_shading(frame, self._shading) if self._good[k] else frame


def surface_kind(metadata: dict) -> str | None:
    """The surface of a session's metadata: a simulated scene's "ridge", or a protocol's {"kind": "ridge", ...}."""
    surface = metadata.get("surface")
    if isinstance(surface, dict):
        surface = surface.get("kind")
    return str(surface) if surface else None


def _motion_table(samples: Sequence[MotionSample]) -> tuple[np.ndarray, np.ndarray]:
    pairs = np.zeros(len(samples), dtype=PAIR_DTYPE)
    parts = []
    for i, s in enumerate(samples):
        pairs[i] = (s.frame_a, s.frame_b, len(s), b"ok" if len(s) else b"no motion measured")
        t = np.zeros(len(s), dtype=MOTION_DTYPE)
        t["pair"] = i
        t["id"] = s.ids
        t["x"], t["y"] = s.points.T
        t["dx"], t["dy"] = s.displacement.T
        parts.append(t)
    return pairs, (np.concatenate(parts) if parts else np.zeros(0, MOTION_DTYPE))


def analyze_frames(
    frames: Sequence[np.ndarray],
    *,
    calibration: Calibration,
    method: str = "features",
    params: AnalysisParams | None = None,
    mapping=None,
    session_path: str = "",
    progress: bool = False,
    surface: str | None = None,
) -> Results:
    """The whole pipeline on frames in memory; :func:`analyze_session` wraps it for a session file.

    ``surface`` ("flat", "ridge", "valley", ...) decides the glass-shading step when ``params.glass_shading`` is None.
    """
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {METHODS}, got {method!r}")
    params = params or AnalysisParams()
    n = len(frames)
    if n < 2:
        raise InsufficientDataError(f"a session needs at least 2 frames to measure motion, got {n}")
    image_shape = tuple(int(v) for v in np.asarray(frames[0]).shape)
    t_start = time.perf_counter()
    frames, shading_status = without_glass_shading(frames, calibration=calibration, params=params, surface=surface)
    t_shading = time.perf_counter() - t_start
    measure = measure_features if method == "features" else measure_flow
    m = measure(frames, calibration=calibration, params=params, mapping=mapping, progress=progress)
    t0 = time.perf_counter()
    d = derive(m, n_frames=n, image_shape=image_shape, calibration=calibration, params=params)
    t_derive = time.perf_counter() - t0
    total = time.perf_counter() - t_start
    timing = dict(m.timing)
    timing.update({"glass_shading_s": t_shading, "derive_s": t_derive, "total_s": total,
                   "frames_per_s": n / total if total > 0 else float("nan")})
    pairs, motion = _motion_table(m.samples)
    ft = d["fingertip"]
    win = d.get("window")
    movie = d.get("movie")
    prof = d["profile"]
    flow_disp = flow_valid = gx = gy = None
    if m.flow_fields:
        gx, gy = m.flow_fields[0].grid_x, m.flow_fields[0].grid_y
        flow_disp = np.stack([np.nan_to_num(f.displacement, nan=0.0) for f in m.flow_fields]).astype(np.float32)
        flow_valid = np.stack([f.valid for f in m.flow_fields])
    return Results(
        method=method,
        session_path=session_path,
        n_frames=n,
        image_shape=image_shape,
        px_per_mm=calibration.px_per_mm,
        coordinates="image" if mapping is None else "rectified",
        frame_flags=m.frame_flags,
        motion_pairs=pairs,
        motion=motion,
        fingertip_displacement=ft.displacement,
        fingertip_valid=ft.valid,
        fingertip_position=ft.position,
        window={"x0": win.x0, "y0": win.y0, "x1": win.x1, "y1": win.y1} if win else {"status": d["window_status"]},
        window_centers=win.centers if win else None,
        strain=d["strain"],
        profile_axis=d["profile_axis"],
        profile_position=prof.x,
        profile_change=prof.change,
        profile_valid=prof.valid,
        tactile_positions_um=movie.positions_um if movie else None,
        tactile_reset=movie.reset if movie else None,
        tactile_clipped=movie.clipped if movie else None,
        tactile_stretch_change=movie.stretch_change if movie else None,
        timing=timing,
        params={**params.to_dict(), "glass_shading_status": shading_status, "parallel": m.parallel},
        versions=software_versions(),
        features=m.features,
        trajectories=m.trajectories,
        flow_grid_x=gx,
        flow_grid_y=gy,
        flow_displacement=flow_disp,
        flow_valid=flow_valid,
    )


def summarize(r: Results, results_path: Path) -> dict[str, Any]:
    """The small JSON summary written next to the results."""
    out: dict[str, Any] = {
        "results": str(results_path),
        "session": r.session_path,
        "method": r.method,
        "n_frames": r.n_frames,
        "coordinates": r.coordinates,
        "timing": r.timing,
        "glass_shading": r.params.get("glass_shading_status", "off"),
        "frames_flagged": int(sum(1 for f in r.frame_flags if f)),
        "fingertip_travel_px": np.ptp(r.fingertip_position, axis=0).tolist(),
        "profile_axis": "x" if r.profile_axis == 0 else "y",
        "window": r.window,
    }
    if r.trajectories is not None:
        lengths = r.trajectories["present"].sum(axis=0)
        out["n_trajectories"] = int(lengths.size)
        out["median_trajectory_frames"] = float(np.median(lengths)) if lengths.size else 0.0
    for span, s in r.strain.items():
        ok = s.pairs["status"] == b"ok"
        e = s.edges["change"]
        out[f"strain_span_{span}"] = {
            "pairs": int(s.pairs.size),
            "pairs_ok": int(ok.sum()),
            "edges": int(e.size),
            "edge_change_p5_p95": np.percentile(e, [5, 95]).tolist() if e.size else None,
        }
    return out


def analyze_session(
    session_path: str | Path,
    outdir: str | Path,
    *,
    method: str = "features",
    params: AnalysisParams | None = None,
    progress: bool = False,
) -> Path:
    """Analyze one session file into ``outdir`` (created); returns the path of ``results.h5``."""
    session_path = Path(session_path)
    outdir = Path(outdir)
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {METHODS}, got {method!r}")
    with open_session(session_path) as session:
        frames = session.read_frames()
        mapping = _mapping_of(session)
        calibration = Calibration(px_per_mm=session.calibration.px_per_mm, mapping=mapping)
        surface = surface_kind(session.metadata)
    r = analyze_frames(
        frames,
        calibration=calibration,
        method=method,
        params=params,
        mapping=mapping,
        session_path=str(session_path.resolve()),
        progress=progress,
        surface=surface,
    )
    outdir.mkdir(parents=True, exist_ok=True)
    path = write_results(outdir / "results.h5", r)
    (outdir / "summary.json").write_text(json.dumps(json_safe(summarize(r, path)), indent=2, default=json_default))
    return path
