"""The analysis of one session, start to end (seed chapters 4-5): frames in, a results file out.

``analyze_session(path, outdir)`` and ``analyze_frames(frames, calibration=...)`` both run :func:`analyze`:

1. frames are read from the session one at a time (:mod:`.frames`), with glass-fixed shading removed where asked
   for the motion measurement (features are extracted from the frames as recorded);
2. the method (:mod:`.methods`: features or flow behind one interface) measures the motion between consecutive
   frames in chunks on the run's executor (:mod:`.measure`): tracked features refined to sub-pixel, or the dense
   flow grid; everything after it is the one shared tail;
3. the motion is rectified to the skin once (when the session has a geometric mapping), written to the results
   file pair by pair, and the triangulation strain of every span is computed in batches as pairs arrive; the
   feature method's trajectories are stored as the tracker is done with each frame and built at the end, a block
   of frames at a time (:mod:`.trajectories`), and the motion follows from them;
4. the motion and strain of every frame relative to the reference frame (the first with measured points) follow
   (:mod:`.cumulative`): from the stored trajectories, or, for the flow, from each field composed onto the
   reference one and registered from the reference frame directly as the fields arrive;
5. fingertip motion, visibility window, stretch profile and tactile movie are derived from the stored motion, read
   back (:mod:`.derive`), the movie written a block of frames at a time, and the file is closed as ``results.h5``
   (``docs/results-format.md``).

Memory does not grow with the session beyond a few numbers per frame (flags, fingertip, window) and per track:
everything else is written as soon as it is final and read back when a later step needs it (the bench section
``scale`` measures it).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import Executor, Future
from concurrent.futures.process import BrokenProcessPool
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from skinstretch.drivers.disk_space import is_disk_full
from skinstretch.drivers.errors import DiskFullError
from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.analysis.derive import (
    Derived, PixelScales, derive, motion_rows, span_strain, tactile_movie_blocks,
)
from skinstretch.experiments.analysis.density import mesh_density
from skinstretch.experiments.analysis.executor import InlineExecutor, make_executor
from skinstretch.experiments.analysis.frames import (
    ArrayFrames,
    FrameReader,
    FrameSource,
    SessionFrames,
    estimate_shading,
)
from skinstretch.experiments.analysis.methods import Outputs, measurement_method
from skinstretch.experiments.analysis.parameters import METHODS, AnalysisParams, analysis_params
from skinstretch.experiments.analysis.plan import AnalysisPlan, plan_analysis, refuse_unfit_clip
from skinstretch.experiments.analysis.percentiles import StreamedPercentiles
from skinstretch.experiments.codec_error import CodecError
from skinstretch.experiments.json_encoding import json_default, json_safe
from skinstretch.experiments.provenance import software_versions
from skinstretch.experiments.results_file import (
    EDGE_DTYPE, MOTION_DTYPE, PAIR_DTYPE, TRIANGLE_DTYPE, PairStatus, Results, ResultsWriter,
    check_results_dir,
)
from skinstretch.experiments.output_paths import REPLACE_IT, check_output_file, hold_output_dir
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.display_mapping import TactileMovie
from skinstretch.processing.tracking import MotionSample

__all__ = ["analyze", "analyze_frames", "analyze_session", "summarize", "surface_kind", "STRAIN_BATCH_PAIRS"]

log = logging.getLogger(__name__)

#: A displacement whose median predicted standard error exceeds this (px) is warned about: beyond the accuracy the
#: measurement is for (the bench's displacement target).
MEANINGFUL_SIGMA_PX = 0.05
#: The same for the longest span's edge strain (a fraction): the bench's 11-frame edge-strain target.
MEANINGFUL_EDGE_SIGMA = 0.002
#: More than this fraction of the displacements without a bound (windows not matching after the measured motion:
#: a trajectory that jumped, a texture the registration cannot follow) is warned about.
MAX_UNBOUNDED_FRACTION = 0.05
#: Pairs of one span triangulated in one task (one compiled call).
STRAIN_BATCH_PAIRS = 128


class _StrainTables:
    """The strain of every span, computed in batches on the executor as pairs arrive and written in pair order; each
    span's edge changes also go to a :class:`StreamedPercentiles` (the summary's percentiles);
    ``shared_sigma_px``: the part of the points' errors neighbours share (:func:`.derive.span_strain`)."""

    def __init__(self, writer: ResultsWriter, executor: Executor, spans: Sequence[int], max_edge_px: float,
                 stack: ExitStack, min_spacing_px: float = 0.0, shared_sigma_px: float = 0.0) -> None:
        self.writer, self.executor, self.max_edge_px = writer, executor, max_edge_px
        self.min_spacing_px, self.shared_sigma_px = min_spacing_px, shared_sigma_px
        self.buffers: dict[int, list[MotionSample]] = {int(s): [] for s in spans}
        self.done: dict[int, int] = {int(s): 0 for s in spans}  # pairs submitted per span
        self.pending: deque[tuple[int, Future, list, dict]] = deque()
        self.ok: dict[int, int] = {int(s): 0 for s in spans}
        self.edge_change = {int(s): stack.enter_context(StreamedPercentiles(scratch_dir=writer.scratch_dir))
                            for s in spans}
        self.change_sigma = {int(s): _SigmaSpread(writer, stack) for s in spans}
        self.doubted = {int(s): _Doubts() for s in spans}
        self.regularisation: dict[int, Any] = {}  # per span, a dense registration's (its errors' correlation)

    def add(self, span: int, sample: MotionSample) -> None:
        buf = self.buffers[span]
        buf.append(sample)
        if len(buf) >= STRAIN_BATCH_PAIRS:
            self._submit(span)

    def _submit(self, span: int) -> None:
        buf = self.buffers[span]
        if not buf:
            return
        self.buffers[span] = []
        kwargs = dict(span=span, max_edge_px=self.max_edge_px, first_pair=self.done[span],
                      min_spacing_px=self.min_spacing_px, regularisation=self.regularisation.get(span),
                      shared_sigma_px=self.shared_sigma_px)
        fut = self.executor.submit(span_strain, buf, **kwargs)
        self.done[span] += len(buf)
        self.pending.append((span, fut, buf, kwargs))
        while len(self.pending) > 4:  # keep a few batches in flight, write the rest
            self._write_next()

    def _write_next(self) -> None:
        span, fut, buf, kwargs = self.pending.popleft()
        try:
            s = fut.result()
        except (BrokenProcessPool, OSError) as exc:  # the workers died: this process carries on (as measure does)
            log.warning("worker processes failed (%s); the strain is computed in this process", exc)
            self.executor = InlineExecutor()
            s = span_strain(buf, **kwargs)
        g = f"strain/span_{span}"
        self.writer.append(f"{g}/pairs", s.pairs)
        self.writer.append(f"{g}/edges", s.edges)
        self.writer.append(f"{g}/triangles", s.triangles)
        self.writer.file[g].attrs["span"] = span
        self.ok[span] += int(np.sum(s.pairs["status"] == PairStatus.OK))
        self.edge_change[span].add(s.edges["change"])
        self.change_sigma[span].add(s.edges["change_sigma"])
        self.doubted[span].add(s.pairs)

    def finish(self) -> None:
        for span in self.buffers:
            self._submit(span)
        while self.pending:
            self._write_next()
        for span in self.buffers:  # a span longer than the session: an empty table says so
            g = f"strain/span_{span}"
            if g not in self.writer.file:
                for name, dtype in (("pairs", PAIR_DTYPE), ("edges", EDGE_DTYPE), ("triangles", TRIANGLE_DTYPE)):
                    self.writer.append(f"{g}/{name}", np.zeros(0, dtype))
                self.writer.file[g].attrs["span"] = span


