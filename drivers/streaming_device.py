"""The base of every device that streams data in (cameras, force sensors): life cycle, one worker thread, a
bounded queue, errors handed to the reader. (Movies streamed out to a display: :mod:`~.display.movie_stream`.)

:class:`skinstretch.drivers.camera.base.Camera` and :class:`skinstretch.drivers.forcesensor.base.ForceSensor` both own a device that
produces items (frames, force samples) on its own clock. A dedicated worker thread moves them into a bounded
queue so that a slow reader never stalls the device; when the worker fails, its exception is queued *after* the
items acquired before it, so the reader gets every item and then the error. Subclasses say what their items are
called (for messages) and implement ``_do_open``, ``_do_close``, ``_do_start``, ``_do_stop``.
"""

from __future__ import annotations

import math
import queue
import threading
from abc import ABC, abstractmethod
from typing import Any, Callable

from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError

from skinstretch.processing.errors import InvalidInputError

__all__ = ["StreamingDevice"]


class StreamingDevice(ABC):
    """Open/close (or ``with``), start/stop a worker thread, read queued items with a timeout.

    Parameters
    ----------
    queue_size : int
        Items held between the worker thread and the reader.
    """

    #: For messages: what the device is ("camera") and what it delivers ("frame").
    _device_noun = "device"
    _item_noun = "item"
    #: Names the worker thread: ``<Class>-<role>``.
    _worker_role = "worker"

    def __init__(self, *, queue_size: int) -> None:
        if not isinstance(queue_size, int) or queue_size < 1:
            raise InvalidInputError(f"queue_size must be a positive int, got {queue_size!r}")
        self._queue_size = queue_size
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._is_open = False
        self._streaming = False
        self._thread: threading.Thread | None = None
        self._stop_event = threading.Event()
        self._error: BaseException | None = None
        self._lock = threading.Lock()

    # -- life cycle
    def open(self) -> Any:
        """Connect to the device (idempotent). Returns self."""
        if not self._is_open:
            self._do_open()
            self._is_open = True
        return self

    def close(self) -> None:
        """Stop streaming if needed and release the device (idempotent)."""
        if not self._is_open:
            return
        try:
            if self._streaming:
                self.stop()
        finally:
            self._is_open = False
            self._do_close()

    def __enter__(self) -> Any:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._is_open

    @property
    def is_streaming(self) -> bool:
        return self._streaming

    # -- streaming
    def _begin_streaming(self, worker: Callable[[], None]) -> None:
        """Fresh queue and stop flag, ``_do_start``, then the worker thread (subclasses reset their counts first)."""
        self._queue = queue.Queue(maxsize=self._queue_size)
        self._error = None
        self._stop_event = threading.Event()
        self._do_start()
        self._streaming = True
        self._thread = threading.Thread(target=worker, name=f"{type(self).__name__}-{self._worker_role}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop streaming. Items already queued stay readable."""
        if not self._streaming:
            return
        self._stop_event.set()
        thread = self._thread
        if thread is not None:
            thread.join(timeout=5.0)
        self._streaming = False
        self._thread = None
        self._do_stop()
        if thread is not None and thread.is_alive():
            raise DeviceError(f"{self!r}: {self._worker_role} thread did not stop within 5 s")

    def _next_item(self, timeout_s: float, timeout_detail: Callable[[], str]) -> Any:
        """The oldest queued item, waiting up to ``timeout_s``; the worker's error once its items are read.

        ``timeout_detail()`` adds the device's counters to the :class:`DeviceTimeoutError` message.
        """
        if not (isinstance(timeout_s, (int, float)) and timeout_s > 0 and math.isfinite(timeout_s)):
            raise InvalidInputError(f"timeout_s must be a positive finite number of seconds, got {timeout_s!r}")
        try:
            item = self._queue.get_nowait()
        except queue.Empty:
            if self._error is not None:
                raise self._error
            if not self._streaming:
                raise DeviceError(f"{self!r}: not streaming and no {self._item_noun}s queued; start() first")
            try:
                item = self._queue.get(timeout=timeout_s)
            except queue.Empty:
                if self._error is not None:
                    raise self._error from None
                raise DeviceTimeoutError(
                    f"{self!r}: no {self._item_noun} within {timeout_s:g} s ({timeout_detail()})"
                ) from None
        if isinstance(item, BaseException):  # the worker's last word, queued after its items
            self._error = item
            raise item
        return item

    def _worker_failed(self, exc: BaseException, doing: str) -> None:
        """Hand a worker exception to the reader (as a DeviceError), after the items already queued."""
        if not isinstance(exc, DeviceError):
            wrapped = DeviceError(f"{self!r}: {doing} failed: {type(exc).__name__}: {exc}")
            wrapped.__cause__ = exc
            exc = wrapped
        # The queue may be full: wait (bounded by stop()) for room rather than losing the error.
        while not self._stop_event.is_set():
            try:
                self._queue.put(exc, timeout=0.05)
                return
            except queue.Full:
                continue
        self._error = exc

    def _require_open(self) -> None:
        if not self._is_open:
            raise DeviceError(f"{self!r}: {self._device_noun} is not open; call open() or use it in a with-block")

    @abstractmethod
    def _do_open(self) -> None: ...

    @abstractmethod
    def _do_close(self) -> None: ...

    @abstractmethod
    def _do_start(self) -> None: ...

    @abstractmethod
    def _do_stop(self) -> None: ...
