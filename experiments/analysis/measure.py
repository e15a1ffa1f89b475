"""Measuring motion between frames, chunk by chunk on the run's executor: tracked features or the dense flow.

Both methods cut the session into chunks of consecutive frames, submit them to the executor they are given
(:mod:`skinstretch.experiments.analysis.executor`) a few at a time, and hand each chunk's result on in frame order
as it arrives, so no more than a few chunks are ever in memory.

Features (seed 4, 5.1): each chunk is extracted, matched and refined by its own tracker, and the chunks are joined
in order. A chunk after the first starts ``overlap`` frames early: its tracker has then seen the same recent frames
as the previous chunk's at the join, and when the two agree on them bit for bit
(:meth:`skinstretch.processing.tracking.FeatureTracker.continue_with`) the later frames are exactly those one
sequential tracker would have produced. When they do not agree (rare: a relinked feature whose history starts
before the overlap), this process tracks that chunk's frames itself from the features the chunk extracted: the
result is the sequential one either way, whatever the executor (the tests check it). The joined tracker hands its
frames on as soon as matching is done with them (:meth:`~skinstretch.processing.tracking.FeatureTracker.take_frames`)
for the caller to store: it never holds more than a few chunks' records.

Flow: each chunk computes the fields of its consecutive pairs (:meth:`DenseFlow.compute_sequence`), the same as
pair by pair.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, Future
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from typing import Any


from skinstretch.experiments.analysis.executor import InlineExecutor, describe_executor, executor_width
from skinstretch.experiments.analysis.frames import FrameReader
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.progress import progress_bar

__all__ = ["chunk_plan", "measure_features", "measure_flow", "make_tracker", "make_extractor", "MeasurementRun",
           "MAX_CHUNK_FRAMES", "MIN_FRAMES"]

log = logging.getLogger(__name__)

#: Longest chunk: bounded memory (a chunk's feature tables, a chunk's flow fields) and a progress bar that moves.
MAX_CHUNK_FRAMES = 240
#: Shorter sessions are measured in one chunk in the caller: handing frames to workers costs more than it saves.
MIN_FRAMES = 32
#: Frames a worker extracts in one task when this process tracks (:func:`chunks_can_join` False): short, so that
#: tracking starts early and follows the workers closely.
EXTRACTION_CHUNK_FRAMES = 24


def chunk_plan(n_frames: int, *, width: int, overlap: int) -> list[tuple[int, int]]:
    """(first, last) frame of each chunk, inclusive; chunk j > 0 starts ``overlap`` frames before chunk j-1 ends.

    At least ``width`` chunks (the executor's parallelism) and none longer than about :data:`MAX_CHUNK_FRAMES`, all
    about the same length (overlaps included); one chunk for fewer than :data:`MIN_FRAMES` frames or when chunks
    would be shorter than ``2 * overlap + 2`` frames.
    """
    m = max(int(width), math.ceil(n_frames / MAX_CHUNK_FRAMES))
    if n_frames < MIN_FRAMES:
        m = 1
    while m >= 2:
        size = (n_frames + (m - 1) * overlap) / m  # frames per chunk, overlaps included
        if size >= 2 * overlap + 2:
            break
        m -= 1
    if m < 2:
        return [(0, n_frames - 1)]
    plan, first = [], 0
    for j in range(m):
        last = n_frames - 1 if j == m - 1 else int(round((j + 1) * size - j * overlap)) - 1
        plan.append((first, last))
        first = last - overlap
    return plan


def _in_order(executor: Executor, tasks: Sequence[tuple[Callable, tuple]], *, ahead: int) -> Iterator[tuple[int, Any]]:
    """Submit ``tasks`` (function, args) at most ``ahead`` at a time and yield (index, result) in order. A task
    whose worker process died, or that a worker could not run (an OS error), is run again here, and so is every
    later one: the analysis carries on in this process (logged)."""
    inline = InlineExecutor()
    pending: dict[int, Future] = {}
    broken = False

    def submit(j: int) -> None:
        fn, args = tasks[j]
        pending[j] = (inline if broken else executor).submit(fn, *args)

    try:
        for j in range(min(ahead, len(tasks))):
            submit(j)
        for j in range(len(tasks)):
            try:
                result = pending.pop(j).result()
            except (BrokenProcessPool, OSError) as exc:
                if not broken:
                    log.warning("worker processes failed (%s); the analysis carries on in this process", exc)
                broken = True
                fn, args = tasks[j]
                result = fn(*args)
            if j + ahead < len(tasks):
                submit(j + ahead)
            yield j, result
    finally:
        for fut in pending.values():
            fut.cancel()


# -- features ----------------------------------------------------------------------------------------------------


def make_tracker(calibration: Calibration, params) -> Any:
    """The analysis' :class:`~skinstretch.processing.tracking.FeatureTracker` for ``params`` (AnalysisParams)."""
    from skinstretch.processing.displacement_refinement import SubpixelRefiner  # noqa: PLC0415
    from skinstretch.processing.global_motion import GlobalMotionEstimator  # noqa: PLC0415
    from skinstretch.processing.tracking import FeatureTracker  # noqa: PLC0415

    return FeatureTracker(
        calibration=calibration,
        params=params.tracking,
        refiner=SubpixelRefiner(calibration=calibration, params=params.subpixel) if params.subpixel else None,
        motion_estimator=(GlobalMotionEstimator(downsample=calibration.resolvable_reduction(4))
                          if params.robust_matching else None),
    )


def make_extractor(calibration: Calibration, params) -> Any:
    from skinstretch.processing.extraction import FeatureExtractor  # noqa: PLC0415

    return FeatureExtractor(calibration=calibration, params=params.extraction)


@dataclass
class ChunkTracking:
    """One chunk tracked from its first frame: the tracker after it, each frame's features and flags, seconds."""

    first: int
    tracker: Any
    tables: list
    flags: list
    timing: dict = field(default_factory=dict)


def track_chunk(reader: FrameReader, first: int, last: int, calibration: Calibration, params) -> ChunkTracking:
    """Extract, match and refine frames ``first..last`` with a new tracker (runs in a worker)."""
    extractor, tracker = make_extractor(calibration, params), make_tracker(calibration, params)
    tables, flags = [], []
    t_extract = t_prepare = t_track = 0.0
    for k in range(first, last + 1):
        t0 = time.perf_counter()
        recorded, image = reader.pair(k)  # features from the frame as recorded, motion on the shading-free one
        res = extractor.extract(recorded, frame_index=k)
        t1 = time.perf_counter()
        prepared = tracker.prepare_image(image)
        t2 = time.perf_counter()
        feats = res.features if res.ok else res.features[:0]
        tracker.add_frame(feats, prepared=prepared)
        t_track += time.perf_counter() - t2
        t_extract += t1 - t0
        t_prepare += t2 - t1
        tables.append(feats)
        flags.append(",".join(sorted(res.flags)))
    return ChunkTracking(first, tracker, tables, flags,
                         {"extraction_s": t_extract, "image_prep_s": t_prepare, "tracking_s": t_track})


@dataclass
class ChunkExtraction:
    """One chunk's features and flags, extracted in a worker (tracked by the caller), and its seconds."""

    first: int
    tables: list
    flags: list
    seconds: float


def extract_chunk(reader: FrameReader, first: int, last: int, calibration: Calibration, params) -> ChunkExtraction:
    """Extract the features of frames ``first..last`` as recorded (runs in a worker)."""
    extractor = make_extractor(calibration, params)
    tables, flags = [], []
    t0 = time.perf_counter()
    for k in range(first, last + 1):
        res = extractor.extract(reader.pair(k)[0], frame_index=k)
        tables.append(res.features if res.ok else res.features[:0])
        flags.append(",".join(sorted(res.flags)))
    return ChunkExtraction(first, tables, flags, time.perf_counter() - t0)


def chunks_can_join(params) -> bool:
    """Whether chunks tracked apart can be joined (:meth:`FeatureTracker.continue_with`): not when a point may be
    followed by registration alone without end (``max_bridge_frames`` None with a refiner, the analysis' default),
    which outlives any overlap, so that nearly every join is refused and its frames tracked again."""
    return params.subpixel is None or params.tracking.max_bridge_frames is not None


@dataclass
class MeasurementRun:
    """Seconds per stage, and how the measurement ran (chunks, workers)."""

    timing: dict[str, float]
    parallel: str


def measure_features(
    reader: FrameReader,
    *,
    n_frames: int,
    calibration: Calibration,
    params,
    executor: Executor,
    on_frames: Callable[[int, list, list], None],
    on_tracked: Callable[[list], None],
    progress: bool = False,
) -> MeasurementRun:
    """Track every frame in chunks on ``executor``; ``on_frames(first, tables, flags)`` receives each run of
    frames' feature tables and flags in frame order, once (the caller writes them out), and ``on_tracked(frames)``
    the tracked frames (:class:`~skinstretch.processing.tracking.TrackedFrame`) in frame order, each once, as soon
    as the tracker is done with them (the caller stores them: the trajectories are built at the end)."""
    from skinstretch.processing.tracking import join_overlap_frames  # noqa: PLC0415

    overlap = join_overlap_frames(params.tracking)  # the least FeatureTracker.continue_with accepts
    width = executor_width(executor)
    plan = chunk_plan(n_frames, width=width, overlap=overlap)
    here = len(plan) == 1
    if not here and not chunks_can_join(params):
        return _extract_apart_track_here(reader, n_frames=n_frames, calibration=calibration, params=params,
                                         executor=executor, on_frames=on_frames, on_tracked=on_tracked,
                                         progress=progress)
    run_on = InlineExecutor() if here else executor
    tasks = [(track_chunk, (reader.part(a, b) if not here else reader, a, b, calibration, params)) for a, b in plan]
    tracker = None
    timing = {"extraction_s": 0.0, "image_prep_s": 0.0, "tracking_s": 0.0}
    retracked = 0
    bar = progress_bar(n_frames, enabled=progress, desc="features")
    try:
        for j, r in _in_order(run_on, tasks, ahead=width + 1):
            for k, v in r.timing.items():
                timing[k] += v
            if tracker is None:
                tracker = r.tracker
                own = slice(0, None)
            else:
                own = slice(overlap + 1, None)
                t0 = time.perf_counter()
                if not tracker.continue_with(r.tracker, overlap=overlap):
                    retracked += 1
                    for k, feats in enumerate(r.tables[own], start=r.first + overlap + 1):
                        tracker.add_frame(feats, prepared=tracker.prepare_image(reader(k)))
                timing["tracking_s"] += time.perf_counter() - t0
            on_frames(r.first + (own.start or 0), r.tables[own], r.flags[own])
            bar.update(len(r.tables[own]))
            del r  # the chunk's tracker and tables: the joined tracker took what it needs
            on_tracked(tracker.take_frames(last=j == len(plan) - 1))
    finally:
        bar.close()
    how = "serial" if here else describe_executor(executor)
    parallel = f"{how}: {len(plan)} chunk{'s' if len(plan) > 1 else ''}, {retracked} re-tracked at their join"
    return MeasurementRun(timing, parallel)


def _extract_apart_track_here(reader: FrameReader, *, n_frames: int, calibration: Calibration, params,
                              executor: Executor, on_frames, on_tracked, progress: bool) -> MeasurementRun:
    """:func:`measure_features` where chunks tracked apart could not be joined (:func:`chunks_can_join`): the
    workers extract short chunks ahead while this process tracks every frame in order, as one sequential tracker
    (what a refused join falls back to, without tracking those frames twice)."""
    width = executor_width(executor)
    plan = [(a, min(a + EXTRACTION_CHUNK_FRAMES, n_frames) - 1) for a in range(0, n_frames, EXTRACTION_CHUNK_FRAMES)]
    tasks = [(extract_chunk, (reader.part(a, b), a, b, calibration, params)) for a, b in plan]
    tracker = make_tracker(calibration, params)
    timing = {"extraction_s": 0.0, "image_prep_s": 0.0, "tracking_s": 0.0}
    bar = progress_bar(n_frames, enabled=progress, desc="features")
    try:
        for j, r in _in_order(executor, tasks, ahead=2 * width + 1):
            timing["extraction_s"] += r.seconds
            for k, feats in enumerate(r.tables, start=r.first):
                t0 = time.perf_counter()
                prepared = tracker.prepare_image(reader(k))
                t1 = time.perf_counter()
                tracker.add_frame(feats, prepared=prepared)
                timing["image_prep_s"] += t1 - t0
                timing["tracking_s"] += time.perf_counter() - t1
            on_frames(r.first, r.tables, r.flags)
            bar.update(len(r.tables))
            on_tracked(tracker.take_frames(last=j == len(plan) - 1))
    finally:
        bar.close()
    parallel = (f"{describe_executor(executor)}: features extracted in {len(plan)} chunks, tracked in this process "
                "(points bridged without end: chunks tracked apart could not be joined)")
    return MeasurementRun(timing, parallel)


# -- flow --------------------------------------------------------------------------------------------------------


class _FrameRun(Sequence):
    """Frames ``first..first + n - 1`` of a reader as a sequence numbered from 0 (for DenseFlow.compute_sequence)."""

    def __init__(self, reader: FrameReader, first: int, n: int) -> None:
        self._reader, self._first, self._n = reader, first, n

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, i):
        return self._reader(self._first + int(i))


