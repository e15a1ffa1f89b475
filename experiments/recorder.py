"""Crash-safe recording of one trial: a writer thread drains a bounded queue into an SWMR session file.

Acquisition threads (camera loop, force sensor, display feedback) never touch the file: they put frames and
samples on a bounded queue, and one writer thread per session writes them through
:class:`skinstretch.drivers.session_file.SessionWriter`, whose datasets are created up front and which runs in HDF5 SWMR mode.
The file is flushed at least every ``flush_interval_s`` (0.025 s) — after writes and also when the queue is idle —
so a SIGKILL loses at most the last ~0.1 s and leaves a file that opens and reads as incomplete (shared FACTS:
recording crash test).

When the writer fails (disk full, or any other error) it stops writing, closes the session marked *failed* with
the reason, and sets :attr:`Recorder.failure` (and :attr:`Recorder.disk_full`); the producers see it on their next
put and the runner ends the trial cleanly (display to rest, devices stopped). Data already written is kept. The
session writer stops *before* a write could meet a full disk and keeps a reserve to close the file
(:mod:`skinstretch.drivers.disk_space`): HDF5 does not survive ENOSPC.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from skinstretch.drivers.camera_modes import CameraMode
from skinstretch.drivers.disk_space import is_disk_full
from skinstretch.drivers.errors import DiskFullError
from skinstretch.drivers.session_file import STATUS_COMPLETE, STATUS_FAILED, SessionWriter, open_session
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError

__all__ = ["Recorder", "RecorderStats", "describe_os_error", "RecordingCount", "record_from_camera"]

log = logging.getLogger(__name__)
_STOP = object()


@dataclass
class RecorderStats:
    """What a recorder did: counts, bytes, the failure reason if any, and the final status."""

    path: Path
    frames_written: int
    samples_written: dict[str, int]
    frames_dropped: int
    max_queue_depth: int
    bytes_written: int
    status: str
    reason: str
    wall_time_s: float

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": str(self.path),
            "frames_written": self.frames_written,
            "samples_written": dict(self.samples_written),
            "frames_dropped": self.frames_dropped,
            "max_queue_depth": self.max_queue_depth,
            "bytes_written": self.bytes_written,
            "status": self.status,
            "reason": self.reason,
            "wall_time_s": self.wall_time_s,
        }


def describe_os_error(exc: BaseException) -> str:
    """A one-line reason for a failed write, naming disk full explicitly."""
    if isinstance(exc, DiskFullError):
        return str(exc)
    if isinstance(exc, OSError) and exc.errno == errno.ENOSPC:
        return f"disk full while writing (ENOSPC): {exc}"
    return f"{type(exc).__name__}: {exc}"


class Recorder:
    """Record one session file from several producer threads through one writer thread.

    Parameters
    ----------
    path : path-like
        Session file to create (never overwritten).
    camera_mode : CameraMode
        Frame size and rate.
    calibration : Calibration
        Pixel scale stored with the frames.
    metadata : mapping, optional
        JSON metadata stored in the file (subject, surface, trial...).
    streams : mapping name -> (sample shape, dtype), optional
        Sample streams declared up front (SWMR cannot add datasets later), e.g. ``{"force": ((6,), "f8")}``.
    queue_size : int, optional
        Bound of the queue, in items. A full queue blocks the producer for up to ``put_timeout_s``, then the frame
        is counted as dropped (acquisition must never stall behind the disk).
    flush_interval_s : float, optional
        Longest time between flushes (s). 0.025 s by default: half the 0.05 s budget, leaving the other half for
        the queue's lag on a busy host (a SIGKILL loses at most ~0.1 s).
    put_timeout_s : float, optional
        Longest time a producer waits on a full queue (s).
    writer_factory : callable, optional
        Makes the :class:`SessionWriter` (same keywords); tests inject faults through it.

    Examples
    --------
    >>> rec = Recorder(path, camera_mode=CAMERA_MODES["full"], calibration=Calibration(62.0))  # doctest: +SKIP
    >>> rec.start(); rec.put_frame(img, timestamp=t, frame_id=0); stats = rec.finish()  # doctest: +SKIP
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        camera_mode: CameraMode,
        calibration: Calibration,
        metadata: Mapping[str, Any] | None = None,
        streams: Mapping[str, tuple[tuple[int, ...], Any]] | None = None,
        queue_size: int = 256,
        flush_interval_s: float = 0.025,
        put_timeout_s: float = 1.0,
        writer_factory: Callable[..., SessionWriter] = SessionWriter,
    ) -> None:
        if queue_size < 1:
            raise InvalidInputError(f"queue_size must be at least 1, got {queue_size!r}")
        if not (0 < flush_interval_s <= 1.0):
            raise InvalidInputError(f"flush_interval_s must be in (0, 1] s, got {flush_interval_s!r}")
        if not put_timeout_s > 0:
            raise InvalidInputError(f"put_timeout_s must be positive, got {put_timeout_s!r}")
        self.path = Path(path)
        self.camera_mode = camera_mode
        self._flush_interval = float(flush_interval_s)
        self._put_timeout = float(put_timeout_s)
        self._writer = writer_factory(
            self.path,
            camera_mode=camera_mode,
            calibration=calibration,
            metadata=metadata,
            streams=streams,
            flush_interval_s=flush_interval_s,
        )
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._thread = threading.Thread(target=self._run, name=f"recorder:{self.path.name}", daemon=True)
        self._failure: str | None = None
        self._disk_full = False
        self._failed_event = threading.Event()
        self._frames = 0
        self._samples: dict[str, int] = {name: 0 for name in (streams or {})}
        self._dropped = 0
        self._max_depth = 0
        self._final_status = STATUS_COMPLETE
        self._final_reason = ""
        self._t0 = time.monotonic()
        self._started = False
        self._finished: RecorderStats | None = None
        self._pending: tuple | None = None
        self._shapes = {name: tuple(int(v) for v in spec[0]) for name, spec in (streams or {}).items()}

    # -- producer side
    @property
    def failure(self) -> str | None:
        """Why the writer failed (disk full...), or None while all is well."""
        return self._failure

    @property
    def disk_full(self) -> bool:
        """The writer stopped because the disk is full (the run should not start another recording there)."""
        return self._disk_full

    @property
    def failed(self) -> threading.Event:
        """Set as soon as the writer fails; producers and the runner may wait on it."""
        return self._failed_event

    @property
    def frames_written(self) -> int:
        return self._frames

    def start(self) -> "Recorder":
        if not self._started:
            self._started = True
            self._thread.start()
        return self

    def _put(self, item: tuple) -> bool:
        if self._failure is not None:
            return False
        try:
            self._queue.put(item, timeout=self._put_timeout)
        except queue.Full:
            if item[0] == "frame":
                self._dropped += 1
            return False
        depth = self._queue.qsize()
        if depth > self._max_depth:
            self._max_depth = depth
        return True

    def put_frame(
        self, image: np.ndarray, *, timestamp: float, frame_id: int, device_timestamp: float = math.nan
    ) -> bool:
        """Queue one frame; False when it was not queued (writer failed, or queue full for too long)."""
        if not self._started:
            raise InvalidInputError("put_frame before start(): call Recorder.start() first")
        return self._put(("frame", image, float(timestamp), int(frame_id), float(device_timestamp)))

    def put_samples(self, stream: str, t: np.ndarray | float, data: np.ndarray) -> bool:
        """Queue samples of a declared stream; False when they were not queued."""
        if stream not in self._samples:
            raise InvalidInputError(f"stream {stream!r} was not declared; declared: {sorted(self._samples)}")
        return self._put(("samples", stream, np.array(t, dtype=np.float64), np.array(data)))

    # -- writer thread
    def _fail(self, reason: str, exc: BaseException | None = None) -> None:
        self._failure = reason
        self._disk_full = self._disk_full or (exc is not None and is_disk_full(exc))
        self._failed_event.set()
        try:
            self._writer.fail(reason)
        except Exception as close_exc:  # noqa: BLE001 - the data already flushed stays; say why it did not close
            self._disk_full = self._disk_full or is_disk_full(close_exc)
            log.error("%s: could not be closed after the failure: %s", self.path, close_exc)

    def _run(self) -> None:
        dirty = False
        last_flush = time.monotonic()
        while True:
            if self._pending is not None:
                item, self._pending = self._pending, None
            else:
                try:
                    item = self._queue.get(timeout=self._flush_interval)
                except queue.Empty:
                    item = None
            if item is _STOP:
                break
            if self._failure is not None:
                continue  # keep draining so producers never block on a dead writer
            try:
                if item is not None:
                    if item[0] == "frame":
                        run, nxt = self._frame_run(item)
                        if len(run) == 1:
                            _, image, ts, fid, dts = item
                            self._writer.append_frame(image, timestamp=ts, frame_id=fid, device_timestamp=dts)
                        else:
                            self._writer.append_frames(
                                np.stack([r[1] for r in run]),
                                timestamps=np.array([r[2] for r in run]),
                                frame_ids=np.array([r[3] for r in run], dtype=np.int64),
                                device_timestamps=np.array([r[4] for r in run]),
                            )
                        self._frames += len(run)
                        if nxt is not None:
                            self._pending = nxt
                    else:
                        _, stream, t, data = item
                        t, data, item = self._coalesce(stream, t, data)
                        self._writer.append_samples(stream, t, data)
                        self._samples[stream] += int(np.atleast_1d(t).shape[0])
                        if item is not None:  # the item that ended the run of samples is written next
                            self._pending = item
                    dirty = True
                now = time.monotonic()
                # SessionWriter flushes after appends; this also flushes when the producers pause.
                if dirty and now - last_flush >= self._flush_interval:
                    self._writer.flush()
                    dirty = False
                    last_flush = now
            except Exception as exc:  # disk full, I/O error, bad item: the trial fails, the data so far stays
                self._fail(describe_os_error(exc), exc)
        if self._failure is None:
            try:
                self._writer.close(status=self._final_status, reason=self._final_reason)
            except Exception as exc:  # noqa: BLE001 - recorded as the failure
                self._failure = describe_os_error(exc)
                self._disk_full = is_disk_full(exc)
                self._failed_event.set()

    def _frame_run(self, first: tuple) -> tuple[list, tuple | None]:
        """Frames already queued behind ``first`` (up to 32), written in one append when the writer fell behind:
        a busy host then catches up instead of dropping. Returns them and the next, different item."""
        run = [first]
        for _ in range(31):
            try:
                cand = self._queue.get_nowait()
            except queue.Empty:
                return run, None
            if cand is not _STOP and cand[0] == "frame" and cand[1].shape == first[1].shape:
                run.append(cand)
                continue
            return run, cand
        return run, None

    def _coalesce(self, stream: str, t: np.ndarray, data: np.ndarray):
        """Join the samples of ``stream`` already queued behind this block into one append: an HDF5 append costs
        the same for 1 or 100 rows, and a sensor at kHz rates must not starve the frames. Returns the next,
        different item taken off the queue (or None)."""
        ts, ds = [np.atleast_1d(t)], [np.asarray(data)]
        nxt = None
        for _ in range(256):
            try:
                cand = self._queue.get_nowait()
            except queue.Empty:
                break
            if cand is not _STOP and cand[0] == "samples" and cand[1] == stream:
                ts.append(np.atleast_1d(cand[2]))
                ds.append(np.asarray(cand[3]))
                continue
            nxt = cand
            break
        if len(ts) == 1:
            return t, data, nxt
        shape = self._shapes[stream]
        return np.concatenate(ts), np.concatenate([d.reshape(-1, *shape) for d in ds]), nxt

    # -- ending
    def finish(self, *, failed_reason: str | None = None, timeout_s: float = 30.0) -> RecorderStats:
        """Write what is queued, close the file (complete, or failed with ``failed_reason``) and return stats.

        Idempotent: a second call returns the same stats.
        """
        if self._finished is not None:
            return self._finished
        if failed_reason:
            self._final_status, self._final_reason = STATUS_FAILED, failed_reason
        if self._started:
            self._queue.put(_STOP)
            self._thread.join(timeout_s)
        else:
            try:
                self._writer.close(status=self._final_status, reason=self._final_reason)
            except Exception as exc:  # noqa: BLE001 - recorded as the failure
                self._failure = describe_os_error(exc)
                self._disk_full = is_disk_full(exc)
        if self._failure is not None:
            status, reason = "failed", self._failure
        else:
            status = "failed" if self._final_status == STATUS_FAILED else "complete"
            reason = self._final_reason
        try:
            size = self.path.stat().st_size
        except OSError:
            size = 0
        self._finished = RecorderStats(
            path=self.path,
            frames_written=self._frames,
            samples_written=dict(self._samples),
            frames_dropped=self._dropped,
            max_queue_depth=self._max_depth,
            bytes_written=size,
            status=status,
            reason=reason,
            wall_time_s=time.monotonic() - self._t0,
        )
        return self._finished


