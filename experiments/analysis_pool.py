"""Feature measurement in worker processes, chunk by chunk, with exactly the result of one sequential pass.

Extraction, the tracker's image preparation and matching cost ~6-12 ms of CPU a frame, of which 2-4 ms is Python
holding the GIL (the skeleton-graph editing, the matcher's bookkeeping). On threads of one process that Python
serialises: two extraction threads and the tracking thread reached only ~1.2x one thread. Worker processes have no
shared GIL: each tracks a contiguous chunk of the sequence from extraction to matched, refined displacements, and
the chunks are joined in order.

A chunk after the first starts ``overlap`` frames early. Its tracker has then seen the same recent frames as the
previous chunk's tracker at the join, and when the two agree on them bit for bit
(:meth:`skinstretch.processing.tracking.FeatureTracker.continue_with`), the later frames are exactly those one sequential
tracker would have produced. When they do not agree (rare: a relinked feature whose history starts before the
overlap), this process tracks that chunk's frames itself, from the features the worker extracted: the result is
the sequential one either way, which the tests check.

The pool is started once per process (forkserver: workers are forked from a clean server that has imported the
pipeline, never from this possibly multi-threaded process) and kept for later analyses; :func:`warm_up` starts it
ahead of time, :func:`shutdown` stops it. The shared-memory blocks that carry the frames to the workers are kept
for the next analysis too (:data:`MAX_KEPT_BYTES`), and a chunk that /dev/shm has no room for goes to threads.
"""

from __future__ import annotations

import atexit
import math
import multiprocessing as mp
import os
import sys
import threading
import time
from contextlib import contextmanager
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from multiprocessing import shared_memory
from typing import Any, Callable, Sequence

import numpy as np

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError

__all__ = ["chunk_plan", "make_tracker", "track_in_processes", "warm_up", "shutdown", "ProcessPoolFailed"]

# Chunks longer than this are split further: bounded memory (each chunk's frames sit in shared memory while it
# runs) and a progress bar that moves on long sessions.
MAX_CHUNK_FRAMES = 240
# Shorter sequences stay on threads: handing frames to processes costs more than it saves there.
MIN_FRAMES = 32
# Frame blocks in shared memory are kept for the next analysis, up to this many bytes in all: writing a frame into a
# block the first time costs the kernel a page fault per 4 KiB page, on this 2-core VM 16-90 ms for 92 frames of
# 640x484 (it varies with how recently the memory was used), against 4 ms into a block already written once.
MAX_KEPT_BYTES = 256 * 2**20
# Room left free in /dev/shm: a block written beyond the room of its file system kills this process (SIGBUS),
# so a chunk that does not fit goes to threads instead (containers often mount a 64 MB /dev/shm).
SHM_MARGIN_BYTES = 16 * 2**20


class ProcessPoolFailed(RuntimeError):
    """The worker processes could not be started or died (the caller falls back to threads)."""


def make_tracker(calibration: Calibration, params) -> Any:
    """The analysis' :class:`~skinstretch.processing.tracking.FeatureTracker` for ``params`` (an ``AnalysisParams``)."""
    from skinstretch.processing.global_motion import GlobalMotionEstimator  # noqa: PLC0415
    from skinstretch.processing.displacement_refinement import SubpixelRefiner  # noqa: PLC0415
    from skinstretch.processing.tracking import FeatureTracker  # noqa: PLC0415

    return FeatureTracker(
        calibration=calibration,
        params=params.tracking,
        refiner=SubpixelRefiner(calibration=calibration, params=params.subpixel) if params.subpixel else None,
        motion_estimator=GlobalMotionEstimator(downsample=4) if params.robust_matching else None,
    )


def make_extractor(calibration: Calibration, params) -> Any:
    from skinstretch.processing.extraction import ExtractionParams, FeatureExtractor  # noqa: PLC0415

    return FeatureExtractor(calibration=calibration, params=params.extraction or ExtractionParams())


