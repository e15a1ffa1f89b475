"""The STReSS firmware twin's wire: a byte link paced at the line rate, with fault switches, on a replaceable clock.

A pty or an in-process pipe ignores baud rates (shared FACTS), so :class:`PacedLink` models the line itself: bytes
arrive one byte-time apart at the line rate, replies leave at the line rate, plus fault injection (dropped /
corrupted bytes, stalled link, vanished link) from a seeded generator (:class:`LinkFaults`). Time comes from a
replaceable clock (:class:`RealClock` or :class:`ManualClock`) so tests are deterministic.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import TYPE_CHECKING, Protocol

import numpy as np
from pydantic import Field

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import FiniteFloat, NonNegativeInt, validated_dataclass

if TYPE_CHECKING:
    from .stress_firmware import StressFirmware

__all__ = ["Clock", "RealClock", "ManualClock", "LinkVanished", "LinkFaults", "PacedLink"]


class Clock(Protocol):
    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class RealClock:
    """``time.perf_counter`` (CLOCK_MONOTONIC on Linux, comparable across processes)."""

    def now(self) -> float:
        return time.perf_counter()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class ManualClock:
    """A clock that only moves when told; ``sleep`` advances it at once (deterministic tests)."""

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._lock = threading.Lock()

    def now(self) -> float:
        return self._t

    def sleep(self, seconds: float) -> None:
        self.advance(max(seconds, 0.0))

    def advance(self, seconds: float) -> None:
        with self._lock:
            self._t += seconds


class LinkVanished(ConnectionError):
    """The simulated link is gone (unplugged cable, USB device removed)."""


@validated_dataclass
class LinkFaults:
    """Fault injection. Rates are per byte; ``*_after_frames`` count FRAME packets received."""

    drop_rate: FiniteFloat = Field(default=0.0, ge=0, le=1)
    corrupt_rate: FiniteFloat = Field(default=0.0, ge=0, le=1)
    stall_after_frames: NonNegativeInt | None = None
    vanish_after_frames: NonNegativeInt | None = None

    @classmethod
    def parse(cls, text: str) -> "LinkFaults":
        """``"drop:0.001,corrupt:0.001,stall_after:100,vanish_after:200"`` (any subset, "" for none)."""
        names = {"drop": "drop_rate", "corrupt": "corrupt_rate", "stall_after": "stall_after_frames",
                 "vanish_after": "vanish_after_frames"}
        values = {}
        for item in filter(None, (s.strip() for s in text.split(","))):
            key, _, value = item.partition(":")
            if key not in names or not value:
                raise InvalidInputError(f"faults item {item!r} is not one of {sorted(names)} with a value")
            try:
                values[names[key]] = float(value) if key in ("drop", "corrupt") else int(value)
            except ValueError as exc:
                raise InvalidInputError(f"faults item {item!r} has a bad number") from exc
        return cls(**values)


class PacedLink:
    """The firmware behind a wire of a given byte time, with faults. Thread-safe.

    Parameters
    ----------
    firmware : StressFirmware
    byte_time_s : float
        Time one byte occupies the line (10 / baud for 8N1 UART).
    latency_s : float
        Fixed delay added to each delivery (USB microframes; 0 for a UART).
    processing_s : float
        Firmware time between the end of a request and the start of its reply.
    """

    def __init__(self, firmware: StressFirmware, *, clock: Clock, byte_time_s: float, latency_s: float = 0.0,
                 processing_s: float = 20e-6, faults: LinkFaults = LinkFaults(), seed: int = 0) -> None:
        if not byte_time_s > 0:
            raise InvalidInputError(f"byte_time_s must be > 0, got {byte_time_s!r}")
        self.firmware = firmware
        firmware.wall_clock = clock.now  # the firmware records when the simulator actually got to each event
        self.clock = clock
        self.byte_time_s = float(byte_time_s)
        self.latency_s = float(latency_s)
        self.processing_s = float(processing_s)
        self.faults = faults
        self._rng = np.random.default_rng(seed)
        self._decoder = sp.StreamDecoder()
        self._rx: deque[list] = deque()  # [t_first_byte_done, unused, bytes, n_fed]
        self._rx_free = -math.inf
        self._tx: deque[list] = deque()  # [t_first_byte_delivered, bytes, n_delivered]
        self._tx_free = -math.inf
        self._lock = threading.RLock()
        self.stalled = False
        self.vanished = False
        self.host_bytes_in = 0

    @classmethod
    def uart(cls, firmware: StressFirmware, *, clock: Clock, baud: int = sp.DEFAULT_BAUD, **kw) -> "PacedLink":
        if not (isinstance(baud, int) and 9600 <= baud <= 20_000_000):
            raise InvalidInputError(f"baud must be an int in 9600..20e6, got {baud!r}")
        return cls(firmware, clock=clock, byte_time_s=10.0 / baud, **kw)

    @classmethod
    def usb_high_speed(cls, firmware: StressFirmware, *, clock: Clock, **kw) -> "PacedLink":
        # 480 Mbit/s with ~70 % bulk efficiency; a reply waits for the next 125 us microframe poll
        return cls(firmware, clock=clock, byte_time_s=8 / (480e6 * 0.7), latency_s=125e-6, **kw)

    # -- fault switches --
    def stall(self) -> None:
        """From now on the link carries nothing in either direction (the firmware keeps running)."""
        with self._lock:
            self.stalled = True

    def vanish(self) -> None:
        """The link disappears: every host access raises LinkVanished; the firmware's watchdog still runs."""
        with self._lock:
            self.vanished = True

    def _damage(self, data: bytes) -> bytes:
        f = self.faults
        if not data or (f.drop_rate == 0 and f.corrupt_rate == 0):
            return data
        a = np.frombuffer(data, dtype=np.uint8).copy()
        if f.corrupt_rate:
            hit = self._rng.random(a.size) < f.corrupt_rate
            a[hit] ^= self._rng.integers(1, 256, hit.sum(), dtype=np.uint8)
        if f.drop_rate:
            a = a[self._rng.random(a.size) >= f.drop_rate]
        return a.tobytes()

    # -- host side --
    def host_write(self, data: bytes) -> None:
        with self._lock:
            now = self.clock.now()
            self._process(now)
            if self.vanished:
                raise LinkVanished("stresssim link vanished")
            self.host_bytes_in += len(data)
            if self.stalled or not data:
                return
            data = self._damage(bytes(data))
            if not data:
                return
            start = max(now, self._rx_free)
            # element 0: when the chunk's first byte has completely arrived
            self._rx.append([start + self.latency_s + self.byte_time_s, 0, data, 0])
            self._rx_free = start + len(data) * self.byte_time_s

    def host_read(self, max_bytes: int) -> bytes:
        """Replies whose last byte has been delivered (up to ``max_bytes``).

        A reply is handed over whole once its last byte is due: one wake-up per reply instead of one per byte
        (the host cannot use a partial packet anyway). ``max_bytes`` may split a reply.
        """
        with self._lock:
            now = self.clock.now()
            self._process(now)
            if self.vanished:
                raise LinkVanished("stresssim link vanished")
            out = bytearray()
            while self._tx and len(out) < max_bytes:
                chunk = self._tx[0]
                t0, data, done = chunk
                ready = min(len(data), int((now - t0) / self.byte_time_s + 1e-6) + 1) if now >= t0 - 1e-9 else 0
                if ready < len(data):
                    break
                take = min(ready - done, max_bytes - len(out))
                if take <= 0:
                    break
                out += data[done:done + take]
                chunk[2] = done + take
                if chunk[2] == len(data):
                    self._tx.popleft()
                else:
                    break
            return bytes(out)

    def next_event(self) -> float | None:
        """Earliest time something changes for the host or the firmware (None: nothing pending)."""
        with self._lock:
            times = []
            if self._rx:  # requests matter when complete; a chunk is usually one packet
                c = self._rx[0]
                times.append(c[0] + (len(c[2]) - 1) * self.byte_time_s)
            if self._tx:
                t0, data, done = self._tx[0]
                times.append(t0 + (len(data) - 1) * self.byte_time_s)
            deadline = self.firmware.next_deadline()
            if deadline is not None:
                times.append(deadline)
            return min(times) if times else None

    def reset_host_input(self) -> None:
        with self._lock:
            self._tx.clear()

    def advance(self) -> None:
        """Let the firmware catch up with the clock (watchdog, pending requests)."""
        with self._lock:
            self._process(self.clock.now())

    # -- firmware side --
    def _process(self, now: float) -> None:
        while self._rx:
            chunk = self._rx[0]
            t_first, pos, data, fed = chunk
            if now < t_first - 1e-9:
                break
            ready = min(len(data), int((now - t_first) / self.byte_time_s + 1e-6) + 1)
            if ready > fed:
                base = self._decoder.position
                for packet in self._decoder.feed(data[fed:ready]):
                    # the packet is complete when its last byte has arrived
                    t_packet = t_first + (fed + (packet.end - base) - 1) * self.byte_time_s
                    self.firmware.note_crc_errors(self._decoder.counters.bad_packets)
                    self._on_packet(packet, t_packet)
                chunk[3] = ready
                self.firmware.note_crc_errors(self._decoder.counters.bad_packets)
            if ready < len(data):
                break
            self._rx.popleft()
        self.firmware.advance(now)

    def _on_packet(self, packet: sp.Packet, t: float) -> None:
        fw = self.firmware
        reply = fw.handle(packet, t)
        if packet.command in (sp.Command.FRAME, sp.Command.TIMED_FRAME):
            n = fw.frames_received
            f = self.faults
            if f.vanish_after_frames is not None and n >= f.vanish_after_frames:
                self.vanished = True
            if f.stall_after_frames is not None and n >= f.stall_after_frames:
                self.stalled = True
        if not reply or self.stalled:
            return
        reply = self._damage(reply)
        if not reply:
            return
        start = max(t + self.processing_s, self._tx_free)
        self._tx.append([start + self.latency_s + self.byte_time_s, reply, 0])
        self._tx_free = start + len(reply) * self.byte_time_s