class _SigmaSpread:
    """The standard errors of a table, streamed: median and 95th percentile of the finite ones, and how many are
    infinite (no bound: windows that do not match after the motion, or no window)."""

    def __init__(self, writer: ResultsWriter, stack: ExitStack) -> None:
        self.values = stack.enter_context(StreamedPercentiles(scratch_dir=writer.scratch_dir))
        self.unbounded = 0

    def add(self, sigma: np.ndarray) -> None:
        self.values.add(sigma[np.isfinite(sigma)])
        self.unbounded += int(np.count_nonzero(np.isposinf(sigma)))

    def to_dict(self) -> dict[str, float] | None:
        if not self.values.count:
            return None
        median, p95 = self.values.percentiles([50, 95])
        return {"median": median, "p95": p95, "unbounded": self.unbounded,
                "unbounded_fraction": self.unbounded / (self.values.count + self.unbounded)}


class _Doubts:
    """The pairs a self-check doubted (PairStatus.DOUBTED): how many, and the first one's frames and reason."""

    def __init__(self) -> None:
        self.count = 0
        self.first: tuple[int, int, str] | None = None

    def add(self, pairs: np.ndarray) -> None:
        doubted = pairs[pairs["status"] == PairStatus.DOUBTED]
        if doubted.size and self.first is None:
            p = doubted[0]
            self.first = (int(p["frame_a"]), int(p["frame_b"]), p["reason"].decode(errors="replace"))
        self.count += int(doubted.size)

    def describe(self, total: int, what: str) -> str | None:
        """One warning line, or None when no pair was doubted."""
        if not self.count or self.first is None:
            return None
        a, b, reason = self.first
        return (f"{self.count} of {total} {what} failed a self-check and are not reported as ok (first: frames "
                f"{a}-{b}: {reason})")


