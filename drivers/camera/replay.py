"""Replay recorded images through the :class:`~skinstretch.drivers.camera.base.Camera` interface.

Sources (docs/import-and-replay.md):

* a session file (``.h5``/``.hdf5``, see docs/session-format.md): recorded frame ids, device and host time stamps;
* anything ``skinstretch import`` reads, through the same readers (:mod:`skinstretch.drivers.frame_readers`):
  a video file (AVI such as the seed's movies, MP4, MOV, MKV...), a TIFF stack (multi-page, OME, ImageJ), a
  directory or glob pattern of PNG/TIFF/BMP/JPEG images in natural order, or a list of image paths.

Frames come out at the recorded rate (``rate_hz=None``: the session's host time stamps, the rate the video or TIFF
declares), at a chosen rate, or as fast as they are read (``rate_hz=math.inf``). Unlike a live camera a replay
never drops a frame: a slow reader simply slows the replay. After the last frame :meth:`read` raises
:class:`~skinstretch.drivers.camera.base.EndOfStreamError` (unless ``loop=True``). Colour images are converted to
grey by the readers' rule (BT.601 luma); 16-bit images stay 16-bit.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from skinstretch.drivers.camera.base import Camera, Clock, EndOfStreamError, Frame, MonotonicClock
from skinstretch.drivers.camera_modes import CameraMode
from skinstretch.drivers.session_file import open_session
from skinstretch.drivers.errors import DeviceError, SessionFileError
from skinstretch.drivers.frame_readers import FrameReader, open_frame_reader
from skinstretch.processing.errors import InvalidInputError

__all__ = ["ReplayCamera"]

_SESSION_SUFFIXES = {".h5", ".hdf5"}


class _SessionSource:
    def __init__(self, path: Path) -> None:
        self.session = open_session(path)
        self.name = str(path)
        n = self.session.n_frames
        if n < 1:
            self.session.close()
            raise SessionFileError(f"{path}: session holds no frames to replay")
        self.n_frames = n
        self.shape = (self.session.shape[1], self.session.shape[2])
        self.mode_name = self.session.camera_mode.name
        self.frame_ids = np.asarray(self.session.frame_ids, dtype=np.int64)
        self.device_ts = np.asarray(self.session.device_timestamps, dtype=np.float64)
        ts = np.asarray(self.session.timestamps, dtype=np.float64)
        fps = float(self.session.camera_mode.fps)
        # Recorded pacing from the host time stamps when they are usable, else the mode's nominal rate.
        if n > 1 and np.all(np.isfinite(ts)) and np.all(np.diff(ts) >= 0) and ts[-1] > ts[0]:
            self.times = ts - ts[0]
            self.fps = (n - 1) / (ts[-1] - ts[0])
        else:
            self.times = np.arange(n) / fps
            self.fps = fps

    def read(self, k: int) -> tuple[np.ndarray, int, float]:
        return self.session.frame(k), int(self.frame_ids[k]), float(self.device_ts[k])

    def close(self) -> None:
        self.session.close()


class _FileSource:
    """A video, TIFF stack or image folder through its shared reader (skinstretch.drivers.frame_readers)."""

    def __init__(self, reader: FrameReader) -> None:
        self.reader = reader
        self.name = reader.name
        self.n_frames = reader.n_frames
        self.shape = reader.shape
        self.mode_name = "replay"
        self.fps = reader.fps
        self.times = None
        if reader.dtype not in (np.uint8, np.uint16):
            reader.close()
            raise DeviceError(f"{reader.name}: a camera delivers 8- or 16-bit frames, the file holds {reader.dtype}")

    def read(self, k: int) -> tuple[np.ndarray, int, float]:
        try:
            frame = self.reader.read(k)
        except IndexError:
            raise EndOfStreamError(f"{self.name}: ends after {k} frames") from None
        device_t = frame.time_s if math.isfinite(frame.time_s) else (k / self.fps if self.fps else math.nan)
        return frame.image, k, device_t

    def close(self) -> None:
        self.reader.close()


class ReplayCamera(Camera):
    """A camera replaying a session file, an image sequence or a video file.

    Parameters
    ----------
    source : path-like, glob pattern or sequence of paths
        A session file (.h5/.hdf5), a directory of PNG/TIFF/BMP/JPEG images, a glob pattern matching images,
        a list of image paths, a TIFF stack, or a video file.
    rate_hz : float, optional
        Replay rate in Hz; None replays at the recorded rate (session time stamps, the rate a video or TIFF
        declares; image folders have none and need a rate); ``math.inf`` replays as fast as frames are read.
    loop : bool
        Start again from the first frame after the last one.
    clock : Clock, optional
        Time source for pacing (real time by default).
    queue_size : int
        Frames read ahead of :meth:`read`.
    """

    _drop_when_full = False  # a file can wait for its reader

    def __init__(
        self,
        source: str | os.PathLike | Sequence[str | os.PathLike],
        *,
        rate_hz: float | None = None,
        loop: bool = False,
        clock: Clock | None = None,
        queue_size: int = 32,
    ) -> None:
        super().__init__(queue_size=queue_size)
        if rate_hz is not None and not (isinstance(rate_hz, (int, float)) and rate_hz > 0):
            raise InvalidInputError(f"rate_hz must be > 0 (math.inf: unpaced) or None, got {rate_hz!r}")
        self._source_spec = source
        self._rate_hz = None if rate_hz is None else float(rate_hz)
        self._loop = loop
        self._clock = clock if clock is not None else MonotonicClock()
        self._src = None
        self._next = 0
        self._t0 = 0.0
        self._epoch_offset = 0.0

    # -- Camera
    def _do_open(self) -> None:
        self._src = self._open_source(self._source_spec)
        rate = self._rate_hz
        if rate is None:
            if self._src.fps is None:
                self._src.close()
                raise InvalidInputError(f"{self._src.name} has no recorded frame rate: give rate_hz")
            rate = self._src.fps
        h, w = self._src.shape
        # The mode reports the recorded rate when replaying unpaced (math.inf) and the source has one.
        fps = rate if math.isfinite(rate) or self._src.fps is None else self._src.fps
        self._mode = CameraMode(self._src.mode_name, w, h, fps)

    @staticmethod
    def _open_source(spec):
        if not isinstance(spec, (list, tuple)):
            text = os.fspath(spec)
            path = Path(text)
            if not path.exists() and not any(ch in text for ch in "*?["):
                raise InvalidInputError(f"source {text!r} does not exist")
            if path.is_file() and path.suffix.lower() in _SESSION_SUFFIXES:
                return _SessionSource(path)
        return _FileSource(open_frame_reader(spec))

    def _do_close(self) -> None:
        if self._src is not None:
            self._src.close()
            self._src = None

    def _do_set_mode(self, mode: CameraMode) -> None:
        h, w = self._src.shape
        if (mode.height, mode.width) != (h, w):
            raise InvalidInputError(f"mode {mode.name} is {mode.width}x{mode.height} but {self._src.name} is {w}x{h}")
        self._rate_hz = mode.fps  # a replay can only change its rate

    def _do_start(self) -> None:
        self._next = 0
        self._t0 = self._clock.now()
        self._epoch_offset = time.time() - self._t0

    def _do_stop(self) -> None:
        pass

    def _due(self, k: int) -> float:
        src = self._src
        if self._rate_hz is None and src.times is not None:
            n = src.n_frames
            lap, index = divmod(k, n)
            lap_s = src.times[-1] + 1.0 / src.fps
            return self._t0 + lap * lap_s + src.times[index]
        rate = self._rate_hz if self._rate_hz is not None else src.fps
        return self._t0 + k / rate

    def _do_grab(self) -> Frame | None:
        k = self._next
        src = self._src
        n = src.n_frames
        if n is not None and k >= n and not self._loop:
            raise EndOfStreamError(f"{self!r}: all {n} frames replayed")
        rate = self._rate_hz if self._rate_hz is not None else src.fps
        if math.isfinite(rate) and not self._clock.wait_until(self._due(k), self._stop_event):
            return None
        index = k % n if n is not None else k
        try:
            image, frame_id, device_t = src.read(index)
        except EndOfStreamError:
            if not self._loop or k == 0:
                raise
            # A video whose frame count OpenCV did not know: now it is known, loop from the start.
            src.n_frames = k
            self._next = k
            return None
        self._next = k + 1
        if n is not None and k >= n:
            ids = getattr(src, "frame_ids", None)
            span = int(ids[-1] - ids[0] + 1) if ids is not None else n
            frame_id += (k // n) * span  # keep ids increasing across loops, without a false gap
        return Frame(image, frame_id, device_t, self._epoch_offset + self._clock.now())

    def __repr__(self) -> str:
        name = self._src.name if self._src is not None else str(self._source_spec)
        return f"ReplayCamera({name!r})"
