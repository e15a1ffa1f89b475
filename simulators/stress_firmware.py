"""A software twin of the STReSS display firmware, speaking ``docs/protocols/stress.md`` byte for byte.

Three layers, each usable alone:

- :class:`BenderArray`: the 10x10 piezo benders. Each is a first-order lag (time constant ``tau_s``), a play
  operator (rate-independent hysteresis of half-width ``hysteresis_um``), a seeded gain and sensor offset, and a
  deflection that drops under the finger's lateral load (bender and skin as two springs in series).
- :class:`StressFirmware`: the protocol state machine (arm/disarm, watchdog, its own range and slew clamp, rest
  ramp, sensor zeroing, counters, and the timed-playback FIFO played on the movie timer), driven by packets and a
  time. Timer ticks are computed at their scheduled times on the firmware clock, interleaved in time order with
  the packets' arrival times, as a hardware timer interrupt would run them, however late the simulator thread
  gets to them; :class:`TimedRecord` keeps, per timed frame and per tick, the scheduled time, the arrival time
  and the (wall-clock) time the simulator actually computed it.
- :class:`PacedLink`: the wire. A pty or an in-process pipe ignores baud rates (FACTS), so the link models the
  line itself: bytes arrive one byte-time apart at the line rate, replies leave at the line rate, plus fault
  injection (dropped / corrupted bytes, stalled link, vanished link) from a seeded generator.

Time comes from a replaceable clock (:class:`RealClock` or :class:`ManualClock`) so tests are deterministic.
Run ``python -m skinstretch.simulators.stress_firmware --pty-fd N`` to serve the firmware on a pty master in a separate
process (the benchmark does this so the firmware's receive clock is not disturbed by the host's GIL).
"""

from __future__ import annotations

import argparse
import errno
import math
import os
import select
import sys
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.errors import ProtocolError
from skinstretch.processing.errors import InvalidInputError

FIRMWARE_NAME = "stresssim 2.0"


# ---- clocks ------------------------------------------------------------------------------------------------------

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


# ---- the benders -------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class BenderParameters:
    """Piezo bender model. Values are plausible for STReSS-class benders; no datasheet is public."""

    tau_s: float = 0.0004  # first-order lag
    hysteresis_um: float = 0.6  # play-operator half width
    gain_spread: float = 0.03  # seeded per-contactor gain 1 +/- spread (1 sigma)
    offset_spread_um: float = 1.0  # seeded position-sensor offsets (removed by ZERO)
    noise_um: float = 0.05  # position-sensor noise (1 sigma)
    bender_stiffness_n_per_mm: float = 0.5  # lateral stiffness of one bender tip
    rest_tau_s: float = 0.005  # soft return to rest

    def __post_init__(self) -> None:
        for name in ("tau_s", "rest_tau_s", "bender_stiffness_n_per_mm"):
            if not getattr(self, name) > 0:
                raise InvalidInputError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("hysteresis_um", "gain_spread", "offset_spread_um", "noise_um"):
            if not getattr(self, name) >= 0:
                raise InvalidInputError(f"{name} must be >= 0, got {getattr(self, name)!r}")


class BenderArray:
    """10x10 benders, integrated exactly between events (piecewise-constant targets)."""

    def __init__(self, *, params: BenderParameters = BenderParameters(), seed: int = 0, t0: float = 0.0) -> None:
        self.params = params
        rng = np.random.default_rng(seed)
        shape = (sp.ROWS, sp.COLS)
        self.gain = 1.0 + params.gain_spread * rng.standard_normal(shape)
        self.offset_um = params.offset_spread_um * rng.standard_normal(shape)
        self._noise = np.random.default_rng(seed + 1)
        self.load_n_per_mm = np.zeros(shape)
        self.target_um = np.zeros(shape)  # command in force (decays during rest)
        self.lag_um = np.zeros(shape)
        self.play_um = np.zeros(shape)
        self.resting = True
        self.t = float(t0)

    def set_load(self, stiffness_n_per_mm) -> None:
        """Finger load per contactor as a lateral skin stiffness (N/mm); a scalar applies to all."""
        k = np.broadcast_to(np.asarray(stiffness_n_per_mm, dtype=float), (sp.ROWS, sp.COLS)).copy()
        if not np.all(np.isfinite(k)) or np.any(k < 0):
            raise InvalidInputError("stiffness_n_per_mm must be finite and >= 0")
        self.load_n_per_mm = k

    def advance(self, t: float) -> None:
        dt = t - self.t
        if dt <= 0:
            return
        p = self.params
        e = math.exp(-dt / p.tau_s)
        if self.resting:
            # cascade of the rest ramp r(t) = r0 exp(-t/tr) and the bender lag: exact solution
            tr = p.rest_tau_s
            er = math.exp(-dt / tr)
            if abs(tr - p.tau_s) > 1e-12:
                self.lag_um = self.lag_um * e + self.target_um * tr / (tr - p.tau_s) * (er - e)
            else:
                self.lag_um = (self.lag_um + self.target_um * dt / tr) * e
            self.target_um = self.target_um * er
        else:
            self.lag_um = self.target_um + (self.lag_um - self.target_um) * e
        # the lag response between events is monotone, so the play operator at the end point is exact
        h = p.hysteresis_um
        self.play_um = np.clip(self.play_um, self.lag_um - h, self.lag_um + h)
        self.t = t

    def deflection_um(self) -> np.ndarray:
        """True tip deflection: bender and skin are springs in series."""
        kb = self.params.bender_stiffness_n_per_mm
        return self.gain * self.play_um * kb / (kb + self.load_n_per_mm)

    def sensor_um(self) -> np.ndarray:
        """What the position sensors read (offset included, noise seeded)."""
        noise = self.params.noise_um * self._noise.standard_normal((sp.ROWS, sp.COLS))
        return self.deflection_um() + self.offset_um + noise

    def command(self, target_um: np.ndarray) -> None:
        self.target_um = np.asarray(target_um, float).copy()
        self.resting = False

    def rest(self) -> None:
        self.resting = True