class _MotionTable:
    """The consecutive pairs' motion, written a batch of pairs at a time."""

    def __init__(self, writer: ResultsWriter, stack: ExitStack) -> None:
        self.writer = writer
        self.block: list[MotionSample] = []
        self.written = 0
        self.sigma = _SigmaSpread(writer, stack)
        self.doubted = _Doubts()

    def add(self, sample: MotionSample) -> None:
        self.block.append(sample)
        if len(self.block) == STRAIN_BATCH_PAIRS:
            self.flush()

    def flush(self) -> None:
        if self.block:
            pairs, rows = motion_rows(self.block, first_pair=self.written)
            self.writer.append("motion_pairs", pairs)
            self.writer.append("motion", rows)
            self.sigma.add(rows["sigma"])
            self.doubted.add(pairs)
            self.written += len(self.block)
            self.block = []


def analyze(
    source: FrameSource | Sequence[np.ndarray] | np.ndarray,
    *,
    calibration: Calibration,
    method: str = "features",
    params: AnalysisParams | dict | None = None,
    executor: Executor | None = None,
    mapping=None,
    results_path: str | Path | None = None,
    session_path: str = "",
    surface: str | None = None,
    progress: bool = False,
    overwrite: bool = False,
    source_notes: Sequence[str] = (),
    lossy_source: bool = False,
    codec_error: CodecError | None = None,
) -> Results:
    """Analyse ``source`` (a session's :class:`FrameSource`, or frames in memory) into ``results_path`` (None: a
    results file in memory; an existing file is refused unless ``overwrite``) and return it opened.
    ``source_notes``: what the summary's ``notes`` should say about where the frames came from
    (:func:`notes_on_source`); ``lossy_source``: the frames went through lossy video compression, whose error the
    predicted standard errors then include (the plan's): ``codec_error`` as the import measured it
    (:func:`source_codec_error`).

    ``executor`` is the run's (:func:`~skinstretch.experiments.analysis.executor.make_executor`); None makes one from
    ``params.execution`` for this analysis alone. ``surface`` ("flat", "ridge", "valley", ...) enters the
    :class:`~skinstretch.experiments.analysis.plan.AnalysisPlan`, resolved once before the measurement: the
    pipeline executes the plan and makes no choice of its own.
    """
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {METHODS}, got {method!r}")
    if results_path is not None:
        check_output_file(results_path, overwrite=overwrite, remedy=REPLACE_IT)
    params = analysis_params(params)
    if not isinstance(source, FrameSource):
        source = ArrayFrames(source)
    n = len(source)
    refuse_unfit_clip(params, n, method)
    for note in source_notes:
        log.warning("%s", note)
    image_shape = tuple(int(v) for v in source.shape)
    scales = PixelScales.of(calibration, params.strain)
    spans = [int(s) for s in params.strain.spans]
    with ExitStack() as stack:
        if executor is None:
            executor = stack.enter_context(make_executor(params.execution))
        t_start = time.perf_counter()
        shading, shading_status = estimate_shading(source, calibration=calibration, params=params, surface=surface)
        plan = plan_analysis(params, method=method, n_frames=n, surface=surface, shading_removed=shading is not None,
                             shading_status=shading_status, lossy_source=lossy_source,
                             codec_error=codec_error)
        params = plan.params
        notes = [*source_notes, *plan.notes]
        reader = FrameReader(source, shading)
        t_shading = time.perf_counter() - t_start
        writer = stack.enter_context(ResultsWriter(results_path))
        flags = [""] * n
        strain = _StrainTables(writer, executor, spans, scales.max_edge_px, stack, scales.min_spacing_px,
                               plan.shared_sigma_px)
        motion = _MotionTable(writer, stack)
        cumulative = _CumulativeTable(writer, scales, plan.shared_sigma_px)

        out = Outputs(writer=writer, motion=motion, strain=strain, cumulative=cumulative, flags=flags,
                      calibration=calibration, mapping=mapping, spans=spans, executor=executor, stack=stack,
                      progress=progress)
        measurement = measurement_method(method)
        m = measurement.measure(reader, n=n, params=params, plan=plan, out=out)
        timing, parallel = dict(m.timing), m.parallel
        t0 = time.perf_counter()
        strain.finish()
        for sample in measurement.cumulative_samples(n=n, params=params, out=out):
            cumulative.add(sample)
        cumulative.finish()
        timing["cumulative_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        samples = writer.samples()
        d = derive(samples, n_frames=n, image_shape=image_shape, scales=scales)
        _write_derived(writer, d, flags)
        for movie in tactile_movie_blocks(samples, d, calibration=calibration, image_shape=image_shape,
                                          display_params=params.display):
            _append_movie(writer, movie)
        if d.window is not None:
            writer.file["tactile_movie"].attrs["motion_axis"] = d.profile_axis
        timing["derive_s"] = time.perf_counter() - t0
        total = time.perf_counter() - t_start
        timing.update({"glass_shading_s": t_shading, "total_s": total, "frames_per_s": n / total if total > 0 else 0.0})
        attrs = {
            "method": method,
            "session_path": session_path,
            "n_frames": n,
            "image_shape": np.asarray(image_shape, dtype=np.int64),
            "px_per_mm": float(calibration.px_per_mm),
            "coordinates": "image" if mapping is None else "rectified",
            "timing_json": json.dumps(timing),
            "params_json": json.dumps({**params.to_dict(), "glass_shading_status": shading_status,
                                       "parallel": parallel}),
            "plan_json": json.dumps(plan.to_dict()),
            "versions_json": json.dumps(software_versions()),
            "window_json": json.dumps({"x0": d.window.x0, "y0": d.window.y0, "x1": d.window.x1, "y1": d.window.y1}
                                      if d.window is not None else {"status": d.window_status}),
        }
        writer.file.attrs.update(attrs)
        summary = summarize(writer, d, strain, n_frames=n, results_path=results_path, session_path=session_path,
                            method=method, timing=timing, shading_status=shading_status, flags=flags, notes=notes,
                            motion=motion, plan=plan)
        for warning in summary["warnings"][1 if summary["density"].get("too_sparse") else 0:]:
            log.warning("%s", warning)  # (the density's was logged where it was found)
        attrs["summary_json"] = json.dumps(json_safe(summary), default=json_default)
        return writer.finish(attrs)


class _CumulativeTable:
    """The motion and strain of every frame relative to the reference frame (:mod:`.cumulative`), written a batch
    of frames at a time; empty tables (reference_frame -1) when no frame had 3 measured points."""

    def __init__(self, writer: ResultsWriter, scales: PixelScales, shared_sigma_px: float = 0.0) -> None:
        self.writer, self.scales, self.shared_sigma_px = writer, scales, shared_sigma_px
        self.batch: list[MotionSample] = []
        self.written = 0
        self.reference = -1

    def add(self, sample: MotionSample) -> None:
        self.reference = int(sample.frame_a)
        self.batch.append(sample)
        if len(self.batch) == STRAIN_BATCH_PAIRS:
            self._flush()

    def _flush(self) -> None:
        w, batch = self.writer, self.batch
        s = span_strain(batch, span=0, max_edge_px=self.scales.max_edge_px, first_pair=self.written,
                        min_spacing_px=self.scales.min_spacing_px, shared_sigma_px=self.shared_sigma_px)
        w.append("cumulative/pairs", s.pairs)
        w.append("cumulative/motion", motion_rows(batch, first_pair=self.written)[1])
        w.append("cumulative/edges", s.edges)
        w.append("cumulative/triangles", s.triangles)
        self.written += len(batch)
        self.batch = []

    def finish(self) -> None:
        if self.batch:
            self._flush()
        if self.written == 0:
            for name, dtype in (("pairs", PAIR_DTYPE), ("motion", MOTION_DTYPE), ("edges", EDGE_DTYPE),
                                ("triangles", TRIANGLE_DTYPE)):
                self.writer.append(f"cumulative/{name}", np.zeros(0, dtype))
        self.writer.file["cumulative"].attrs["reference_frame"] = self.reference


def _write_derived(w: ResultsWriter, d: Derived, flags: list[str]) -> None:
    w.array("frame_flags", np.array([s.encode() for s in flags], dtype="S128"))
    ft = d.fingertip
    w.array("fingertip/displacement", ft.displacement)
    w.array("fingertip/n_points", ft.n_features)
    w.array("fingertip/valid", ft.valid)
    w.array("fingertip/position", ft.position)
    if d.window is not None:
        w.array("window_centers", d.window.centers)
    w.array("profile/position", d.profile.x)
    w.array("profile/change", d.profile.change)
    w.array("profile/valid", d.profile.valid)
    w.file["profile"].attrs["axis"] = d.profile_axis


def _append_movie(w: ResultsWriter, movie: TactileMovie) -> None:
    """The next block of frames of the tactile movie."""
    w.append_array("tactile_movie/positions_um", movie.positions_um)
    w.append_array("tactile_movie/reset", movie.reset)
    w.append_array("tactile_movie/clipped", movie.clipped)
    w.append_array("tactile_movie/stretch_change", movie.stretch_change)


def _warnings(motion: _MotionTable, strain: _StrainTables, uncertainty: dict[str, Any],
              density: dict[str, Any]) -> list[str]:
    """The lines a user must read before trusting the numbers: a mesh too sparse to map strain (logged where it is
    found), pairs a self-check doubted, and a predicted error beyond what the measurement is for (the bench's
    displacement and edge-strain targets)."""
    out = [density.get("warning") if density.get("too_sparse") else None,
           motion.doubted.describe(motion.written, "consecutive frame pairs")]
    out += [strain.doubted[span].describe(strain.done[span], f"{span}-frame spans")
            for span in strain.buffers if span > 1]
    disp = uncertainty.get("displacement_sigma_px")
    if disp is not None and not disp["median"] <= MEANINGFUL_SIGMA_PX:
        out.append(f"the displacements' predicted error is {disp['median']:.3g} px (median standard error), above "
                   f"{MEANINGFUL_SIGMA_PX} px: the frames' texture or noise limit this measurement")
    if disp is not None and disp.get("unbounded_fraction", 0.0) > MAX_UNBOUNDED_FRACTION:
        out.append(f"{100 * disp['unbounded_fraction']:.0f} % of the displacements do not match after their measured "
                   "motion (no error bound): trajectories that jumped, or a texture the registration cannot follow")
    span = max(strain.buffers)
    edges = uncertainty.get(f"edge_change_sigma_span_{span}")
    if edges is not None and not edges["median"] <= MEANINGFUL_EDGE_SIGMA:
        out.append(f"the {span}-frame edge strain's predicted error is {100 * edges['median']:.2g} % (median "
                   f"standard error), above {100 * MEANINGFUL_EDGE_SIGMA:.1f} %: the points are too few, too close "
                   "or too uncertain for strain at this scale")
    return [w for w in out if w]


def summarize(writer: ResultsWriter, d: Derived, strain: _StrainTables, *, n_frames: int, results_path,
              session_path: str, method: str, timing: dict, shading_status: str, flags: list[str],
              notes: list[str] = (), motion: _MotionTable | None = None,
              plan: AnalysisPlan | None = None) -> dict[str, Any]:
    """The small JSON summary written next to the results (and into them); ``notes``: what the clip's length changed
    and a shape's shading left in (the plan's); ``plan``: the analysis plan executed
    (:meth:`~skinstretch.experiments.analysis.plan.AnalysisPlan.to_dict`); ``warnings``: what a user must read before
    trusting the numbers (self-checks failed, a large predicted error)."""
    f = writer.file
    out: dict[str, Any] = {
        "results": str(results_path) if results_path is not None else "(in memory)",
        "session": session_path,
        "method": method,
        "n_frames": n_frames,
        "coordinates": str(f.attrs["coordinates"]),
        "timing": timing,
        "glass_shading": shading_status,
        "frames_flagged": int(sum(1 for s in flags if s)),
        "fingertip_travel_px": np.ptp(d.fingertip.position, axis=0).tolist(),
        "profile_axis": d.profile_axis,
        "window": json.loads(str(f.attrs["window_json"])),
        "min_track_frames": json.loads(str(f.attrs["params_json"]))["tracking"]["min_length_frames"]
        if method == "features" else None,
        "notes": list(notes),
        "plan": plan.to_dict() if plan is not None else None,
    }
    if "tracks" in f:
        lengths = f["tracks"].fields("n_frames")[()]
        out["n_trajectories"] = int(lengths.size)
        out["median_trajectory_frames"] = float(np.median(lengths)) if lengths.size else 0.0
    out["density"] = mesh_density(f, method=method, n_frames=n_frames, px_per_mm=float(f.attrs["px_per_mm"]),
                                  spans=list(strain.buffers), max_edge_px=strain.max_edge_px,
                                  window=out["min_track_frames"]).to_dict()
    uncertainty: dict[str, Any] = {}
    if motion is not None:
        uncertainty["displacement_sigma_px"] = motion.sigma.to_dict()
    for span in strain.buffers:
        g = f[f"strain/span_{span}"]
        changes = strain.edge_change[span]
        out[f"strain_span_{span}"] = {
            "pairs": int(g["pairs"].shape[0]),
            "pairs_ok": strain.ok[span],
            "pairs_doubted": strain.doubted[span].count,
            "edges": int(g["edges"].shape[0]),
            "edge_change_p5_p95": changes.percentiles([5, 95]) if changes.count else None,
        }
        uncertainty[f"edge_change_sigma_span_{span}"] = strain.change_sigma[span].to_dict()
    out["uncertainty"] = uncertainty
    out["warnings"] = _warnings(motion, strain, uncertainty, out["density"]) if motion is not None else []
    return out


def surface_kind(metadata: dict) -> str | None:
    """The surface of a session's metadata: a simulated scene's "ridge", or a protocol's {"kind": "ridge", ...}."""
    surface = metadata.get("surface")
    if isinstance(surface, dict):
        surface = surface.get("kind")
    return str(surface) if surface else None


def source_is_lossy(metadata: dict) -> bool:
    """The session's frames were imported from a lossy file (:mod:`skinstretch.experiments.frame_import` records
    ``source.lossy``)."""
    source = metadata.get("source")
    return isinstance(source, dict) and source.get("lossy") is True


def source_codec_error(metadata: dict) -> CodecError | None:
    """The lossy codec's displacement error the import measured (``source.codec_error``); None when not recorded or
    not a pair of finite, non-negative errors."""
    source = metadata.get("source")
    found = source.get("codec_error") if isinstance(source, dict) else None
    if not isinstance(found, dict):
        return None
    values = [found.get("sigma_px"), found.get("independent_px")]
    if not all(isinstance(v, (int, float)) and math.isfinite(v) and v >= 0 for v in values):
        return None
    sigma = float(values[0])
    return CodecError(sigma_px=sigma, independent_px=min(float(values[1]), sigma), how=str(found.get("how", "")),
                      n_points=int(found.get("n_points") or 0))


def notes_on_source(metadata: dict) -> list[str]:
    """What a session's metadata says its frames lost before the analysis: imported from a lossy file."""
    if source_is_lossy(metadata):
        return [f"the frames were imported from lossy compression ({metadata['source'].get('compression') or 'unknown'}"
                "): the motion measured departs from what the camera's own frames give (docs/import-and-replay.md, "
                "Accuracy)"]
    return []



#: The pipeline on frames in memory (a list of 2-D uint8 arrays or an (N, H, W) array): :func:`analyze`, whose
#: results stay in memory unless ``results_path`` is given.
analyze_frames = analyze


def analyze_session(
    session_path: str | Path,
    outdir: str | Path,
    *,
    method: str = "features",
    params: AnalysisParams | dict | None = None,
    executor: Executor | None = None,
    progress: bool = False,
    overwrite: bool = False,
) -> Results:
    """Analyse one session file into ``outdir`` (created): ``results.h5`` and ``summary.json``; returns the results.

    Frames are read from the file as they are measured, so a session of any length fits in memory. An ``outdir``
    that holds results already is refused (before anything is analysed) unless ``overwrite``, and so is one
    another analysis is writing into (:func:`~skinstretch.experiments.output_paths.hold_output_dir`)."""
    with hold_output_dir(outdir, holder=f"an analysis of {Path(session_path).name}"):
        return _analyze_session_held(session_path, outdir, method=method, params=params, executor=executor,
                                     progress=progress, overwrite=overwrite)


def _analyze_session_held(session_path, outdir, *, method, params, executor, progress, overwrite) -> Results:
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {METHODS}, got {method!r}")
    session_path, outdir = Path(session_path), Path(outdir)
    with open_session(session_path) as session:
        check_results_dir(outdir, overwrite=overwrite)
        mapping = None
        if session.mapping_json:
            from skinstretch.processing.geometric_calibration import mapping_from_dict  # noqa: PLC0415

            mapping = mapping_from_dict(json.loads(session.mapping_json))
        calibration = Calibration(px_per_mm=session.calibration.px_per_mm, mapping=mapping)
        surface = surface_kind(session.metadata)
        notes = notes_on_source(session.metadata) + session.timestamp_faults()
        lossy = source_is_lossy(session.metadata)
        codec = source_codec_error(session.metadata) if lossy else None
    source = SessionFrames(session_path)
    outdir.mkdir(parents=True, exist_ok=True)
    try:
        r = analyze(source, calibration=calibration, method=method, params=params, executor=executor,
                    mapping=mapping, results_path=outdir / "results.h5", session_path=str(session_path.resolve()),
                    surface=surface, progress=progress, overwrite=overwrite, source_notes=notes, lossy_source=lossy,
                    codec_error=codec)
        (outdir / "summary.json").write_text(json.dumps(json_safe(r.summary), indent=2, default=json_default))
    except (OSError, RuntimeError) as exc:
        if not is_disk_full(exc):
            raise
        raise DiskFullError(f"{outdir}: disk full while writing the analysis there (the session file is untouched)"
                            ) from None
    finally:
        source.close()
    return r