def chunk_plan(n_frames: int, *, workers: int, overlap: int) -> list[tuple[int, int]] | None:
    """(first, last) frame of each chunk, inclusive; chunk j > 0 starts ``overlap`` frames before chunk j-1 ends.

    All chunks get about the same number of frames (the first has no overlap to redo, so it owns more). None for
    fewer than :data:`MIN_FRAMES` frames, too few for two chunks of at least ``2 * overlap + 2`` frames, or in a
    process that is itself a worker: the experiment runner analyses trials in a worker process while it records the
    next one, and that analysis keeps to its threads (no pool of its own, no more cores taken from the recording).
    """
    if workers < 2 or overlap < 1 or n_frames < MIN_FRAMES or mp.parent_process() is not None:
        return None
    m = max(int(workers), math.ceil(n_frames / MAX_CHUNK_FRAMES))
    while m >= 2:
        size = (n_frames + (m - 1) * overlap) / m  # frames per chunk, overlaps included
        if size >= 2 * overlap + 2:
            break
        m -= 1
    if m < 2:
        return None
    plan, first = [], 0
    for j in range(m):
        last = n_frames - 1 if j == m - 1 else int(round((j + 1) * size - j * overlap)) - 1
        plan.append((first, last))
        first = last - overlap
    return plan


# -- the pool ----------------------------------------------------------------------------------------------------

_lock = threading.Lock()
_pool: ProcessPoolExecutor | None = None
_pool_workers = 0


def _context():
    methods = mp.get_all_start_methods()
    if "forkserver" in methods:
        ctx = mp.get_context("forkserver")
        ctx.set_forkserver_preload([__name__])
        return ctx
    return mp.get_context("spawn")  # pragma: no cover - platforms without forkserver (Windows)


def _get_pool(workers: int) -> ProcessPoolExecutor:
    """The running pool of ``workers`` processes, started (all of them, initialised) if need be."""
    global _pool, _pool_workers
    with _lock:
        if _pool is not None and _pool_workers == workers:
            return _pool
        if _pool is not None:
            _pool.shutdown(wait=False, cancel_futures=True)
            _pool = None
        try:
            pool = ProcessPoolExecutor(max_workers=workers, mp_context=_context(), initializer=_worker_init)
            # Every worker is started here, each by one of these tasks (a worker is started by a submission
            # that finds none idle), without re-running the caller's main script in it.
            with _main_script_hidden():
                started = [pool.submit(_pid_after, 0.0) for _ in range(workers)]
            for f in started:
                f.result()
        except (OSError, ValueError, BrokenProcessPool) as exc:
            raise ProcessPoolFailed(f"could not start {workers} worker processes: {exc}") from exc
        _pool, _pool_workers = pool, workers
        return pool


@contextmanager
def _main_script_hidden():
    """While workers start, the main module looks like an interactive session's (no file, no spec).

    A started process otherwise runs the caller's main script again, as ``__mp_main__``, to find functions
    defined there: a lab script that calls the analysis at top level, without ``if __name__ == "__main__"``,
    would run in every worker. The workers only run this module's functions, so they never need it.
    """
    main = sys.modules.get("__main__")
    if main is None:
        yield
        return
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if k in main.__dict__}
    main.__dict__.pop("__file__", None)
    main.__dict__["__spec__"] = None
    try:
        yield
    finally:
        main.__dict__.pop("__spec__", None)
        main.__dict__.update(saved)


def shutdown(*, wait: bool = True) -> None:
    """Stop the worker processes (they are otherwise kept for the next analysis until this process exits) and free
    the kept frame blocks. ``wait=False``: do not wait for them (a broken pool is dropped this way; the next analysis
    starts a new one)."""
    global _pool
    with _lock:
        if _pool is not None:
            _pool.shutdown(wait=wait, cancel_futures=True)
        _pool = None
        while _kept_blocks:
            block = _kept_blocks.pop()
            if os.getpid() == _blocks_pid:
                _free_block(block)


# -- frame blocks in shared memory -------------------------------------------------------------------------------

_kept_blocks: list[shared_memory.SharedMemory] = []  # written once already, no worker using them (under _lock)
_blocks_pid = os.getpid()  # a child forked from this process inherits the list but must not unlink the blocks


def _shm_room() -> int | None:
    """Bytes free in /dev/shm (where POSIX shared memory lives on Linux), or None where it cannot be told."""
    try:
        st = os.statvfs("/dev/shm")
    except (OSError, AttributeError):
        return None
    return int(st.f_bavail) * int(st.f_frsize)