def flow_chunk(reader: FrameReader, first: int, last: int, calibration: Calibration, flow_params) -> tuple[list, float]:
    """The fields of pairs (k, k + 1) for k in ``first..last - 1`` (runs in a worker), and the seconds taken."""
    from skinstretch.processing.flow import DenseFlow  # noqa: PLC0415

    t0 = time.perf_counter()
    fields = DenseFlow(calibration=calibration, params=flow_params).compute_sequence(
        _FrameRun(reader, first, last - first + 1), first_frame=first, threads=1)
    return fields, time.perf_counter() - t0


def measure_flow(
    reader: FrameReader,
    *,
    n_frames: int,
    calibration: Calibration,
    flow_params,
    executor: Executor,
    on_field: Callable[[Any], None],
    progress: bool = False,
) -> MeasurementRun:
    """Dense flow (:class:`~skinstretch.processing.flow.FlowParams` ``flow_params``) between consecutive frames in
    chunks on ``executor``; ``on_field(field)`` receives every field in pair order."""
    width = executor_width(executor)
    plan = chunk_plan(n_frames, width=width, overlap=0)  # a chunk starts at the last frame of the one before
    here = len(plan) == 1
    run_on = InlineExecutor() if here else executor
    tasks = [(flow_chunk, (reader.part(a, b) if not here else reader, a, b, calibration, flow_params))
             for a, b in plan]
    t0 = time.perf_counter()
    busy = 0.0
    bar = progress_bar(max(n_frames - 1, 0), enabled=progress, desc="flow")
    try:
        for _, (fields, seconds) in _in_order(run_on, tasks, ahead=width + 1):
            busy += seconds
            for f in fields:
                on_field(f)
            bar.update(len(fields))
    finally:
        bar.close()
    how = "serial" if here else describe_executor(executor)
    return MeasurementRun({"flow_s": time.perf_counter() - t0, "flow_cpu_s": busy},
                           f"{how}: {len(plan)} chunk{'s' if len(plan) > 1 else ''}")
