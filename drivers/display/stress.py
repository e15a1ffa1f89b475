"""The STReSS 10x10 display driver: the :mod:`stress_protocol` codec over any :class:`Transport` it owns.

>>> # experiments pick the transport; e.g. a real adapter:
>>> # display = StressDisplay(SerialTransport("/dev/ttyUSB0", baudrate=2_000_000))
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict, deque
from typing import Callable

import numpy as np

from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError, ProtocolError

from skinstretch.processing.errors import InvalidInputError

from . import stress_protocol as sp
from .base import DisplayInfo, FrameAck, TactileDisplay, TimedFrameAck, TimedReceipt
from .transports import Transport


#: How long a command waits for its reply once the link has been declared dead (see StressDisplay._transact).
LOST_LINK_WAIT_S = 0.005


class StressDisplay(TactileDisplay):
    """STReSS display over a serial or USB transport.

    Parameters
    ----------
    transport : Transport
        The link; owned (closed by :meth:`close`).
    reply_timeout_s : float, keyword-only
        How long a command waits for its reply before one retry (commands are idempotent).
    ack_timeout_s : float, keyword-only
        A frame ack older than this is written off as lost (counted in :attr:`lost_acks`).
    link_timeout_s : float, keyword-only
        No byte at all for this long while frames are outstanding: the link is declared dead
        (DeviceTimeoutError).
    clock : callable, keyword-only
        Host clock (``time.perf_counter``); replaceable for tests.
    **limits
        ``range_um``, ``max_step_um``, ``watchdog_s`` (see :class:`TactileDisplay`).

    Timed playback (protocol version 2): :meth:`start_movie`, :meth:`send_timed`; each TIMED_FRAME reply becomes a
    :class:`TimedReceipt` (:meth:`take_receipts`) and, when it carries a tick report, a :class:`TimedFrameAck`
    measurement (:meth:`collect_acks`). A version-1 firmware refuses START_MOVIE (``UNKNOWN_COMMAND``).
    """

    RECEIPT_HISTORY = 8192  # receipts nobody took are dropped beyond this (counted in receipts_dropped)

    def __init__(self, transport: Transport, *, reply_timeout_s: float = 0.05, ack_timeout_s: float = 0.05,
                 link_timeout_s: float = 0.2, clock: Callable[[], float] = time.perf_counter, **limits) -> None:
        super().__init__(**limits)
        if not isinstance(transport, Transport):
            raise InvalidInputError(f"transport must be a Transport, got {type(transport).__name__}")
        for name, value in (("reply_timeout_s", reply_timeout_s), ("ack_timeout_s", ack_timeout_s),
                            ("link_timeout_s", link_timeout_s)):
            if not (np.isfinite(value) and 0 < value <= 10):
                raise InvalidInputError(f"{name} must be in (0, 10] s, got {value!r}")
        self.transport = transport
        self.reply_timeout_s = float(reply_timeout_s)
        self.ack_timeout_s = float(ack_timeout_s)
        self.link_timeout_s = float(link_timeout_s)
        self._clock = clock
        self._decoder = sp.StreamDecoder()
        self._seq = 0
        # seq -> (command, sent_at, tick or None for an immediate frame)
        self._outstanding: OrderedDict[int, tuple[np.ndarray, float, int | None]] = OrderedDict()
        self._early_acks: list[FrameAck] = []
        self._receipts: deque[TimedReceipt] = deque()
        self.receipts_dropped = 0
        # timed movie bookkeeping for the measurement records: what was sent for each recent tick
        self._tick_sent: dict[int, tuple[np.ndarray, float]] = {}
        self._in_force = np.zeros((sp.ROWS, sp.COLS))  # command in force after the last reported tick
        self._reported_tick = sp.NO_TICK
        self._expect_since: float | None = None  # first send after the last received byte
        self._link_lost: str | None = None  # why the link was declared dead (cleared by the next byte received)
        self._frame_refusal: str | None = None
        self.lost_acks = 0
        self.naks: list[tuple[int, int]] = []
        self._closed = False

    # ---- plumbing ----------------------------------------------------------------------------------------------

    @property
    def outstanding(self) -> int:
        return len(self._outstanding)

    @property
    def decoder_counters(self) -> sp.DecoderCounters:
        return self._decoder.counters

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _send(self, command: int, payload: bytes = b"") -> tuple[int, float]:
        if self._closed:
            raise DeviceError("the display is closed")
        seq = self._next_seq()
        packet = sp.encode_packet(seq=seq, command=command, payload=payload)
        sent_at = self._clock()
        self.transport.write(packet)
        if self._expect_since is None:
            self._expect_since = sent_at
        return seq, sent_at

    def _pump(self, timeout_s: float) -> list[sp.Packet]:
        """Read what arrives within ``timeout_s`` (returns at the first chunk) and decode it."""
        data = self.transport.read(4096, timeout_s=timeout_s)
        if not data:
            return []
        self._expect_since = None
        self._link_lost = None
        packets = []
        for packet in self._decoder.feed(data):
            if packet.command == sp.reply_command(sp.Command.FRAME):
                self._accept_frame_ack(packet)
            elif packet.command == sp.reply_command(sp.Command.TIMED_FRAME):
                self._accept_timed_reply(packet)
            elif packet.command == sp.Command.NAK and packet.seq in self._outstanding:
                # a refused frame: the firmware is not armed any more (watchdog trip) or saw a bad frame
                del self._outstanding[packet.seq]
                try:
                    code, _ = sp.decode_nak(packet.payload)
                except ProtocolError:
                    code = 0
                self.naks.append((code, int(sp.Command.FRAME)))
                name = sp.NakCode(code).name if code in sp.NakCode._value2member_map_ else str(code)
                self._frame_refusal = f"display refused frame {packet.seq}: {name}"
            else:
                packets.append(packet)
        return packets

    def _accept_frame_ack(self, packet: sp.Packet) -> None:
        entry = self._outstanding.get(packet.seq)
        if entry is None or entry[2] is not None:
            return  # an ack we had written off (late), a duplicate, or not an immediate frame's
        del self._outstanding[packet.seq]
        command, sent_at, _ = entry
        try:
            status, measured = sp.decode_frame_ack(packet.payload)
        except ProtocolError:
            self.lost_acks += 1
            return
        self._early_acks.append(FrameAck(packet.seq, status, measured, command, sent_at, self._clock()))

    def _accept_timed_reply(self, packet: sp.Packet) -> None:
        entry = self._outstanding.get(packet.seq)
        if entry is None or entry[2] is None:
            return  # written off, flushed by a stop, or a duplicate
        del self._outstanding[packet.seq]
        command, sent_at, tick = entry
        try:
            reply = sp.TimedFrameReply.decode(packet.payload)
        except ProtocolError:
            self.lost_acks += 1
            return
        received_at = self._clock()
        if len(self._receipts) >= self.RECEIPT_HISTORY:
            self._receipts.popleft()
            self.receipts_dropped += 1
        self._receipts.append(TimedReceipt(packet.seq, tick, command, reply, sent_at, received_at))
        self._file_tick_report(reply.report, reply.status, received_at)

    def _file_tick_report(self, report: sp.TickReport, status: sp.Status, received_at: float) -> None:
        """Turn a tick report into a measurement record (a :class:`TimedFrameAck`) for :meth:`collect_acks`."""
        if not report.present or report.tick <= self._reported_tick:
            return
        # reports come oldest first; one lost with its reply leaves the ticks in between unreported: the command
        # in force is then the last one sent up to the tick (a lost frame is as likely as a lost reply; rare)
        for j in range(max(self._reported_tick + 1, report.tick - 2 * sp.FIFO_DEPTH), report.tick):
            if j in self._tick_sent:
                self._in_force = self._tick_sent[j][0]
        sent = self._tick_sent.get(report.tick)
        if report.applied and sent is not None:
            self._in_force = sent[0]
        self._reported_tick = report.tick
        while self._tick_sent:  # ticks were sent in increasing order: the oldest entries come first
            oldest = next(iter(self._tick_sent))
            if oldest > report.tick:
                break
            del self._tick_sent[oldest]
        self._early_acks.append(TimedFrameAck(
            report.tick & 0xFF, status, report.sample_um, self._in_force,
            sent[1] if sent is not None else math.nan, received_at,
            tick=report.tick, time_s=report.time_us * 1e-6, applied=report.applied))

    def _drop_timed_outstanding(self) -> None:
        """Frames in flight when the movie was flushed: their replies (or NAK NO_MOVIE) no longer matter."""
        for seq in [seq for seq, entry in self._outstanding.items() if entry[2] is not None]:
            del self._outstanding[seq]

    def _expire(self) -> None:
        now = self._clock()
        while self._outstanding:
            seq, (_, sent_at, _) = next(iter(self._outstanding.items()))
            if now - sent_at <= self.ack_timeout_s:
                break
            del self._outstanding[seq]
            self.lost_acks += 1

    def _transact(self, command: sp.Command, payload: bytes = b"", *, attempts: int = 2) -> sp.Packet:
        """Send a command and wait for its reply (same seq). Retries once: every command is idempotent.

        On a link already declared dead (silent beyond ``link_timeout_s``) the command is sent once and given
        :data:`LOST_LINK_WAIT_S` for a reply: REST and DISARM after a stall must not add two reply timeouts each
        to the time the failure takes to reach the caller (the firmware's watchdog rests the contactors anyway).
        """
        last_error = ""
        wait = self.reply_timeout_s
        if self._link_lost is not None:
            attempts, wait = 1, min(wait, LOST_LINK_WAIT_S)
        for _ in range(attempts):
            seq, sent_at = self._send(command, payload)
            deadline = sent_at + wait
            while True:
                remaining = deadline - self._clock()
                if remaining <= 0:
                    last_error = f"no reply to {command.name} (seq {seq}) within {wait} s" + (
                        f" (the link was already lost: {self._link_lost})" if self._link_lost else "")
                    break
                for packet in self._pump(remaining):
                    if packet.seq != seq:
                        continue  # a stale reply to an earlier attempt
                    if packet.command == sp.Command.NAK:
                        code, _ = sp.decode_nak(packet.payload)
                        self.naks.append((code, int(command)))
                        name = sp.NakCode(code).name if code in sp.NakCode._value2member_map_ else str(code)
                        raise DeviceError(f"display refused {command.name}: {name}")
                    if packet.command == sp.reply_command(command):
                        return packet
        raise DeviceTimeoutError(last_error)

    # ---- TactileDisplay ------------------------------------------------------------------------------------------

    def _do_identify(self) -> DisplayInfo:
        ident = sp.Identity.decode(self._transact(sp.Command.IDENTIFY).payload)
        if (ident.rows, ident.cols) != (sp.ROWS, sp.COLS):
            raise ProtocolError(f"display reports {ident.rows}x{ident.cols} contactors, this driver needs 10x10")
        return DisplayInfo("STReSS", ident.firmware, ident.protocol_version, ident.rows, ident.cols,
                           ident.range_um, ident.max_rate_hz)

    def _do_configure(self, *, watchdog_s: float, max_step_um: float) -> None:
        config = sp.WatchdogConfig(watchdog_s=watchdog_s, max_step_um=max_step_um)
        sp.decode_status(self._transact(sp.Command.CONFIGURE, config.encode()).payload)

    def _do_arm(self) -> None:
        self._drop_timed_outstanding()
        status = sp.decode_status(self._transact(sp.Command.ARM).payload)
        if not status & sp.Status.ARMED:
            raise DeviceError(f"display did not arm (status {status!r})")

    def _do_disarm(self) -> None:
        self._outstanding.clear()
        sp.decode_status(self._transact(sp.Command.DISARM).payload)

    def _do_zero(self) -> None:
        sp.decode_status(self._transact(sp.Command.ZERO).payload)

    def _do_rest(self) -> None:
        self._drop_timed_outstanding()  # REST flushes the display's FIFO: frames in flight get NAK NO_MOVIE
        sp.decode_status(self._transact(sp.Command.REST).payload)

    def _do_read_status(self) -> sp.StatusReport:
        return sp.StatusReport.decode(self._transact(sp.Command.READ_STATUS).payload)

    def _do_submit_frame(self, command_um: np.ndarray) -> int:
        return self._do_send_prepared(self._do_prepare_frame(command_um), command_um)

    def _do_prepare_frame(self, command_um: np.ndarray) -> bytes:
        return sp.encode_positions(command_um)

    def _do_wire_command(self, wire: bytes) -> np.ndarray:
        if not isinstance(wire, (bytes, bytearray)):
            raise TypeError(f"a STReSS frame payload is bytes, got {type(wire).__name__}")
        return sp.decode_positions(wire)

    def _do_send_prepared(self, wire: bytes, command_um: np.ndarray) -> int:
        seq, sent_at = self._send(sp.Command.FRAME, wire)
        self._track(seq, command_um, sent_at, None)
        return seq

    def _track(self, seq: int, command_um: np.ndarray, sent_at: float, tick: int | None) -> None:
        if seq in self._outstanding:  # 256 frames without an ack: the old one is certainly lost
            del self._outstanding[seq]
            self.lost_acks += 1
        self._outstanding[seq] = (command_um, sent_at, tick)

    # ---- timed playback ------------------------------------------------------------------------------------------

    @property
    def supports_timed_playback(self) -> bool:
        return True

    def _movie_status(self, packet: sp.Packet) -> sp.MovieStatus:
        status = sp.MovieStatus.decode(packet.payload)
        self._file_tick_report(status.report, status.status, self._clock())
        return status

    def _do_start_movie(self, start: sp.MovieStart) -> sp.MovieStatus:
        self._drop_timed_outstanding()
        self._tick_sent.clear()
        self._reported_tick = sp.NO_TICK
        self._in_force = self._last_command  # what the contactors hold until tick 0
        return self._movie_status(self._transact(sp.Command.START_MOVIE, start.encode()))

    def _do_send_timed(self, tick: int, wire: bytes, command_um: np.ndarray) -> int:
        seq, sent_at = self._send(sp.Command.TIMED_FRAME, sp.encode_timed_frame(tick, wire))
        self._track(seq, command_um, sent_at, tick)
        self._tick_sent[tick] = (command_um, sent_at)
        return seq

    def _do_take_receipts(self) -> list[TimedReceipt]:
        got = list(self._receipts)
        self._receipts.clear()
        return got

    def _do_stop_movie(self) -> sp.MovieStatus:
        self._drop_timed_outstanding()
        return self._movie_status(self._transact(sp.Command.STOP_MOVIE))

    def _do_read_movie_status(self) -> sp.MovieStatus:
        return self._movie_status(self._transact(sp.Command.READ_MOVIE))

    def _do_collect_acks(self, *, wait_for: int | None, timeout_s: float) -> list[FrameAck]:
        deadline = self._clock() + timeout_s
        while True:
            if wait_for is not None and any(a.seq == wait_for for a in self._early_acks):
                break
            if self._frame_refusal is not None:
                self._check_link()  # raises the refusal
            if wait_for is not None and wait_for not in self._outstanding:
                raise DeviceTimeoutError(f"frame {wait_for} was written off before its ack arrived")
            remaining = deadline - self._clock()
            if remaining <= 0:
                if wait_for is not None:
                    raise DeviceTimeoutError(f"no ack for frame {wait_for} within {timeout_s} s")
                break
            self._pump(remaining)
            if wait_for is None and self._early_acks:
                self._pump(0.0)  # drain what is already there, then return
                break
        self._check_link()
        got, self._early_acks = self._early_acks, []
        return got

    def _check_link(self) -> None:
        if self._frame_refusal is not None:
            message, self._frame_refusal = self._frame_refusal, None
            self._armed = False
            raise DeviceError(message)
        if self._expect_since is not None:
            silent = self._clock() - self._expect_since
            if silent > self.link_timeout_s:
                self._link_lost = (f"display silent for {silent * 1000:.0f} ms with {len(self._outstanding)} frames "
                                   f"unacknowledged ({self.transport.description})")
                raise DeviceTimeoutError(self._link_lost)
        self._expire()

    def _do_declare_link_lost(self, reason: str) -> None:
        self._link_lost = reason

    def _do_close(self) -> None:
        if self._closed:
            return
        try:
            if self._armed:
                self._armed = False
                self._do_disarm()
        except DeviceError:
            pass  # the link is gone: the firmware watchdog brings the contactors to rest
        finally:
            self._closed = True
            self.transport.close()