def _take_block(nbytes: int) -> shared_memory.SharedMemory:
    """A block of at least ``nbytes``: the smallest kept one that fits, or a new one if /dev/shm has room for it."""
    with _lock:
        fitting = [b for b in _kept_blocks if b.size >= nbytes]
        if fitting:
            block = min(fitting, key=lambda b: b.size)
            _kept_blocks.remove(block)
            return block
    room = _shm_room()
    if room is not None and nbytes + SHM_MARGIN_BYTES > room:
        raise ProcessPoolFailed(
            f"/dev/shm has {room / 2**20:.0f} MB free, a chunk of frames needs {nbytes / 2**20:.0f} MB "
            f"(+{SHM_MARGIN_BYTES / 2**20:.0f} MB margin)"
        )
    try:
        return shared_memory.SharedMemory(create=True, size=int(nbytes))
    except OSError as exc:
        raise ProcessPoolFailed(f"could not create a shared frame block of {nbytes} bytes: {exc}") from exc


def _keep_block(block: shared_memory.SharedMemory) -> None:
    """Keep a block no worker uses any more for the next analysis (the largest ones, up to MAX_KEPT_BYTES)."""
    with _lock:
        _kept_blocks.append(block)
        _kept_blocks.sort(key=lambda b: b.size, reverse=True)
        total = 0
        for b in list(_kept_blocks):
            if total + b.size > MAX_KEPT_BYTES:
                _kept_blocks.remove(b)
                _free_block(b)
            else:
                total += b.size


def _free_block(block: shared_memory.SharedMemory) -> None:
    block.close()
    try:
        block.unlink()
    except FileNotFoundError:  # already gone (another process cleaned up)
        pass


atexit.register(shutdown)


def warm_up(workers: int) -> float:
    """Start the ``workers`` processes now (each loads the compiled kernels) and return the seconds it took.

    The first analysis would otherwise pay it: a few seconds, once per process.
    """
    t0 = time.perf_counter()
    _get_pool(int(workers))
    return time.perf_counter() - t0


def _pid_after(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def _worker_init() -> None:
    """Each worker: one OpenCV thread (the parallelism is the processes), and the compiled kernels loaded now
    rather than inside the first timed chunk."""
    import cv2  # noqa: PLC0415

    cv2.setNumThreads(1)
    try:
        _exercise_pipeline()
    except Exception:  # noqa: BLE001 - a warm-up failure only costs the loading time later
        pass


def _exercise_pipeline() -> None:
    """Extract and track two small synthetic prints (ridges with endings, forks and pores) once."""
    from skinstretch.processing.pixel_scale import Calibration  # noqa: PLC0415

    from skinstretch.experiments.analysis import AnalysisParams  # noqa: PLC0415

    cal = Calibration(px_per_mm=62.0)
    params = AnalysisParams()
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:200, 0:240].astype(np.float64)
    warp = np.cumsum(rng.normal(0, 0.15, (200, 240)), axis=1) * 0.1
    ex, tr = make_extractor(cal, params), make_tracker(cal, params)
    for shift in (0.0, 1.5):
        phase = 2 * np.pi * (yy + shift) / 27.0 + warp + 0.002 * (xx - 120) ** 2 / 10
        img = np.clip(128 + 70 * np.sin(phase) + rng.normal(0, 6, phase.shape), 0, 255).astype(np.uint8)
        res = ex.extract(img)
        tr.add_frame(res.features if res.ok else res.features[:0], image=img)


# -- one chunk, in a worker --------------------------------------------------------------------------------------


@dataclass
class ChunkResult:
    first: int
    tracker: Any  # FeatureTracker after the chunk's frames
    tables: list  # feature table of each frame of the chunk
    flags: list  # flags of each frame
    timing: dict = field(default_factory=dict)


def _track_chunk(shm_name: str, shape: tuple[int, ...], first: int, calibration, params, shading, good) -> ChunkResult:
    from skinstretch.processing.glass_shading import remove_glass_shading  # noqa: PLC0415

    shm = shared_memory.SharedMemory(name=shm_name)
    try:
        frames = np.ndarray(shape, dtype=np.uint8, buffer=shm.buf)
        extractor, tracker = make_extractor(calibration, params), make_tracker(calibration, params)
        tables, flags = [], []
        t_extract = t_prepare = t_track = 0.0
        for i in range(shape[0]):
            t0 = time.perf_counter()
            if shading is not None and good[i]:
                image = remove_glass_shading(frames[i], shading)  # a new array
            else:
                image = np.array(frames[i])  # a copy: nothing may keep a view of the shared block
            res = extractor.extract(image, frame_index=first + i)
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
        del frames
    finally:
        shm.close()
    timing = {"extraction_s": t_extract, "image_prep_s": t_prepare, "tracking_s": t_track}
    return ChunkResult(first, tracker, tables, flags, timing)


