"""The camera interface every camera implements: real (Aravis, V4L2), replayed and simulated.

A :class:`Camera` owns its transport (an Aravis stream, an OpenCV capture, a file, a frame renderer) and a
dedicated acquisition thread that does nothing but move finished frames into a bounded queue, so that a slow
consumer never stalls the device. Frames that cannot be queued are *counted* as dropped, never lost silently.

Public methods validate their arguments and the camera's state, then call a private ``_do_*`` method that holds
the device-specific code (the python-microscope pattern, see docs STYLE).

Clocks
------
Host time stamps are Unix-epoch seconds (:func:`time.time`, the clock Aravis uses for its system time stamps),
the same clock the force-sensor driver uses, so camera frames and force samples can be aligned. Cameras that
*pace* themselves (replay, simulation) take a :class:`Clock` so that tests can step time by hand
(:class:`ManualClock`) instead of sleeping.
"""

from __future__ import annotations

import queue
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from skinstretch.drivers.camera_modes import CameraMode, camera_mode
from skinstretch.drivers.streaming_device import StreamingDevice
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import InvalidInputError

__all__ = [
    "Camera",
    "CameraStats",
    "Clock",
    "EndOfStreamError",
    "Frame",
    "ManualClock",
    "MonotonicClock",
    "FrameIdUnwrapper",
]


class EndOfStreamError(DeviceError):
    """A finite frame source (a replayed file, a non-looping simulation) has delivered its last frame."""


@dataclass(frozen=True)
class Frame:
    """One acquired image.

    Attributes
    ----------
    image : (H, W) uint8 or uint16
        The pixels, rows first.
    frame_id : int
        The camera's frame counter, unwrapped to increase monotonically; a gap means frames were lost.
    device_timestamp_s : float
        Camera clock time of the exposure in seconds (NaN when the device has no clock).
    host_timestamp_s : float
        Host time (Unix epoch, s) when the frame reached the host.
    """

    image: np.ndarray
    frame_id: int
    device_timestamp_s: float
    host_timestamp_s: float


@dataclass(frozen=True)
class CameraStats:
    """Counts since the last :meth:`Camera.start`.

    Attributes
    ----------
    completed : int
        Whole frames the device delivered to the acquisition thread.
    failed : int
        Frames the device delivered damaged (incomplete, missing packets, wrong size); not queued.
    dropped : int
        Frames lost: gaps in the frame ids, device buffer underruns, or a full queue (consumer too slow).
    delivered : int
        Frames returned by :meth:`Camera.read`.
    """

    completed: int = 0
    failed: int = 0
    dropped: int = 0
    delivered: int = 0


class FrameIdUnwrapper:
    """Turn a wrapping hardware frame counter into a monotonically increasing one and count the gaps.

    GigE Vision 1.x block ids are 16 bits and skip 0 when they wrap (65535 is followed by 1); the Aravis fake
    camera does the same. With ``modulus=None`` ids are taken as they are.

    Parameters
    ----------
    modulus : int or None
        Counter period (65536 for GigE Vision 1.x), or None for counters that do not wrap.
    skip_zero : bool
        Whether the counter skips 0 after wrapping.
    """

    def __init__(self, *, modulus: int | None = 65536, skip_zero: bool = True) -> None:
        if modulus is not None and modulus < 2:
            raise InvalidInputError(f"modulus must be >= 2 or None, got {modulus!r}")
        self._modulus = modulus
        self._skip_zero = skip_zero
        self._last_raw: int | None = None
        self._value = 0
        self.gaps = 0

    def __call__(self, raw: int) -> int:
        raw = int(raw)
        if self._last_raw is None:
            self._last_raw, self._value = raw, raw
            return raw
        if self._modulus is None:
            step = raw - self._last_raw
        else:
            step = (raw - self._last_raw) % self._modulus
            if self._skip_zero and raw < self._last_raw:
                step -= 1  # the counter went ... 65535, 1: zero is never used
            if step > self._modulus // 2 or step <= 0:
                # Out of order or a counter reset: do not invent a huge gap, restart from here.
                step = 1
        if step > 1:
            self.gaps += step - 1
        self._last_raw = raw
        self._value += max(step, 1)
        return self._value


