"""A software twin of the STReSS display firmware, speaking ``docs/protocols/stress.md`` byte for byte.

The twin is split by concern, each part usable alone:

- :mod:`.stress_benders`: the 10x10 piezo benders (:class:`~.stress_benders.BenderArray`).
- this module: :class:`StressFirmware`, the protocol state machine (arm/disarm, watchdog, its own range and slew
  clamp, rest ramp, sensor zeroing, counters, and the timed-playback FIFO played on the movie timer), driven by
  packets and a time. Timer ticks are computed at their scheduled times on the firmware clock, interleaved in time
  order with the packets' arrival times, as a hardware timer interrupt would run them, however late the simulator
  thread gets to them; :class:`TimedRecord` keeps, per timed frame and per tick, the scheduled time, the arrival
  time and the (wall-clock) time the simulator actually computed it.
- :mod:`.stress_wire`: the wire (:class:`~.stress_wire.PacedLink`, paced at the line rate, with fault switches)
  and the clocks.
- :mod:`.stress_pty`: the firmware on a pty, from a thread or a separate process.
- :mod:`.stress_links`: how drivers reach it (pyserial ``stresssim://`` URLs, pty, pyusb backend).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.errors import ProtocolError
from .stress_benders import BenderArray, BenderParameters

__all__ = ["FIRMWARE_NAME", "REFUSED", "TimedRecord", "StressFirmware"]

FIRMWARE_NAME = "stresssim 2.0"


REFUSED = -1  # TimedRecord disposition of a timed frame answered with a NAK (not armed, no movie)


class TimedRecord:
    """What the simulator saw of timed playback, for tests and the bench (never sent on the wire).

    Per timed frame (in arrival order): ``ticks``, ``play_times`` (scheduled, firmware clock), ``arrivals``
    (receive clock: when its last byte arrived on the modelled line), ``handled_at`` (the clock when the simulator
    thread actually processed it), ``dispositions`` (:class:`~skinstretch.drivers.display.stress_protocol.Disposition` or
    :data:`REFUSED`) and ``applied_at`` (the clock when the simulator computed the tick that applied it; NaN if it
    never played). Per movie tick: ``tick_times`` (scheduled), ``tick_computed_at`` and ``tick_applied``.
    A frame whose arrival is at or after its play time missed its deadline, whoever is to blame.
    """

    def __init__(self) -> None:
        self.ticks: list[int] = []
        self.play_times: list[float] = []
        self.arrivals: list[float] = []
        self.handled_at: list[float] = []
        self.dispositions: list[int] = []
        self.applied_at: list[float] = []
        self.tick_times: list[float] = []
        self.tick_computed_at: list[float] = []
        self.tick_applied: list[bool] = []

    def add_frame(self, tick: int, play_time: float, arrival: float, handled_at: float, disposition: int) -> int:
        self.ticks.append(tick)
        self.play_times.append(play_time)
        self.arrivals.append(arrival)
        self.handled_at.append(handled_at)
        self.dispositions.append(disposition)
        self.applied_at.append(math.nan)
        return len(self.ticks) - 1

    def as_arrays(self) -> dict[str, np.ndarray]:
        return {
            "timed_ticks": np.asarray(self.ticks, dtype=np.int64),
            "timed_play_times": np.asarray(self.play_times, dtype=float),
            "timed_arrivals": np.asarray(self.arrivals, dtype=float),
            "timed_handled_at": np.asarray(self.handled_at, dtype=float),
            "timed_dispositions": np.asarray(self.dispositions, dtype=np.int8),
            "timed_applied_at": np.asarray(self.applied_at, dtype=float),
            "tick_times": np.asarray(self.tick_times, dtype=float),
            "tick_computed_at": np.asarray(self.tick_computed_at, dtype=float),
            "tick_applied": np.asarray(self.tick_applied, dtype=bool),
        }


class StressFirmware:
    """The protocol state machine. Call :meth:`advance` with the time, :meth:`handle` for each packet.

    Timed playback (``docs/protocols/stress.md``, "Timed playback"): START_MOVIE sets the rate and the epoch;
    TIMED_FRAMEs wait in a FIFO of :data:`~skinstretch.drivers.display.stress_protocol.FIFO_DEPTH` frames indexed by tick;
    at each tick the timer samples the sensors, applies that tick's frame (firmware clamp included) or holds the
    position (underrun), and logs a tick report for the next reply to carry. ``wall_clock`` (set by the link) is
    only used to record when the simulator got to things.
    """

    def __init__(self, *, seed: int = 0, bender: BenderParameters = BenderParameters(), t0: float = 0.0) -> None:
        self.benders = BenderArray(params=bender, seed=seed, t0=t0)
        self.armed = False
        self.config = sp.WatchdogConfig()
        self.last_command_um = np.zeros((sp.ROWS, sp.COLS))
        self.sensor_zero_um = np.zeros((sp.ROWS, sp.COLS))
        self.status = sp.Status.RESTING
        self.watchdog_deadline: float | None = None
        self.frames_received = 0
        self.crc_errors = 0
        self.sequence_gaps = 0
        self.watchdog_trips = 0
        self.clamped_frames = 0
        self.frame_times: list[float] = []  # receive time of every FRAME (end of its last byte)
        self.frame_seqs: list[int] = []
        self.commands_um: list[np.ndarray] = []  # every applied frame target (after the firmware clamp)
        self._last_seq: int | None = None
        self.t = float(t0)
        # timed playback
        self.movie: sp.MovieStart | None = None  # None: no movie accepting frames
        self.movie_running = False  # the movie timer ticks
        self.movie_epoch = math.nan
        self._rate_mhz = 0
        self._n_frames = 0  # of the last movie started (its counters stay readable after it ends)
        self.next_tick = 0
        self.fifo: dict[int, tuple[np.ndarray, int]] = {}  # tick -> (requested um, TimedRecord index)
        self.tick_log: deque[sp.TickReport] = deque(maxlen=sp.TICK_LOG_DEPTH)
        self.movie_counters = dict.fromkeys(("frames_queued", "frames_played", "late_frames", "underruns",
                                             "fifo_rejects", "reports_lost"), 0)
        self.timed = TimedRecord()
        self.wall_clock = None  # callable giving the simulator's real clock (set by PacedLink); None: event time

    # -- time --
    def _wall(self, t: float) -> float:
        return self.wall_clock() if self.wall_clock is not None else t

    def tick_time(self, tick: int) -> float:
        """When ``tick`` plays, on the firmware clock (the 1 us timer of the current movie)."""
        return self.movie_epoch + sp.tick_time_us(tick, rate_mhz=self._rate_mhz) * 1e-6

    def advance(self, t: float) -> None:
        """Move to time ``t``: run every movie tick and the watchdog due by then, in time order; integrate."""
        while True:
            tick_at = self.tick_time(self.next_tick) if self.movie_running else math.inf
            wd = self.watchdog_deadline if self.watchdog_deadline is not None else math.inf
            if tick_at <= t and tick_at <= wd:  # a frame due with the watchdog still plays (and re-arms it)
                self.benders.advance(tick_at)
                self._play_tick(tick_at)
            elif wd <= t:
                self.benders.advance(wd)
                self._trip_watchdog()
            else:
                break
        self.benders.advance(t)
        self.t = max(self.t, t)

    def _trip_watchdog(self) -> None:
        self.watchdog_trips += 1
        self.armed = False
        self.watchdog_deadline = None
        self._end_movie()
        self.status = (self.status | sp.Status.WATCHDOG_TRIPPED | sp.Status.RESTING) & ~sp.Status.ARMED
        self.benders.rest()
        self.last_command_um = np.zeros((sp.ROWS, sp.COLS))

    def next_deadline(self) -> float | None:
        """The next timer event: a movie tick or the watchdog (None: nothing scheduled)."""
        times = [x for x in (self.watchdog_deadline,
                             self.tick_time(self.next_tick) if self.movie_running else None) if x is not None]
        return min(times) if times else None

    def _guard(self, request: np.ndarray) -> tuple[np.ndarray, bool]:
        """The firmware's own range and slew clamp: a host that skips drivers/display/safety.py cannot hurt."""
        step = self.config.max_step_um
        target = np.clip(request, -sp.RANGE_UM, sp.RANGE_UM)
        target = self.last_command_um + np.clip(target - self.last_command_um, -step, step)
        clamped = bool(np.any(target != request))
        if clamped:
            self.clamped_frames += 1
            self.status |= sp.Status.CLAMPED
        return target, clamped

    def _apply(self, target: np.ndarray) -> None:
        self.last_command_um = target
        self.commands_um.append(target)
        self.benders.command(target)
        self.status &= ~sp.Status.RESTING

    def _play_tick(self, at: float) -> None:
        """The movie timer interrupt: sample, apply this tick's frame or hold, log the tick."""
        k = self.next_tick
        sample = self.measured_um()  # before the frame takes effect: the response to the previous tick
        entry = self.fifo.pop(k, None)
        flags = sp.TickFlags(0)
        computed_at = self._wall(at)
        if entry is not None:
            request, record = entry
            target, clamped = self._guard(request)
            self._apply(target)
            flags |= sp.TickFlags.APPLIED | (sp.TickFlags.CLAMPED if clamped else 0)
            self.movie_counters["frames_played"] += 1
            self.watchdog_deadline = at + self.config.watchdog_s  # only playing feeds the watchdog
            self.timed.applied_at[record] = computed_at
        else:
            self.movie_counters["underruns"] += 1  # hold the last position
            self.status |= sp.Status.UNDERRUN
        if len(self.tick_log) == self.tick_log.maxlen:
            self.movie_counters["reports_lost"] += 1
        self.tick_log.append(sp.TickReport(k, round((at - self.movie_epoch) * 1e6), flags, sample))
        self.timed.tick_times.append(at)
        self.timed.tick_computed_at.append(computed_at)
        self.timed.tick_applied.append(entry is not None)
        self.next_tick = k + 1
        if self.movie is not None and self.movie.n_frames and self.next_tick >= self.movie.n_frames:
            # the last tick has played: the timer stops, the position is held, later frames are late
            self.movie_running = False
            self.status &= ~sp.Status.MOVIE

    def _end_movie(self) -> None:
        """STOP_MOVIE, REST, DISARM, ARM, watchdog: flush the FIFO at once; counters and tick log stay readable."""
        self.fifo.clear()
        self.movie = None
        self.movie_running = False
        self.status &= ~sp.Status.MOVIE

    def measured_um(self) -> np.ndarray:
        measured = self.benders.sensor_um() - self.sensor_zero_um
        if np.any(np.abs(measured) > sp.POSITION_CODE_MAX * sp.POSITION_STEP_UM):
            self.status |= sp.Status.SATURATED
        return measured

    def note_crc_errors(self, count: int) -> None:
        if count > self.crc_errors:
            self.status |= sp.Status.CRC_ERRORS
        self.crc_errors = count

    # -- packets --
    def handle(self, packet: sp.Packet, t: float) -> bytes:
        """Process one request received (completely) at time ``t``; return the reply packet bytes."""
        self.advance(t)
        if packet.is_reply:
            return b""  # not for us
        if self._last_seq is not None and packet.seq != (self._last_seq + 1) & 0xFF:
            self.sequence_gaps += 1
            self.status |= sp.Status.SEQUENCE_GAP
        self._last_seq = packet.seq
        try:
            command = sp.Command(packet.command)
        except ValueError:
            return self._nak(packet, sp.NakCode.UNKNOWN_COMMAND)
        handler = {
            sp.Command.IDENTIFY: self._identify, sp.Command.CONFIGURE: self._configure,
            sp.Command.ARM: self._arm, sp.Command.DISARM: self._disarm, sp.Command.ZERO: self._zero,
            sp.Command.FRAME: self._frame, sp.Command.REST: self._rest, sp.Command.READ_STATUS: self._read_status,
            sp.Command.START_MOVIE: self._start_movie, sp.Command.TIMED_FRAME: self._timed_frame,
            sp.Command.STOP_MOVIE: self._stop_movie, sp.Command.READ_MOVIE: self._read_movie,
        }.get(command)
        if handler is None:
            return self._nak(packet, sp.NakCode.UNKNOWN_COMMAND)
        return handler(packet, t)

    def _reply(self, packet: sp.Packet, payload: bytes) -> bytes:
        return sp.encode_packet(seq=packet.seq, command=sp.reply_command(packet.command), payload=payload)

    def _nak(self, packet: sp.Packet, code: sp.NakCode) -> bytes:
        return sp.encode_packet(seq=packet.seq, command=sp.Command.NAK, payload=sp.encode_nak(code, packet.command))

    def _needs_empty(self, packet: sp.Packet) -> bool:
        return len(packet.payload) == 0

    def _identify(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        ident = sp.Identity(sp.PROTOCOL_VERSION, sp.ROWS, sp.COLS, sp.RANGE_UM, 700, FIRMWARE_NAME)
        return self._reply(packet, ident.encode())

    def _configure(self, packet, t):
        if len(packet.payload) != 3:
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        try:
            self.config = sp.WatchdogConfig.decode(packet.payload)
        except ProtocolError:  # a value out of range is refused, not fatal
            return self._nak(packet, sp.NakCode.BAD_VALUE)
        if self.armed:
            self.watchdog_deadline = t + self.config.watchdog_s
        return self._reply(packet, sp.encode_status(self.status))

    def _arm(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        self._end_movie()
        self.armed = True
        self.status = (self.status | sp.Status.ARMED) & ~sp.Status.WATCHDOG_TRIPPED
        self.watchdog_deadline = t + self.config.watchdog_s
        self.last_command_um = np.zeros((sp.ROWS, sp.COLS))
        return self._reply(packet, sp.encode_status(self.status))

    def _disarm(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        self._end_movie()
        self.armed = False
        self.watchdog_deadline = None
        self.benders.rest()
        self.last_command_um = np.zeros((sp.ROWS, sp.COLS))
        self.status = (self.status | sp.Status.RESTING) & ~sp.Status.ARMED
        return self._reply(packet, sp.encode_status(self.status))

    def _zero(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        if self.armed:
            return self._nak(packet, sp.NakCode.ARMED)
        # reference the sensors with the benders at rest (average out the sensor noise)
        self.sensor_zero_um = np.mean([self.benders.sensor_um() for _ in range(16)], axis=0)
        self.status |= sp.Status.ZEROED
        return self._reply(packet, sp.encode_status(self.status))

    def _rest(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        self._end_movie()  # never queued behind buffered frames: the FIFO is flushed and the ramp starts now
        self.benders.rest()
        self.last_command_um = np.zeros((sp.ROWS, sp.COLS))
        self.status |= sp.Status.RESTING
        return self._reply(packet, sp.encode_status(self.status))

    def _read_status(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        report = sp.StatusReport(self.status, self.measured_um(), self.frames_received, self.crc_errors,
                                 self.sequence_gaps, self.watchdog_trips)
        reply = self._reply(packet, report.encode())
        # the sticky "since last read" bits are cleared by reading them
        self.status &= ~(sp.Status.CRC_ERRORS | sp.Status.SEQUENCE_GAP | sp.Status.CLAMPED | sp.Status.SATURATED
                         | sp.Status.LATE_FRAME | sp.Status.UNDERRUN | sp.Status.FIFO_REJECT)
        return reply

    def _frame(self, packet, t):
        self.frame_times.append(t)
        self.frame_seqs.append(packet.seq)
        if len(packet.payload) != sp.N_CONTACTORS:
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        if not self.armed:
            return self._nak(packet, sp.NakCode.NOT_ARMED)
        if self.movie_running:
            return self._nak(packet, sp.NakCode.MOVIE_RUNNING)
        self.frames_received += 1
        self.watchdog_deadline = t + self.config.watchdog_s
        measured = self.measured_um()  # sampled as the frame arrives, before it takes effect
        request = np.frombuffer(packet.payload, dtype=np.int8).astype(float).reshape(sp.ROWS, sp.COLS)
        request *= sp.POSITION_STEP_UM
        target, _ = self._guard(request)
        self._apply(target)
        return self._reply(packet, sp.encode_frame_ack(self.status, measured))

    # -- timed playback --
    def _movie_status(self, t: float) -> sp.MovieStatus:
        c = self.movie_counters
        report = self.tick_log.popleft() if self.tick_log else sp.TickReport()
        time_us = round((t - self.movie_epoch) * 1e6) if math.isfinite(self.movie_epoch) else 0
        return sp.MovieStatus(self.status, sp.FIFO_DEPTH, len(self.fifo), self._rate_mhz,
                              self._n_frames, time_us, self.next_tick,
                              c["frames_queued"], c["frames_played"], c["late_frames"], c["underruns"],
                              c["fifo_rejects"], c["reports_lost"], report)

    def _start_movie(self, packet, t):
        if len(packet.payload) != 12:
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        try:
            start = sp.MovieStart.decode(packet.payload)
        except ProtocolError:
            return self._nak(packet, sp.NakCode.BAD_VALUE)
        if not self.armed:
            return self._nak(packet, sp.NakCode.NOT_ARMED)
        self._end_movie()
        self.movie = start
        self.movie_running = True
        self.movie_epoch = t + start.start_delay_us * 1e-6
        self._rate_mhz = start.rate_mhz
        self._n_frames = start.n_frames
        self.next_tick = 0
        self.tick_log.clear()
        self.movie_counters = dict.fromkeys(self.movie_counters, 0)
        self.status |= sp.Status.MOVIE
        # nothing is due before the epoch: the watchdog counts from there
        self.watchdog_deadline = self.movie_epoch + self.config.watchdog_s
        return self._reply(packet, self._movie_status(t).encode())

    def _timed_frame(self, packet, t):
        if len(packet.payload) != 4 + sp.N_CONTACTORS:
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        tick, request = sp.decode_timed_frame(packet.payload)
        play_time = self.tick_time(tick) if self._rate_mhz else math.nan  # NaN: no movie was ever started
        refused = None
        if not self.armed:
            refused = sp.NakCode.NOT_ARMED
        elif self.movie is None:
            refused = sp.NakCode.NO_MOVIE
        if refused is not None:
            self.timed.add_frame(tick, play_time, t, self._wall(t), REFUSED)
            return self._nak(packet, refused)
        self.frames_received += 1
        c = self.movie_counters
        if tick < self.next_tick:  # its time has come and gone (the timer already ran that tick): dropped
            disposition = sp.Disposition.LATE
            c["late_frames"] += 1
            self.status |= sp.Status.LATE_FRAME
        elif self.movie.n_frames and tick >= self.movie.n_frames:
            disposition = sp.Disposition.PAST_END
        elif tick >= self.next_tick + sp.FIFO_DEPTH:
            disposition = sp.Disposition.FIFO_FULL  # refused, never waited for: the host must not block us
        elif tick in self.fifo:
            disposition = sp.Disposition.DUPLICATE
        else:
            disposition = sp.Disposition.QUEUED
        if disposition in (sp.Disposition.PAST_END, sp.Disposition.FIFO_FULL, sp.Disposition.DUPLICATE):
            c["fifo_rejects"] += 1
            self.status |= sp.Status.FIFO_REJECT
        record = self.timed.add_frame(tick, play_time, t, self._wall(t), int(disposition))
        if disposition == sp.Disposition.QUEUED:
            self.fifo[tick] = (request, record)
            c["frames_queued"] += 1
        report = self.tick_log.popleft() if self.tick_log else sp.TickReport()
        reply = sp.TimedFrameReply(self.status, tick, disposition, len(self.fifo),
                                   round((t - self.movie_epoch) * 1e6), c["late_frames"], c["underruns"], report)
        return self._reply(packet, reply.encode())

    def _stop_movie(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        self._end_movie()  # flush at once; the position is held
        if self.armed:
            self.watchdog_deadline = t + self.config.watchdog_s  # frames or REST must follow, as after any frame
        return self._reply(packet, self._movie_status(t).encode())

    def _read_movie(self, packet, t):
        if not self._needs_empty(packet):
            return self._nak(packet, sp.NakCode.BAD_LENGTH)
        return self._reply(packet, self._movie_status(t).encode())