# -- the caller's side -------------------------------------------------------------------------------------------


@dataclass
class ProcessTracking:
    tracker: Any
    tables: list
    flags: list
    timing: dict
    n_chunks: int
    n_retracked: int  # chunks whose join did not agree and were tracked here (see the module docstring)


def track_in_processes(
    frames: Sequence[np.ndarray],
    *,
    calibration: Calibration,
    params,
    workers: int,
    plan: list[tuple[int, int]],
    overlap: int,
    shading=None,
    good: np.ndarray | None = None,
    read_frame: Callable[[int], np.ndarray] | None = None,
    on_frames: Callable[[int], None] | None = None,
) -> ProcessTracking:
    """Track ``frames`` (the raw frames; ``shading`` is removed from those flagged ``good`` in the workers) in the
    chunks of ``plan`` on ``workers`` processes, joined in order. ``read_frame(k)`` gives frame k as the tracker
    should see it, for a chunk tracked here. Raises :class:`ProcessPoolFailed` when the workers die."""
    n = len(frames)
    good = np.ones(n, bool) if good is None else np.asarray(good, bool)
    pool = _get_pool(int(workers))
    pending: dict[int, tuple[Future, shared_memory.SharedMemory]] = {}
    blocks: list[shared_memory.SharedMemory] = []
    shape0 = np.asarray(frames[0]).shape

    def submit(j: int) -> None:
        first, last = plan[j]
        shape = (last - first + 1, *shape0)
        shm = _take_block(int(np.prod(shape)))
        blocks.append(shm)
        block = np.ndarray(shape, dtype=np.uint8, buffer=shm.buf)
        for i in range(shape[0]):
            f = np.asarray(frames[first + i])
            if f.shape != shape0 or f.dtype != np.uint8:
                del block
                raise InvalidInputError(
                    f"frame {first + i} is {f.dtype} {f.shape}, expected uint8 {shape0} like frame 0"
                )
            block[i] = f
        del block
        fut = pool.submit(_track_chunk, shm.name, shape, first, calibration, params, shading, good[first : last + 1])
        pending[j] = (fut, shm)

    def release(shm: shared_memory.SharedMemory, *, keep: bool) -> None:
        """``keep``: no worker uses the block any more (its chunk returned), so the next analysis may reuse it."""
        blocks.remove(shm)
        if keep:
            _keep_block(shm)
        else:
            _free_block(shm)

    tracker = None
    tables: list = []
    flags: list = []
    timing = {"extraction_s": 0.0, "image_prep_s": 0.0, "tracking_s": 0.0}
    retracked = 0
    try:
        ahead = int(workers) + 1
        for j in range(min(ahead, len(plan))):
            submit(j)
        for j in range(len(plan)):
            fut, shm = pending.pop(j)
            returned = False
            try:
                r: ChunkResult = fut.result()
                returned = True
            except BrokenProcessPool as exc:
                shutdown(wait=False)
                raise ProcessPoolFailed(f"a worker process died: {exc}") from exc
            except OSError as exc:  # e.g. the worker could not open the frame block: threads can still do it
                raise ProcessPoolFailed(f"a worker process could not track its chunk: {exc!r}") from exc
            finally:
                release(shm, keep=returned)
            if j + ahead < len(plan):
                submit(j + ahead)
            for k, v in r.timing.items():
                timing[k] += v
            if tracker is None:
                tracker, tables, flags = r.tracker, list(r.tables), list(r.flags)
            else:
                own = slice(overlap + 1, None)
                t0 = time.perf_counter()
                if not tracker.continue_with(r.tracker, overlap=overlap):
                    retracked += 1
                    for i, feats in enumerate(r.tables[own], start=r.first + overlap + 1):
                        image = read_frame(i) if read_frame is not None else np.asarray(frames[i])
                        tracker.add_frame(feats, prepared=tracker.prepare_image(image))
                timing["tracking_s"] += time.perf_counter() - t0
                tables.extend(r.tables[own])
                flags.extend(r.flags[own])
            if on_frames is not None:
                on_frames(len(tables))
    finally:
        for fut, _shm in pending.values():
            fut.cancel()
        for shm in list(blocks):  # a chunk still running may read its block: never reuse those
            release(shm, keep=False)
    return ProcessTracking(tracker, tables, flags, timing, len(plan), retracked)