# --------------------------------------------------------------------------------------------------- clocks


class Clock(ABC):
    """Time source for cameras that pace themselves (replay, simulation)."""

    @abstractmethod
    def now(self) -> float:
        """Current time in seconds (arbitrary origin)."""

    @abstractmethod
    def wait_until(self, t: float, cancel: threading.Event) -> bool:
        """Block until ``now() >= t``; return False early if ``cancel`` is set."""


class MonotonicClock(Clock):
    """Wall time (:func:`time.monotonic`): frames come out in real time."""

    def now(self) -> float:
        return time.monotonic()

    def wait_until(self, t: float, cancel: threading.Event) -> bool:
        while True:
            remaining = t - time.monotonic()
            if remaining <= 0:
                return not cancel.is_set()
            if cancel.wait(min(remaining, 0.1)):
                return False


class ManualClock(Clock):
    """A clock that only moves when :meth:`advance` or :meth:`set` is called (stepping a simulation by hand)."""

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._cond = threading.Condition()

    def now(self) -> float:
        with self._cond:
            return self._t

    def advance(self, dt_s: float) -> None:
        """Move time forward by ``dt_s`` seconds (>= 0) and wake everything waiting on the clock."""
        if not dt_s >= 0:
            raise InvalidInputError(f"dt_s must be >= 0, got {dt_s!r}")
        with self._cond:
            self._t += float(dt_s)
            self._cond.notify_all()

    def set(self, t: float) -> None:
        """Jump to time ``t`` (never backwards)."""
        with self._cond:
            if t < self._t:
                raise InvalidInputError(f"t must not go backwards: now {self._t}, got {t}")
            self._t = float(t)
            self._cond.notify_all()

    def wait_until(self, t: float, cancel: threading.Event) -> bool:
        with self._cond:
            while self._t < t:
                if cancel.is_set():
                    return False
                # Short timed waits so a cancel (set without notifying this condition) is seen promptly.
                self._cond.wait(0.02)
            return not cancel.is_set()


# --------------------------------------------------------------------------------------------------- camera