# ---- the firmware ------------------------------------------------------------------------------------------------

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


# ---- the wire ----------------------------------------------------------------------------------------------------

class LinkVanished(ConnectionError):
    """The simulated link is gone (unplugged cable, USB device removed)."""


@dataclass(frozen=True)
class LinkFaults:
    """Fault injection. Rates are per byte; ``*_after_frames`` count FRAME packets received."""

    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    stall_after_frames: int | None = None
    vanish_after_frames: int | None = None

    def __post_init__(self) -> None:
        for name in ("drop_rate", "corrupt_rate"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise InvalidInputError(f"{name} must be in 0..1, got {v!r}")
        for name in ("stall_after_frames", "vanish_after_frames"):
            v = getattr(self, name)
            if v is not None and v < 0:
                raise InvalidInputError(f"{name} must be >= 0, got {v!r}")

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


# ---- a pty server (thread or separate process) ------------------------------------------------------------------

class PtyFirmwareServer:
    """Serve a :class:`PacedLink` on the master side of a pty; the driver opens :attr:`port` as a serial port.

    Either create the pty here (``PtyFirmwareServer(link)``, then :meth:`start` a thread) or hand over a master
    fd created by a parent process (``master_fd=``) and call :meth:`serve` in that process.
    """

    def __init__(self, link: PacedLink, *, master_fd: int | None = None) -> None:
        self.link = link
        self._slave_fd: int | None = None
        if master_fd is None:
            master_fd, slave_fd = os.openpty()
            tty.setraw(slave_fd)  # FACTS: raw mode on the slave, or the line discipline mangles bytes
            self._slave_fd = slave_fd
            self.port = os.ttyname(slave_fd)
        else:
            self.port = None
        self.master_fd = master_fd
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def start(self) -> "PtyFirmwareServer":
        self._thread = threading.Thread(target=self._run, name="stress-firmware-pty", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        try:
            self.serve()
        except BaseException as exc:  # noqa: BLE001 - kept for the owner to inspect
            self.error = exc

    def serve(self) -> None:
        """Run until :meth:`stop`, the host side closes (EIO), or the link vanishes."""
        fd = self.master_fd
        link = self.link
        clock = link.clock
        while not self._stop.is_set():
            now = clock.now()
            nxt = link.next_event()
            wait = 0.005 if nxt is None else min(max(nxt - now, 0.0), 0.005)
            readable, _, _ = select.select([fd], [], [], wait)
            if readable:
                try:
                    data = os.read(fd, 65536)
                except OSError as exc:
                    if exc.errno == errno.EIO:  # every slave fd closed: the host went away
                        return
                    raise
                if not data:
                    return
                try:
                    link.host_write(data)
                except LinkVanished:
                    break
            try:
                out = link.host_read(65536)
            except LinkVanished:
                break
            if out:
                try:
                    os.write(fd, out)
                except OSError as exc:
                    if exc.errno == errno.EIO:
                        return
                    raise
        if link.vanished:
            self._close_fds()  # an unplugged adapter: the host's port goes dead

    def _close_fds(self) -> None:
        for name in ("master_fd", "_slave_fd"):
            fd = getattr(self, name)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, name, None)

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._close_fds()


def main(argv: list[str] | None = None) -> int:
    """Serve the firmware on an inherited pty master fd; on exit save the frame receive times (``.npy``)."""
    parser = argparse.ArgumentParser(description="STReSS firmware simulator on a pty master fd")
    parser.add_argument("--pty-fd", type=int, required=True)
    parser.add_argument("--baud", type=int, default=sp.DEFAULT_BAUD)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--faults", default="")
    parser.add_argument("--record", default="", help="write frame receive times / seqs / targets here (.npz)")
    args = parser.parse_args(argv)
    clock = RealClock()
    firmware = StressFirmware(seed=args.seed, t0=clock.now())
    link = PacedLink.uart(firmware, clock=clock, baud=args.baud, faults=LinkFaults.parse(args.faults),
                          seed=args.seed)
    server = PtyFirmwareServer(link, master_fd=args.pty_fd)
    print("ready", flush=True)  # the parent waits for this before talking to the port
    try:
        server.serve()
    except KeyboardInterrupt:
        pass
    finally:
        if args.record:
            np.savez(args.record, frame_times=np.asarray(firmware.frame_times),
                     frame_seqs=np.asarray(firmware.frame_seqs, dtype=np.int16),
                     commands_um=np.asarray(firmware.commands_um).reshape(-1, sp.ROWS, sp.COLS),
                     watchdog_trips=firmware.watchdog_trips, crc_errors=firmware.crc_errors,
                     clamped_frames=firmware.clamped_frames, **firmware.timed.as_arrays(),
                     **{f"movie_{k}": v for k, v in firmware.movie_counters.items()})
        server._close_fds()
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