@dataclass(frozen=True)
class RecordingCount:
    """What a timed recording from a camera wrote and lost (:func:`record_from_camera`)."""

    frames: int  # in the file
    dropped: int  # frame-id gaps in the file + frames the camera dropped + frames the recorder's queue dropped
    seconds: float  # wall time, from the first read to the file closed
    cpu_s: float  # CPU time of this process (every thread) over the same span
    stats: RecorderStats

    @property
    def status(self) -> str:
        return self.stats.status


def record_from_camera(camera, path: str | os.PathLike, *, mode: CameraMode, calibration: Calibration,
                       seconds: float, metadata: Mapping[str, Any] | None = None, queue_size: int = 256,
                       on_frame: Callable[[int, Any], None] | None = None,
                       stop: threading.Event | None = None) -> RecordingCount:
    """Record ``camera`` (opened here, set to ``mode``, started, then stopped and closed) into ``path`` through a
    :class:`Recorder` for ``seconds`` (or until ``stop`` is set), and count what the file holds.
    ``on_frame(k, frame)`` sees every frame as it is queued (the benches sample checksums)."""
    camera.open()
    camera.set_mode(mode)
    rec = Recorder(path, camera_mode=mode, calibration=calibration, metadata=metadata or {},
                   queue_size=queue_size).start()
    t0, cpu0 = time.perf_counter(), time.process_time()
    k = 0
    try:
        camera.start()
        while time.perf_counter() - t0 < seconds and not (stop is not None and stop.is_set()):
            f = camera.read(timeout_s=1.0)
            rec.put_frame(f.image, timestamp=f.host_timestamp_s, frame_id=f.frame_id,
                          device_timestamp=f.device_timestamp_s)
            if on_frame is not None:
                on_frame(k, f)
            k += 1
        camera_dropped = camera.stats.dropped
    finally:
        try:
            camera.stop()
        finally:
            camera.close()
    stats = rec.finish()
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    with open_session(path) as s:
        ids = s.frame_ids
        gaps = int(np.sum(np.maximum(np.diff(ids) - 1, 0))) if ids.size > 1 else 0
        frames = s.n_frames
    return RecordingCount(frames, gaps + camera_dropped + stats.frames_dropped, wall, cpu, stats)
