"""The STReSS wire protocol: a pure, byte-testable codec (no I/O). Documented in ``docs/protocols/stress.md``.

The STReSS display has no public wire protocol (FACTS: "No public wire protocol"), so this project defines one.
Every packet, in both directions, is::

    0xA5 0x5A | LEN (u8) | SEQ (u8) | CMD (u8) | PAYLOAD (LEN bytes) | CRC16 (u16, big endian)

The CRC is CRC-16/CCITT-FALSE (polynomial 0x1021, initial value 0xFFFF, no reflection, no final xor) over
``LEN SEQ CMD PAYLOAD``. A reply carries the request's SEQ and ``CMD | 0x80``; a refusal is ``NAK`` (0x7F) with an
error code. Contactor positions travel as int8 in 0.5 um steps (+/-63.5 um covers the +/-50 um range).

>>> packet = encode_packet(seq=7, command=Command.IDENTIFY)
>>> packet.hex()
'a55a000701452a'
>>> decoder = StreamDecoder()
>>> [Command(p.command) for p in decoder.feed(b"garbage" + packet)]
[<Command.IDENTIFY: 1>]

Version 2 adds timed, buffered playback: ``START_MOVIE`` sets a rate and an epoch on the firmware's clock,
``TIMED_FRAME`` carries a frame with its play tick, the firmware queues it in a bounded FIFO and applies it on its
own timer; ``STOP_MOVIE`` / ``REST`` / ``DISARM`` flush the FIFO at once.

>>> tick_time_us(700, rate_mhz=700_000)  # tick 700 at 700 Hz plays 1 s after the epoch
1000000
"""

from __future__ import annotations

import binascii
import enum
import numbers
import struct
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from skinstretch.drivers.errors import ProtocolError

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import FiniteFloat, NonNegativeInt, PositiveInt, validated_dataclass

SYNC = b"\xa5\x5a"
HEADER_SIZE = 5  # sync (2) + len + seq + cmd
CRC_SIZE = 2
OVERHEAD = HEADER_SIZE + CRC_SIZE
MAX_PAYLOAD = 255
REPLY_FLAG = 0x80

PROTOCOL_VERSION = 2  # 2: timed, buffered playback (START_MOVIE, TIMED_FRAME, STOP_MOVIE, READ_MOVIE)
ROWS = COLS = 10
N_CONTACTORS = ROWS * COLS
POSITION_STEP_UM = 0.5  # one int8 count
POSITION_CODE_MAX = 127
RANGE_UM = 50.0  # mechanical range of a contactor, seed 2 / Pasquero & Hayward 2003 (~ +/-50 um)
DEFAULT_BAUD = 2_000_000
DEFAULT_WATCHDOG_S = 0.050
DEFAULT_MAX_STEP_UM = 10.0
FIRMWARE_NAME_MAX = 32
FIFO_DEPTH = 128  # timed frames the firmware can hold: 183 ms at 700 Hz
TICK_LOG_DEPTH = 64  # ticks whose report (time, applied, sampled positions) waits for a reply to carry it: 91 ms
MAX_RATE_MHZ = 700_000  # 700 Hz, the STReSS refresh rate
MIN_RATE_MHZ = 1_000
MAX_START_DELAY_US = 1_000_000
NO_TICK = -1  # "none" in the signed tick fields


class Command(enum.IntEnum):
    """Request codes (host -> display). The reply uses ``code | 0x80``."""

    IDENTIFY = 0x01
    CONFIGURE = 0x02  # payload: watchdog_ms u16, max_step u8 (0.5 um counts)
    ARM = 0x03
    DISARM = 0x04
    ZERO = 0x05  # re-reference the position sensors (only when disarmed)
    FRAME = 0x06  # payload: 100 x int8 positions (0.5 um), row-major
    REST = 0x07  # every contactor back to 0 with the firmware's soft ramp
    READ_STATUS = 0x08
    START_MOVIE = 0x09  # payload: rate_mhz u32, n_frames u32 (0: open-ended), start_delay_us u32
    TIMED_FRAME = 0x0A  # payload: tick u32 + 100 x int8 positions: play at tick's time on the firmware clock
    STOP_MOVIE = 0x0B  # flush the FIFO, end the movie, hold the position
    READ_MOVIE = 0x0C  # movie counters + the oldest unreported tick report
    NAK = 0x7F  # reply only: payload u8 error code + u8 offending command


