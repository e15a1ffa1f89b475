"""The force/torque sensor interface.

A :class:`ForceSensor` owns its transport (a UDP socket for the ATI Net F/T) and a receive thread that moves
decoded samples into a bounded queue; a full queue drops the *new* sample and counts it. Public methods validate,
then call private ``_do_*`` methods (python-microscope pattern, docs STYLE).

Units: forces in newtons, torques in newton-metres, times in seconds. Host time stamps are Unix-epoch seconds
(:func:`time.time`), the clock the camera drivers use, so force samples and frames can be aligned.
"""

from __future__ import annotations

import queue
from abc import abstractmethod
from dataclasses import dataclass

import numpy as np

from skinstretch.drivers.streaming_device import StreamingDevice
from skinstretch.processing.errors import InvalidInputError

__all__ = ["FORCE_SAMPLE_DTYPE", "ForceSample", "ForceSensor", "ForceStats"]

#: One row per sample, as :meth:`ForceSensor.drain` returns them and a session's ``force`` stream can store them.
FORCE_SAMPLE_DTYPE = np.dtype(
    [
        ("t", "f8"),  # host time, Unix epoch s
        ("sequence", "u8"),  # transport sequence number, unwrapped (rdt_sequence for the Net F/T)
        ("device_sequence", "u8"),  # the device's own sample counter (ft_sequence for the Net F/T)
        ("status", "u4"),  # device status word (0 = healthy on the Net F/T)
        ("ft", "f8", (6,)),  # Fx, Fy, Fz in N; Tx, Ty, Tz in N m
    ]
)


@dataclass(frozen=True)
class ForceSample:
    """One force/torque sample.

    Attributes
    ----------
    ft : (6,) float64
        Fx, Fy, Fz in N and Tx, Ty, Tz in N m, in the sensor frame.
    sequence : int
        Transport sequence number, unwrapped (gaps = lost samples).
    device_sequence : int
        The device's internal sample counter.
    status : int
        Device status word (0 = healthy).
    host_timestamp_s : float
        Host time (Unix epoch, s) the sample arrived.
    """

    ft: np.ndarray
    sequence: int
    device_sequence: int
    status: int
    host_timestamp_s: float

    @property
    def force_n(self) -> np.ndarray:
        return self.ft[:3]

    @property
    def torque_nm(self) -> np.ndarray:
        return self.ft[3:]


@dataclass(frozen=True)
class ForceStats:
    """Counts since the last :meth:`ForceSensor.start`.

    Attributes
    ----------
    received : int
        Samples decoded and accepted.
    lost : int
        Samples missing from the sequence (gaps) and not recovered later.
    reordered : int
        Samples that arrived after a later one (they are still delivered, in arrival order).
    duplicates : int
        Samples seen twice (discarded).
    protocol_errors : int
        Packets that could not be decoded (wrong length, garbled); discarded.
    dropped : int
        Samples discarded because the queue was full (the reader is too slow).
    status_errors : int
        Samples whose device status word reported a fault.
    """

    received: int = 0
    lost: int = 0
    reordered: int = 0
    duplicates: int = 0
    protocol_errors: int = 0
    dropped: int = 0
    status_errors: int = 0


class ForceSensor(StreamingDevice):
    """A streaming force/torque sensor: open/close (or ``with``), :meth:`start`/:meth:`stop`, :meth:`read`,
    :meth:`drain`, :meth:`bias`.

    Subclasses implement ``_do_open``, ``_do_close``, ``_do_start``, ``_do_stop``, ``_do_bias`` and
    ``_do_receive`` (receive thread: return a list of samples, possibly empty after a short wait) and update the
    counters through :meth:`_count`.

    Parameters
    ----------
    queue_size : int
        Samples held between the receive thread and the reader (default 65536: over 9 s at 7 kHz).
    """

    _device_noun = "sensor"
    _item_noun = "sample"
    _worker_role = "receive"

    def __init__(self, *, queue_size: int = 65536) -> None:
        super().__init__(queue_size=queue_size)
        self._counts = dict.fromkeys(ForceStats.__dataclass_fields__, 0)

    # -- streaming
    def start(self) -> None:
        """Start streaming; resets :attr:`stats` and the queue."""
        self._require_open()
        if self._streaming:
            return
        with self._lock:
            self._counts = dict.fromkeys(ForceStats.__dataclass_fields__, 0)
        self._begin_streaming(self._receive_loop)

    def read(self, timeout_s: float = 1.0) -> ForceSample:
        """The next sample, oldest first; DeviceTimeoutError if none arrives within ``timeout_s``."""

        def detail() -> str:
            st = self.stats
            return f"received {st.received}, lost {st.lost}, protocol errors {st.protocol_errors}"

        return self._next_item(timeout_s, detail)

    def drain(self, max_samples: int | None = None) -> np.ndarray:
        """Every queued sample (up to ``max_samples``) as a FORCE_SAMPLE_DTYPE array, without waiting."""
        if max_samples is not None and (not isinstance(max_samples, int) or max_samples < 0):
            raise InvalidInputError(f"max_samples must be a non-negative int or None, got {max_samples!r}")
        items = []
        while max_samples is None or len(items) < max_samples:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, BaseException):
                self._error = item
                break
            items.append(item)
        out = np.empty(len(items), dtype=FORCE_SAMPLE_DTYPE)
        for i, s in enumerate(items):
            out[i] = (s.host_timestamp_s, s.sequence, s.device_sequence, s.status, s.ft)
        if not items and self._error is not None:
            raise self._error
        return out

    def bias(self) -> None:
        """Zero the sensor at the present load (the device's own bias / tare)."""
        self._require_open()
        self._do_bias()

    @property
    def stats(self) -> ForceStats:
        with self._lock:
            return ForceStats(**self._counts)

    # -- for subclasses
    def _count(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counts[name] += n

    def _receive_loop(self) -> None:
        stop = self._stop_event
        try:
            while not stop.is_set():
                for sample in self._do_receive():
                    try:
                        self._queue.put_nowait(sample)
                    except queue.Full:
                        self._count("dropped")
        except BaseException as exc:  # handed to the reader, after the samples received before it
            self._worker_failed(exc, "receiving")

    @abstractmethod
    def _do_bias(self) -> None: ...

    @abstractmethod
    def _do_receive(self) -> list[ForceSample]:
        """Receive thread: the samples that arrived, or [] after a short wait (<= 0.1 s)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"