class Camera(StreamingDevice):
    """A camera: open/close (or ``with``), :meth:`set_mode`, :meth:`start`/:meth:`stop`, :meth:`read` frames.

    Subclasses implement the ``_do_*`` methods. ``_do_grab`` runs in the acquisition thread and returns the
    next :class:`Frame` (with its raw device frame id), or None when nothing arrived within its short internal
    wait; it reports damaged frames with :meth:`_count_failed`.

    Parameters
    ----------
    queue_size : int
        Frames held between the acquisition thread and :meth:`read` (default 256: over 1 s at 220 Hz).
    """

    #: Whether a full queue drops the new frame (a live device) or makes the acquisition thread wait (a file).
    _drop_when_full = True
    _device_noun = "camera"
    _item_noun = "frame"
    _worker_role = "acquisition"

    def __init__(self, *, queue_size: int = 256) -> None:
        super().__init__(queue_size=queue_size)
        self._mode: CameraMode | None = None
        self._reset_counts()

    # -- configuration
    @property
    def mode(self) -> CameraMode:
        """The current acquisition mode (size and rate)."""
        self._require_open()
        if self._mode is None:
            raise DeviceError(f"{self!r}: no mode set")
        return self._mode

    def set_mode(self, mode: CameraMode | str) -> None:
        """Set image size and frame rate: a :class:`CameraMode` or a name from ``CAMERA_MODES``.

        Raises InvalidInputError if the device cannot do it, DeviceError if the camera is streaming.
        """
        if isinstance(mode, str):
            mode = camera_mode(mode)
        if not isinstance(mode, CameraMode):
            raise InvalidInputError(f"mode must be a CameraMode or a mode name, got {mode!r}")
        self._require_open()
        if self._streaming:
            raise DeviceError(f"{self!r}: cannot change mode while streaming; stop() first")
        self._do_set_mode(mode)
        self._mode = mode

    # -- streaming
    def start(self) -> None:
        """Start acquisition: frames accumulate in the queue until :meth:`read`. Resets :attr:`stats`."""
        self._require_open()
        if self._streaming:
            return
        if self._mode is None:
            raise DeviceError(f"{self!r}: set_mode() before start()")
        self._reset_counts()
        self._begin_streaming(self._acquire)

    def read(self, timeout_s: float = 1.0) -> Frame:
        """Return the next frame, oldest first.

        Parameters
        ----------
        timeout_s : float
            Longest wait in seconds (> 0).

        Raises
        ------
        DeviceTimeoutError
            No frame arrived within ``timeout_s`` (the camera stays usable; frames that arrive later are kept).
        EndOfStreamError
            A finite source is exhausted and every frame has been read.
        DeviceError
            The acquisition failed (raised once every frame acquired before the failure has been read), or the
            camera is neither streaming nor holding queued frames.
        """
        def detail() -> str:
            st = self.stats
            return f"completed {st.completed}, failed {st.failed}, dropped {st.dropped}"

        frame = self._next_item(timeout_s, detail)
        with self._lock:
            self._delivered += 1
        return frame

    def frames(self, count: int, *, timeout_s: float = 1.0) -> list[Frame]:
        """Read ``count`` frames (each within ``timeout_s``)."""
        if not isinstance(count, int) or count < 0:
            raise InvalidInputError(f"count must be a non-negative int, got {count!r}")
        return [self.read(timeout_s) for _ in range(count)]

    @property
    def stats(self) -> CameraStats:
        """Completed, failed, dropped and delivered frame counts since :meth:`start`."""
        with self._lock:
            return CameraStats(
                completed=self._completed,
                failed=self._failed,
                dropped=self._overflow + max(self._unwrapper.gaps, self._device_drops()),
                delivered=self._delivered,
            )

    # -- for subclasses
    def _count_failed(self, n: int = 1) -> None:
        with self._lock:
            self._failed += n

    def _device_drops(self) -> int:
        """Frames the device itself reports lost (e.g. Aravis buffer underruns); 0 when it reports none.

        Combined with the frame-id gaps by ``max`` because the same lost frame often shows in both.
        """
        return 0

    def _frame_id_unwrapper(self) -> FrameIdUnwrapper:
        """How raw frame ids wrap; the default takes them as they are."""
        return FrameIdUnwrapper(modulus=None)

    def _reset_counts(self) -> None:
        self._completed = 0
        self._failed = 0
        self._overflow = 0
        self._delivered = 0
        self._unwrapper = self._frame_id_unwrapper()

    def _acquire(self) -> None:
        """Acquisition thread: grab, number, queue. Never blocks on the consumer for a live device."""
        stop = self._stop_event
        try:
            while not stop.is_set():
                frame = self._do_grab()
                if frame is None:
                    continue
                with self._lock:
                    frame_id = self._unwrapper(frame.frame_id)
                    self._completed += 1
                frame = Frame(frame.image, frame_id, frame.device_timestamp_s, frame.host_timestamp_s)
                if self._drop_when_full:
                    try:
                        self._queue.put_nowait(frame)
                    except queue.Full:
                        with self._lock:
                            self._overflow += 1
                else:
                    while True:
                        try:
                            self._queue.put(frame, timeout=0.05)
                            break
                        except queue.Full:
                            if stop.is_set():  # stopped while the reader lagged: the frame is counted lost
                                with self._lock:
                                    self._overflow += 1
                                break
        except BaseException as exc:  # handed to the reader, after the frames acquired before it
            self._worker_failed(exc, "acquisition")

    @abstractmethod
    def _do_set_mode(self, mode: CameraMode) -> None: ...

    @abstractmethod
    def _do_grab(self) -> Frame | None:
        """Acquisition thread: the next frame with its raw frame id, or None after a short wait (<= 0.1 s)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