class Status(enum.IntFlag):
    """Status bits carried by every status reply and frame ack (u16)."""

    ARMED = 0x0001
    WATCHDOG_TRIPPED = 0x0002  # no frame within the watchdog time: contactors sent to rest, disarmed
    RESTING = 0x0004  # contactors ramping to / sitting at rest
    CLAMPED = 0x0008  # the firmware had to clamp a command (range or slew): the host sent an unsafe frame
    CRC_ERRORS = 0x0010  # at least one corrupted packet received since the last READ_STATUS
    SEQUENCE_GAP = 0x0020  # at least one frame sequence number skipped since the last READ_STATUS
    SATURATED = 0x0040  # a measured position is outside the int8 encoding
    ZEROED = 0x0080  # position sensors have been re-referenced since power-up
    MOVIE = 0x0100  # a timed movie is running (its timer ticks)
    LATE_FRAME = 0x0200  # a timed frame arrived at or after its play time (dropped) since the last READ_STATUS
    UNDERRUN = 0x0400  # a movie tick found no frame to play (position held) since the last READ_STATUS
    FIFO_REJECT = 0x0800  # a timed frame was refused (FIFO full, duplicate, past the end) since the last READ_STATUS


class NakCode(enum.IntEnum):
    """Why the display refused a request."""

    UNKNOWN_COMMAND = 1
    BAD_LENGTH = 2
    NOT_ARMED = 3
    ARMED = 4  # command only allowed while disarmed
    BAD_VALUE = 5
    MOVIE_RUNNING = 6  # an immediate FRAME while a timed movie runs
    NO_MOVIE = 7  # a TIMED_FRAME without a movie (never started, or ended by REST / DISARM / STOP / watchdog)


class Disposition(enum.IntEnum):
    """What the firmware did with a timed frame (in its reply)."""

    QUEUED = 0  # in the FIFO, will play at its tick
    LATE = 1  # arrived at or after its play time: dropped, counted in late_frames
    FIFO_FULL = 2  # tick at or beyond next_tick + FIFO_DEPTH: no room, refused (counted in fifo_rejects)
    DUPLICATE = 3  # a frame for that tick is already queued: the first one stays (counted in fifo_rejects)
    PAST_END = 4  # tick >= the movie's n_frames (counted in fifo_rejects)


class TickFlags(enum.IntFlag):
    """Flags of a tick report."""

    APPLIED = 0x01  # a frame was applied at this tick (otherwise: underrun, the position was held)
    CLAMPED = 0x02  # the firmware had to clamp that frame (range or slew)


@dataclass(frozen=True)
class Packet:
    """One decoded packet. ``end`` is the stream offset just past its last byte (decoder byte count)."""

    seq: int
    command: int
    payload: bytes
    end: int = 0

    @property
    def is_reply(self) -> bool:
        return bool(self.command & REPLY_FLAG) or self.command == Command.NAK

    @property
    def request_command(self) -> int:
        return self.command & ~REPLY_FLAG if self.command != Command.NAK else Command.NAK


def crc16_ccitt(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value of ``b"123456789"`` is 0x29B1)."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode_packet(*, seq: int, command: int, payload: bytes = b"") -> bytes:
    """Frame one packet. Raises InvalidInputError for an out-of-range seq/command or an oversized payload."""
    if not 0 <= int(seq) <= 255:
        raise InvalidInputError(f"seq must be in 0..255, got {seq!r}")
    if not 0 <= int(command) <= 255:
        raise InvalidInputError(f"command must be in 0..255, got {command!r}")
    payload = bytes(payload)
    if len(payload) > MAX_PAYLOAD:
        raise InvalidInputError(f"payload must be at most {MAX_PAYLOAD} bytes, got {len(payload)}")
    body = bytes((len(payload), int(seq), int(command))) + payload
    return SYNC + body + struct.pack(">H", crc16_ccitt(body))


def reply_command(command: int) -> int:
    """The reply code of a request code."""
    return int(command) | REPLY_FLAG


@dataclass
class DecoderCounters:
    """What the decoder had to throw away, for diagnostics (never silently lost: the counts are kept)."""

    skipped_bytes: int = 0
    crc_errors: int = 0  # complete packets whose CRC failed
    resyncs: int = 0  # announced packets abandoned because a valid packet was found inside them

    @property
    def bad_packets(self) -> int:
        return self.crc_errors + self.resyncs


class StreamDecoder:
    """Incremental decoder: feed any chunking of a byte stream, get whole packets out.

    Garbage before a sync, truncated packets and CRC failures are skipped; the decoder resynchronises on the
    next sync word (a failed CRC rescans from the byte after the bad sync, so a packet hidden inside garbage is
    still found). What was skipped is counted in :attr:`counters`. ``feed`` never raises on bad bytes.
    """

    def __init__(self, *, max_buffer: int = 4096) -> None:
        self._buffer = bytearray()
        self._consumed = 0  # absolute stream offset of _buffer[0]
        self._max_buffer = max_buffer
        self.counters = DecoderCounters()

    @property
    def pending(self) -> int:
        """Bytes held waiting for the rest of a packet."""
        return len(self._buffer)

    @property
    def position(self) -> int:
        """Total number of bytes fed so far."""
        return self._consumed + len(self._buffer)

    def reset(self) -> None:
        self.counters.skipped_bytes += len(self._buffer)
        self._consumed += len(self._buffer)
        self._buffer.clear()

    def _drop(self, n: int, *, skipped: bool) -> None:
        del self._buffer[:n]
        self._consumed += n
        if skipped:
            self.counters.skipped_bytes += n

    def _complete_packet_after(self, start: int) -> int | None:
        """Offset of the first later sync that begins a complete packet with a good CRC, or None."""
        buf = self._buffer
        at = buf.find(SYNC, start + 1)
        while at >= 0 and len(buf) - at >= OVERHEAD:
            total = HEADER_SIZE + buf[at + 2] + CRC_SIZE
            if len(buf) - at >= total:
                (crc,) = struct.unpack_from(">H", buf, at + total - CRC_SIZE)
                if crc == crc16_ccitt(bytes(buf[at + 2:at + total - CRC_SIZE])):
                    return at
            at = buf.find(SYNC, at + 1)
        return None

    def feed(self, data: bytes) -> list[Packet]:
        """Add bytes; return every packet completed by them, in stream order."""
        self._buffer += data
        out: list[Packet] = []
        buf = self._buffer
        while True:
            start = buf.find(SYNC)
            if start < 0:
                # keep a trailing 0xA5: it may be the first half of a sync word
                keep = 1 if buf[-1:] == SYNC[:1] else 0
                self._drop(len(buf) - keep, skipped=True)
                break
            if start:
                self._drop(start, skipped=True)
            if len(buf) < HEADER_SIZE:
                break
            length = buf[2]
            total = HEADER_SIZE + length + CRC_SIZE
            if len(buf) < total:
                # A sync word in garbage can announce a long packet that never comes. If a complete, valid
                # packet already sits behind it, the candidate was garbage: skip to the real one now rather than
                # after LEN more bytes (a false CRC match needs 1 in 65536 luck).
                later = self._complete_packet_after(0)
                if later is None:
                    break
                self.counters.resyncs += 1
                self._drop(later, skipped=True)
                continue
            body = bytes(buf[2:HEADER_SIZE + length])
            (crc,) = struct.unpack_from(">H", buf, HEADER_SIZE + length)
            if crc != crc16_ccitt(body):
                self.counters.crc_errors += 1
                self._drop(1, skipped=True)  # rescan from the next byte: resynchronise
                continue
            packet = Packet(seq=buf[3], command=buf[4], payload=body[3:], end=self._consumed + total)
            self._drop(total, skipped=False)
            out.append(packet)
        return out


# ---- payload codecs ---------------------------------------------------------------------------------------------

def encode_positions(positions_um: np.ndarray) -> bytes:
    """(10, 10) um -> 100 int8 counts of 0.5 um, row-major. Values must already be within the encodable range."""
    a = np.asarray(positions_um, dtype=float)
    if a.shape != (ROWS, COLS):
        raise InvalidInputError(f"positions_um must have shape (10, 10), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InvalidInputError("positions_um must be finite (clamp with skinstretch.drivers.display.safety first)")
    counts = np.rint(a / POSITION_STEP_UM)
    if np.any(np.abs(counts) > POSITION_CODE_MAX):
        raise InvalidInputError(f"positions_um outside +/-{POSITION_CODE_MAX * POSITION_STEP_UM} um: "
                                f"min {a.min()}, max {a.max()}")
    return counts.astype(np.int8).tobytes()


def decode_positions(data: bytes) -> np.ndarray:
    """100 int8 counts -> (10, 10) float um."""
    if len(data) != N_CONTACTORS:
        raise ProtocolError(f"positions need {N_CONTACTORS} bytes, got {len(data)}")
    return np.frombuffer(bytes(data), dtype=np.int8).astype(float).reshape(ROWS, COLS) * POSITION_STEP_UM


@dataclass(frozen=True)
class Identity:
    """IDENTIFY reply."""

    protocol_version: int
    rows: int
    cols: int
    range_um: float
    max_rate_hz: int
    firmware: str

    def encode(self) -> bytes:
        name = self.firmware.encode("ascii", "replace")[:FIRMWARE_NAME_MAX]
        return struct.pack(">BBBBH", self.protocol_version, self.rows, self.cols, int(self.range_um),
                           self.max_rate_hz) + name

    @classmethod
    def decode(cls, payload: bytes) -> "Identity":
        if len(payload) < 6:
            raise ProtocolError(f"IDENTIFY reply too short: {len(payload)} bytes")
        version, rows, cols, range_um, rate = struct.unpack_from(">BBBBH", payload)
        return cls(version, rows, cols, float(range_um), rate, payload[6:].decode("ascii", "replace"))


@validated_dataclass
class WatchdogConfig:
    """CONFIGURE payload: watchdog time and the firmware's own per-frame slew limit."""

    watchdog_s: FiniteFloat = Field(default=DEFAULT_WATCHDOG_S, ge=0.001, le=65.535)  # u16 milliseconds
    max_step_um: FiniteFloat = Field(default=DEFAULT_MAX_STEP_UM, ge=POSITION_STEP_UM, le=2 * RANGE_UM)

    def encode(self) -> bytes:
        return struct.pack(">HB", round(self.watchdog_s * 1000), int(self.max_step_um / POSITION_STEP_UM))

    @classmethod
    def decode(cls, payload: bytes) -> "WatchdogConfig":
        if len(payload) != 3:
            raise ProtocolError(f"CONFIGURE payload must be 3 bytes, got {len(payload)}")
        ms, step = struct.unpack(">HB", payload)
        try:
            return cls(watchdog_s=ms / 1000.0, max_step_um=step * POSITION_STEP_UM)
        except InvalidInputError as exc:
            raise ProtocolError(f"CONFIGURE values out of range: {exc}") from exc


@dataclass(frozen=True)
class StatusReport:
    """READ_STATUS reply: status bits, measured positions and the firmware's counters."""

    status: Status
    positions_um: np.ndarray = field(repr=False)
    frames_received: int
    crc_errors: int
    sequence_gaps: int
    watchdog_trips: int

    def encode(self) -> bytes:
        return (struct.pack(">H", int(self.status)) + _encode_measured(self.positions_um)
                + struct.pack(">IHHH", self.frames_received & 0xFFFFFFFF, min(self.crc_errors, 0xFFFF),
                              min(self.sequence_gaps, 0xFFFF), min(self.watchdog_trips, 0xFFFF)))

    @classmethod
    def decode(cls, payload: bytes) -> "StatusReport":
        if len(payload) != 2 + N_CONTACTORS + 10:
            raise ProtocolError(f"status reply must be {2 + N_CONTACTORS + 10} bytes, got {len(payload)}")
        (status,) = struct.unpack_from(">H", payload)
        positions = decode_positions(payload[2:2 + N_CONTACTORS])
        frames, crc, gaps, trips = struct.unpack_from(">IHHH", payload, 2 + N_CONTACTORS)
        return cls(Status(status), positions, frames, crc, gaps, trips)


def _encode_measured(positions_um: np.ndarray) -> bytes:
    """Measured positions saturate at the int8 limits (the SATURATED status bit says so)."""
    counts = np.clip(np.rint(np.asarray(positions_um, float) / POSITION_STEP_UM), -128, 127)
    return counts.astype(np.int8).tobytes()


def encode_frame_ack(status: int, measured_um: np.ndarray) -> bytes:
    """FRAME reply payload: status u16 + 100 int8 measured positions (sampled when the frame arrived)."""
    return struct.pack(">H", int(status)) + _encode_measured(measured_um)


def decode_frame_ack(payload: bytes) -> tuple[Status, np.ndarray]:
    if len(payload) != 2 + N_CONTACTORS:
        raise ProtocolError(f"frame ack must be {2 + N_CONTACTORS} bytes, got {len(payload)}")
    (status,) = struct.unpack_from(">H", payload)
    return Status(status), decode_positions(payload[2:])


def encode_status(status: int) -> bytes:
    """Reply payload of CONFIGURE, ARM, DISARM, ZERO and REST: the status word."""
    return struct.pack(">H", int(status))


def decode_status(payload: bytes) -> Status:
    if len(payload) != 2:
        raise ProtocolError(f"status payload must be 2 bytes, got {len(payload)}")
    return Status(struct.unpack(">H", payload)[0])


def encode_nak(code: NakCode, command: int) -> bytes:
    return bytes((int(code), int(command) & 0xFF))


def decode_nak(payload: bytes) -> tuple[int, int]:
    if len(payload) != 2:
        raise ProtocolError(f"NAK payload must be 2 bytes, got {len(payload)}")
    return payload[0], payload[1]


# ---- timed playback (protocol version 2) ------------------------------------------------------------------------

def tick_time_us(tick: int, *, rate_mhz: int) -> int:
    """Play time of ``tick`` in whole microseconds after the movie epoch (the firmware's 1 MHz timer).

    Integer arithmetic, so host and firmware agree exactly and the period never drifts: at 700 Hz the timer
    alternates 1428 and 1429 us.
    """
    return (int(tick) * 1_000_000_000) // int(rate_mhz)


def rate_to_mhz(rate_hz: float) -> int:
    """A frame rate in Hz as the wire's millihertz, checked against 1..700 Hz."""
    if isinstance(rate_hz, bool) or not (isinstance(rate_hz, numbers.Real) and np.isfinite(rate_hz)):
        raise InvalidInputError(f"rate_hz must be a finite number, got {rate_hz!r}")
    mhz = int(round(rate_hz * 1000))
    if not MIN_RATE_MHZ <= mhz <= MAX_RATE_MHZ:
        raise InvalidInputError(f"rate_hz must be in 1..700 Hz, got {rate_hz!r}")
    return mhz


def _i32(value: int) -> int:
    return int(max(-2**31, min(2**31 - 1, value)))


@validated_dataclass
class MovieStart:
    """START_MOVIE payload: tick k plays ``start_delay_us + tick_time_us(k)`` after the command arrived."""

    rate_mhz: PositiveInt = Field(ge=MIN_RATE_MHZ, le=MAX_RATE_MHZ)
    n_frames: NonNegativeInt = Field(le=0xFFFFFFFF)  # ticks 0..n_frames-1; 0 = open-ended
    start_delay_us: NonNegativeInt = Field(le=MAX_START_DELAY_US)

    def encode(self) -> bytes:
        return struct.pack(">III", self.rate_mhz, self.n_frames, self.start_delay_us)

    @classmethod
    def decode(cls, payload: bytes) -> "MovieStart":
        if len(payload) != 12:
            raise ProtocolError(f"START_MOVIE payload must be 12 bytes, got {len(payload)}")
        try:
            return cls(*struct.unpack(">III", payload))
        except InvalidInputError as exc:
            raise ProtocolError(f"START_MOVIE values out of range: {exc}") from exc


def encode_timed_frame(tick: int, positions: bytes) -> bytes:
    """TIMED_FRAME payload: tick u32 + the 100 encoded positions (:func:`encode_positions`)."""
    if not 0 <= int(tick) <= 0xFFFFFFFF:
        raise InvalidInputError(f"tick must be in 0..2**32-1, got {tick!r}")
    if len(positions) != N_CONTACTORS:
        raise InvalidInputError(f"positions must be {N_CONTACTORS} encoded bytes, got {len(positions)}")
    return struct.pack(">I", int(tick)) + bytes(positions)


def decode_timed_frame(payload: bytes) -> tuple[int, np.ndarray]:
    """TIMED_FRAME payload -> (tick, (10, 10) um)."""
    if len(payload) != 4 + N_CONTACTORS:
        raise ProtocolError(f"TIMED_FRAME payload must be {4 + N_CONTACTORS} bytes, got {len(payload)}")
    (tick,) = struct.unpack_from(">I", payload)
    return tick, decode_positions(payload[4:])


@dataclass(frozen=True)
class TickReport:
    """What happened at one movie tick: its firmware time, whether a frame was applied, the positions sampled
    at the tick *before* that frame took effect (the response to the previous tick's frame).

    ``tick == NO_TICK`` means "no report" (nothing waiting in the tick log); the other fields are then zero.
    """

    tick: int = NO_TICK
    time_us: int = 0  # firmware clock, microseconds after the movie epoch
    flags: TickFlags = TickFlags(0)
    sample_um: np.ndarray = field(default_factory=lambda: np.zeros((ROWS, COLS)), repr=False)

    SIZE = 4 + 4 + 1 + N_CONTACTORS

    @property
    def present(self) -> bool:
        return self.tick >= 0

    @property
    def applied(self) -> bool:
        return bool(self.flags & TickFlags.APPLIED)

    def encode(self) -> bytes:
        return (struct.pack(">iiB", _i32(self.tick), _i32(self.time_us), int(self.flags) & 0xFF)
                + _encode_measured(self.sample_um))

    @classmethod
    def decode(cls, payload: bytes) -> "TickReport":
        if len(payload) != cls.SIZE:
            raise ProtocolError(f"tick report must be {cls.SIZE} bytes, got {len(payload)}")
        tick, time_us, flags = struct.unpack_from(">iiB", payload)
        if tick < NO_TICK:
            raise ProtocolError(f"tick report has a negative tick {tick}")
        return cls(tick, time_us, TickFlags(flags & 0x03), decode_positions(payload[9:]))


@dataclass(frozen=True)
class TimedFrameReply:
    """TIMED_FRAME reply: what became of the frame, the FIFO, the firmware time of its arrival, running
    counters, and one tick report (the oldest the firmware had not reported yet)."""

    status: Status
    tick: int  # the frame's tick (echoed)
    disposition: Disposition
    fifo_fill: int  # frames in the FIFO after this one was handled
    rx_time_us: int  # firmware clock when its last byte arrived, microseconds after the epoch (negative: before)
    late_frames: int  # running count, modulo 65536
    underruns: int  # running count, modulo 65536
    report: TickReport = field(repr=False)

    SIZE = 2 + 4 + 1 + 1 + 4 + 2 + 2 + TickReport.SIZE

    def encode(self) -> bytes:
        return (struct.pack(">HIBBiHH", int(self.status), self.tick & 0xFFFFFFFF, int(self.disposition),
                            min(self.fifo_fill, 255), _i32(self.rx_time_us), self.late_frames & 0xFFFF,
                            self.underruns & 0xFFFF) + self.report.encode())

    @classmethod
    def decode(cls, payload: bytes) -> "TimedFrameReply":
        if len(payload) != cls.SIZE:
            raise ProtocolError(f"timed frame reply must be {cls.SIZE} bytes, got {len(payload)}")
        status, tick, disposition, fill, rx, late, under = struct.unpack_from(">HIBBiHH", payload)
        if disposition not in Disposition._value2member_map_:
            raise ProtocolError(f"timed frame reply has an unknown disposition {disposition}")
        report = TickReport.decode(payload[cls.SIZE - TickReport.SIZE:])
        return cls(Status(status), tick, Disposition(disposition), fill, rx, late, under, report)


@dataclass(frozen=True)
class MovieStatus:
    """START_MOVIE / STOP_MOVIE / READ_MOVIE reply: the movie's counters (kept after it ends, until the next
    START_MOVIE), the firmware time now, and one tick report (so a host can drain the tick log at the end)."""

    status: Status
    fifo_depth: int
    fifo_fill: int
    rate_mhz: int
    n_frames: int
    time_us: int  # firmware clock now, microseconds after the epoch (negative before it)
    next_tick: int  # the next tick the timer will play (= ticks played or underrun so far)
    frames_queued: int
    frames_played: int
    late_frames: int
    underruns: int
    fifo_rejects: int
    reports_lost: int  # tick reports overwritten before a reply could carry them (tick log full)
    report: TickReport = field(default_factory=TickReport, repr=False)

    SIZE = 2 + 1 + 1 + 4 + 4 + 4 + 4 * 7 + TickReport.SIZE
    _FORMAT = ">HBBIIiIIIIIII"

    @property
    def running(self) -> bool:
        return bool(self.status & Status.MOVIE)

    def encode(self) -> bytes:
        counters = [min(int(v), 0xFFFFFFFF) for v in (self.next_tick, self.frames_queued, self.frames_played,
                                                      self.late_frames, self.underruns, self.fifo_rejects,
                                                      self.reports_lost)]
        return (struct.pack(self._FORMAT, int(self.status), min(self.fifo_depth, 255), min(self.fifo_fill, 255),
                            self.rate_mhz, self.n_frames, _i32(self.time_us), *counters) + self.report.encode())

    @classmethod
    def decode(cls, payload: bytes) -> "MovieStatus":
        if len(payload) != cls.SIZE:
            raise ProtocolError(f"movie status must be {cls.SIZE} bytes, got {len(payload)}")
        fields_ = struct.unpack_from(cls._FORMAT, payload)
        return cls(Status(fields_[0]), *fields_[1:], report=TickReport.decode(payload[cls.SIZE - TickReport.SIZE:]))


def link_budget(*, rate_hz: float, baud: float, bits_per_byte: int = 10) -> dict[str, float]:
    """Bytes and line occupancy of streaming at ``rate_hz`` over a UART (8N1: 10 bits a byte).

    >>> link_budget(rate_hz=700, baud=2_000_000)["min_baud"]
    749000
    """
    frame_bytes = OVERHEAD + N_CONTACTORS
    ack_bytes = OVERHEAD + 2 + N_CONTACTORS
    timed_bytes = OVERHEAD + 4 + N_CONTACTORS
    timed_reply_bytes = OVERHEAD + TimedFrameReply.SIZE
    byte_s = bits_per_byte / baud
    return {
        "frame_bytes": frame_bytes,
        "ack_bytes": ack_bytes,
        "frame_time_s": frame_bytes * byte_s,
        "ack_time_s": ack_bytes * byte_s,
        "frame_utilisation": frame_bytes * byte_s * rate_hz,
        "ack_utilisation": ack_bytes * byte_s * rate_hz,
        "min_baud": frame_bytes * bits_per_byte * rate_hz,
        "timed_frame_bytes": timed_bytes,
        "timed_reply_bytes": timed_reply_bytes,
        "timed_frame_utilisation": timed_bytes * byte_s * rate_hz,
        "timed_reply_utilisation": timed_reply_bytes * byte_s * rate_hz,
    }
