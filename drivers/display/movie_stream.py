"""Stream a tactile movie to a display at a fixed rate (up to 700 Hz) with deadline tracking.

Two modes, two functions:

- :func:`stream_movie_buffered` (timed, buffered; the default of ``skinstretch.experiments.playback`` for open-loop movies on a
  display that supports it): every frame carries its play tick on the display's clock and is sent ``lead_s``
  ahead; the firmware plays it from its FIFO on its own timer, so a host stall shorter than the lead costs
  nothing. Corrections by a callback act with the buffer's latency (``lead_s``).
- :func:`stream_movie` (immediate): each frame is sent at its deadline and applied when it arrives; a host stall
  longer than a period is a missed deadline. Lowest latency from a callback's correction to the skin.

Immediate mode details.
Frames are pipelined: frame k is sent at its deadline ``t0 + k / rate`` without waiting for the ack of frame
k - 1 (at 2 Mbaud a request/ack round trip is ~1.1 ms of the 1.43 ms period, so a lock-step loop has no margin).
The wait for a deadline reads acks (the transport's blocking read, which releases the GIL) until ``spin_s``
before the deadline, then spins on ``perf_counter`` (sleep alone overshoots by 50-100 us on Linux).

On a link failure (write error, silent link, too many unacknowledged frames) the movie stops, the driver sends
rest when it can (the firmware watchdog does it otherwise) and the report, with everything acquired so far, is
returned flagged ``outcome="link_failure"``. A callback may correct each command (closed loop) and may stop the
movie by raising :class:`skinstretch.drivers.errors.SafetyStop` (force ceiling): ``outcome="safety_stop"``.

Every frame is stamped at each phase of the loop (:data:`PHASES`) with the sending thread's CPU time at its top,
so :meth:`PlaybackReport.stalls` can say where the loop lost the CPU and whether the lost time was charged to the
thread (it ran, or the kernel/hypervisor billed it) or not (it was not running). Per-frame arrays are written
before the first deadline so that no first-touch page fault lands on the deadline path; the garbage collector is
off during the movie.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError, SafetyStop

from skinstretch.processing.errors import InvalidInputError

from .base import FrameAck, TactileDisplay, TimedFrameAck, TimedReceipt
from .safety import check_movie
from .stress_protocol import COLS, FIFO_DEPTH, ROWS, TICK_LOG_DEPTH, Disposition, MovieStatus, rate_to_mhz

#: What :attr:`PlaybackReport.phase_times_s` columns record, per frame: top of the loop, end of the ack wait,
#: command ready (callback + limits + encoding), end of the spin (= send time), bytes written and filed.
PHASES = ("start", "waited", "prepared", "send", "sent")

#: ``callback(index, command_um, latest_ack) -> corrected command (10, 10) or None (keep)``
FrameCallback = Callable[[int, np.ndarray, Optional[FrameAck]], Optional[np.ndarray]]


@dataclass(frozen=True)
class Stall:
    """A gap of at least ``min_gap_s`` between two consecutive phase stamps of the streaming loop.

    ``thread_cpu_s`` is the sending thread's CPU time over the frames the gap spans: about ``duration_s`` when the
    thread was charged for the time (spinning, or kernel/interrupt/hypervisor time billed to it), about 0 when it
    was not running at all (sleeping past its wake-up, waiting for the GIL, preempted, throttled, vCPU stolen).
    """

    frame: int  # the frame whose phase ``after`` ended the gap
    before: str  # phase stamped just before the gap
    after: str  # phase stamped just after it
    start_s: float  # relative to the first deadline
    duration_s: float
    thread_cpu_s: float  # NaN when the gap lies in the last frame (no later CPU stamp)


def find_stalls(phase_times_s: np.ndarray | None, thread_cpu_s: np.ndarray | None, *,
                min_gap_s: float = 0.004) -> list[Stall]:
    """Gaps of at least ``min_gap_s`` between consecutive stamps of a (frames, len(PHASES)) phase-time array.

    NaN stamps (phases a skipped frame never reached) are passed over. ``thread_cpu_s`` (frames,) is the thread
    CPU time stamped at the top of each frame, or None.
    """
    if phase_times_s is None or phase_times_s.size == 0:
        return []
    if not (np.isfinite(min_gap_s) and min_gap_s > 0):
        raise InvalidInputError(f"min_gap_s must be > 0, got {min_gap_s!r}")
    flat = np.asarray(phase_times_s, dtype=float).reshape(-1)
    width = phase_times_s.shape[1]
    idx = np.flatnonzero(~np.isnan(flat))
    gaps = np.diff(flat[idx])
    cpu = np.full(phase_times_s.shape[0], np.nan) if thread_cpu_s is None else np.asarray(thread_cpu_s, float)
    out = []
    for g in np.flatnonzero(gaps >= min_gap_s):
        k0, p0 = divmod(int(idx[g]), width)
        k1, p1 = divmod(int(idx[g + 1]), width)
        # CPU time is stamped at the top of each frame: take the frames the gap lies in
        c1 = cpu[k1 + 1] if k1 + 1 < cpu.size else np.nan
        out.append(Stall(k1, PHASES[p0], PHASES[p1], float(flat[idx[g]]), float(gaps[g]), float(c1 - cpu[k0])))
    return out


@dataclass
class PlaybackReport:
    """What happened during a playback. Arrays cover the frames sent; ``acked`` flags frames with an ack.

    ``commands_um[k]`` is the command in force after frame k (for a skipped frame: the previous one).
    ``measured_um[k]`` is what the contactors read when frame k arrived (the response to frame k - 1); where
    no ack came back it is NaN *and* ``acked[k]`` is False. Position errors compare ``measured_um[k]`` with the
    command of frame k - 1 (``settle_frames`` excluded).
    """

    outcome: str  # "completed" | "link_failure" | "safety_stop"
    error: str
    rested: bool
    rate_hz: float
    frames_total: int
    frames_played: int  # frames whose slot has come: sent, or skipped because the host was starved
    commands_um: np.ndarray = field(repr=False)
    measured_um: np.ndarray = field(repr=False)
    acked: np.ndarray = field(repr=False)
    deadlines_s: np.ndarray = field(repr=False)  # relative to the first deadline
    send_times_s: np.ndarray = field(repr=False)  # relative to the first deadline (decision time if skipped)
    skipped: np.ndarray = field(repr=False)  # frames not sent because their whole slot had passed
    missed_deadlines: int  # late frames + skipped frames
    miss_tolerance_s: float
    lost_acks: int
    settle_frames: int
    #: per frame, host clock relative to the first deadline at each phase of the loop (see :data:`PHASES`)
    phase_times_s: np.ndarray = field(default=None, repr=False)
    #: per frame, the sending thread's CPU time (``time.thread_time``) at the top of the loop
    thread_cpu_s: np.ndarray = field(default=None, repr=False)
    #: the host clock's value at the first deadline (times above are relative to it)
    clock_origin_s: float = float("nan")

    @property
    def completed(self) -> bool:
        return self.outcome == "completed"

    @property
    def frames_skipped(self) -> int:
        return int(self.skipped.sum())

    @property
    def lateness_s(self) -> np.ndarray:
        """Send time - deadline of the frames actually sent."""
        return (self.send_times_s - self.deadlines_s)[~self.skipped]

    @property
    def periods_s(self) -> np.ndarray:
        """Intervals between consecutive frames actually sent."""
        return np.diff(self.send_times_s[~self.skipped])

    @property
    def period_jitter_p99_s(self) -> float:
        """99th percentile of |period - nominal| of the host's send times (0 with fewer than 2 frames)."""
        p = self.periods_s
        return float(np.percentile(np.abs(p - 1.0 / self.rate_hz), 99)) if p.size else 0.0

    def stalls(self, min_gap_s: float = 0.004) -> list[Stall]:
        """Gaps of at least ``min_gap_s`` between consecutive phase stamps (where the loop lost the CPU)."""
        return find_stalls(self.phase_times_s, self.thread_cpu_s, min_gap_s=min_gap_s)

    def _errors(self) -> np.ndarray:
        """(n, 10, 10) measured - previous command over acked frames after the settle time."""
        k = np.arange(max(1, self.settle_frames), self.frames_played)
        k = k[self.acked[k]]
        if k.size == 0:
            return np.empty((0, ROWS, COLS))
        return self.measured_um[k] - self.commands_um[k - 1]

    @property
    def error_frames(self) -> int:
        return int(self._errors().shape[0])

    def position_rms_error_um(self) -> np.ndarray:
        """Per-contactor RMS of measured - commanded (10, 10). InvalidInputError if no ack is usable."""
        e = self._errors()
        if e.shape[0] == 0:
            raise InvalidInputError("no acknowledged frame after the settle time: no position error to report")
        return np.sqrt(np.mean(e ** 2, axis=0))

    def position_mean_error_um(self) -> np.ndarray:
        """Per-contactor mean (bias) of measured - commanded (10, 10)."""
        e = self._errors()
        if e.shape[0] == 0:
            raise InvalidInputError("no acknowledged frame after the settle time: no position error to report")
        return e.mean(axis=0)


def _checked_movie(movie_um, *, rate_hz: float, settle_frames: int) -> np.ndarray:
    """The movie as a float array, and the options both streaming modes share, checked before the display is
    armed: finite real targets (NaN, inf, complex are refused), 1..700 Hz, settle_frames an int >= 0."""
    movie = check_movie(movie_um)
    rate_to_mhz(rate_hz)
    if not (isinstance(settle_frames, int) and settle_frames >= 0):
        raise InvalidInputError(f"settle_frames must be an int >= 0, got {settle_frames!r}")
    return movie


def _frame_arrays(n: int) -> tuple[np.ndarray, ...]:
    """Per-frame arrays of an ``n``-frame movie: commands, measured positions (NaN), acked, skipped, phase times
    (NaN) and thread CPU stamps (NaN). Every page is written here: np.zeros maps untouched pages, and a first
    touch inside the loop would be a page fault on the deadline path."""
    commands = np.empty((n, ROWS, COLS))
    commands.fill(0.0)
    return (commands, np.full((n, ROWS, COLS), np.nan), np.full(n, False), np.full(n, False),
            np.full((n, len(PHASES)), np.nan), np.full(n, np.nan))


def stream_movie(display: TactileDisplay, movie_um, *, rate_hz: float = 700.0,
                 callback: FrameCallback | None = None, spin_s: float = 0.0004, max_outstanding: int = 32,
                 miss_tolerance_s: float | None = None, final_ack_timeout_s: float = 0.05, settle_frames: int = 5,
                 rest_at_end: bool = True, clock: Callable[[], float] = time.perf_counter) -> PlaybackReport:
    """Play ``movie_um`` (frames, 10, 10) in micrometres on ``display`` at ``rate_hz``.

    Parameters
    ----------
    display : TactileDisplay
        Armed here if it is not armed yet. Its range / slew limits apply to every frame.
    movie_um : array_like, shape (frames, 10, 10)
        Requested positions: finite real numbers (InvalidTargetError naming frame and contactor otherwise); out
        of range or slew they are limited by the driver (see :mod:`skinstretch.drivers.display.safety`).
    rate_hz : float, keyword-only
        Frame rate, 1..700 Hz (the STReSS refresh rate).
    callback : callable, keyword-only
        Called just before each frame's deadline with (index, command, latest ack); returns a corrected
        command or None. Raise SafetyStop in it to stop the movie (contactors go to rest).
    spin_s : float, keyword-only
        The last part of every wait is a busy spin of this length.
    max_outstanding : int, keyword-only
        More unacknowledged frames than this is a link failure.
    miss_tolerance_s : float, keyword-only
        A frame sent later than its deadline plus this is a missed deadline (default: a quarter period).
    settle_frames : int, keyword-only
        Frames left out of the position error statistics.
    clock : callable, keyword-only
        Must be the clock the display driver uses (``time.perf_counter``).
    """
    movie = _checked_movie(movie_um, rate_hz=rate_hz, settle_frames=settle_frames)
    period = 1.0 / rate_hz
    if not (np.isfinite(spin_s) and 0 <= spin_s < period):
        raise InvalidInputError(f"spin_s must be in [0, period), got {spin_s!r}")
    if not (isinstance(max_outstanding, int) and 1 <= max_outstanding <= 200):
        raise InvalidInputError(f"max_outstanding must be an int in 1..200, got {max_outstanding!r}")
    tolerance = period / 4 if miss_tolerance_s is None else float(miss_tolerance_s)
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise InvalidInputError(f"miss_tolerance_s must be >= 0, got {miss_tolerance_s!r}")

    n = movie.shape[0]
    commands, measured, acked, skipped, phases, cpu = _frame_arrays(n)
    deadlines = np.arange(n) * period
    send_times = np.full(n, 0.0)
    thread_time = time.thread_time
    frame_of_seq: dict[int, int] = {}
    latest: list[FrameAck | None] = [None]
    lost_before = getattr(display, "lost_acks", 0)

    def file_acks(acks: list[FrameAck]) -> None:
        for ack in acks:
            k = frame_of_seq.pop(ack.seq, None)
            if k is not None:
                measured[k] = ack.measured_um
                acked[k] = True
            latest[0] = ack

    sent = 0
    t0 = float("nan")
    with _MovieLoop(display) as loop:
        if not display.armed:
            display.arm()
        t0 = clock() + 2 * period  # a little lead so frame 0 is not late by construction
        for k in range(n):
            deadline = t0 + k * period
            now = clock()
            phases[k, 0] = now - t0
            cpu[k] = thread_time()
            if now > deadline + period:
                # this frame's whole slot has passed (the host was starved): a burst of stale frames would only
                # overrun the line, so skip it; the next frame is limited against what the contactors last got
                skipped[k] = True
                send_times[k] = now - t0
                commands[k] = display.last_command_um
                sent = k + 1
                continue
            while True:
                remaining = deadline - clock() - spin_s
                if remaining <= 0:
                    break
                file_acks(display.collect_acks(timeout_s=remaining))
            phases[k, 1] = clock() - t0
            command = movie[k]
            if callback is not None:
                corrected = callback(k, command.copy(), latest[0])
                if corrected is not None:
                    command = corrected
            prepared = display.prepare_frame(command)  # limits and encoding off the deadline path
            phases[k, 2] = clock() - t0
            while clock() < deadline:
                pass
            now = clock()
            seq = display.send_prepared(prepared)
            send_times[k] = phases[k, 3] = now - t0
            commands[k] = display.last_command_um
            frame_of_seq[seq] = k
            sent = k + 1
            phases[k, 4] = clock() - t0
            if display.outstanding > max_outstanding // 2:
                # behind schedule the wait above is skipped: collect what has arrived without waiting
                file_acks(display.collect_acks(timeout_s=0.0))
            if display.outstanding > max_outstanding:
                lost = (f"{display.outstanding} frames unacknowledged "
                        f"({display.outstanding * period * 1000:.0f} ms of movie)")
                display.declare_link_lost(lost)
                raise DeviceTimeoutError(lost)
        file_acks(display.collect_acks(timeout_s=0.0))
        end = clock() + final_ack_timeout_s
        while display.outstanding and clock() < end:
            file_acks(display.collect_acks(timeout_s=max(end - clock(), 0.0)))
    outcome, error = loop.outcome, loop.error
    rested, error = _rest_unless(display, outcome == "completed" and not rest_at_end, error)
    lateness = (send_times[:sent] - deadlines[:sent])[~skipped[:sent]]
    return PlaybackReport(
        outcome=outcome, error=error, rested=rested, rate_hz=float(rate_hz), frames_total=n, frames_played=sent,
        commands_um=commands[:sent], measured_um=measured[:sent], acked=acked[:sent],
        deadlines_s=deadlines[:sent], send_times_s=send_times[:sent], skipped=skipped[:sent],
        missed_deadlines=int(np.sum(lateness > tolerance) + skipped[:sent].sum()), miss_tolerance_s=tolerance,
        lost_acks=getattr(display, "lost_acks", 0) - lost_before, settle_frames=settle_frames, clock_origin_s=t0,
        phase_times_s=phases[:sent], thread_cpu_s=cpu[:sent] - cpu[0] if sent else cpu[:0])


class _MovieLoop:
    """Around a streaming loop: how it ended, and no garbage collection while it runs (a full collection over
    thousands of acks takes milliseconds).

    A :class:`SafetyStop` raised in it ends the movie as ``"safety_stop"``, a :class:`DeviceError` as
    ``"link_failure"`` (:attr:`outcome`, :attr:`error`; the caller reports them with what was acquired).
    Anything else (a bug in a callback, a bad corrected command, Ctrl-C) still leaves the skin at rest, then
    propagates; if even the rest fails, the firmware's watchdog rests the contactors.
    """

    def __init__(self, display: TactileDisplay) -> None:
        self.display = display
        self.outcome, self.error = "completed", ""

    def __enter__(self) -> "_MovieLoop":
        self._gc_was_enabled = gc.isenabled()
        gc.disable()
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if self._gc_was_enabled:
            gc.enable()
        if exc is None:
            return False
        if isinstance(exc, SafetyStop):
            self.outcome, self.error = "safety_stop", str(exc)
            return True
        if isinstance(exc, DeviceError):
            self.outcome, self.error = "link_failure", f"{type(exc).__name__}: {exc}"
            return True
        try:
            self.display.rest()
        except DeviceError:
            pass
        return False


def _rest_unless(display: TactileDisplay, skip: bool, error: str | None) -> tuple[bool, str | None]:
    """Send REST at the end of a movie unless ``skip``; returns (rested, error). A failed REST is reported in
    ``error`` (unless an earlier error is there) and leaves the firmware's watchdog to rest the contactors."""
    if skip:
        return True, error
    try:
        display.rest()
    except DeviceError as exc:
        return False, error or f"rest failed: {exc}"
    return True, error


# ---- timed, buffered playback -------------------------------------------------------------------------------------

#: Default lead of buffered playback (the FIFO's high watermark). This VM stalls the host for 15-55 ms every few
#: seconds (the bench's timer-only row); 80 ms rides those out with a margin, and stays well inside the firmware's
#: 128-frame FIFO (183 ms at 700 Hz). Longer buys nothing here and costs: a host that dies leaves up to the lead of
#: movie playing (then the watchdog rests the skin), and closed-loop corrections reach the skin that much later.
DEFAULT_LEAD_S = 0.080

#: Frames in flight (sent, reply not back) at most: a burst (the start, a catch-up after a stall) is paced by the
#: replies, so a 2 Mbaud line never holds more than ~20 ms of replies (below the driver's 50 ms ack timeout).
DEFAULT_WINDOW = 32

#: A frame whose play time is closer than this is not sent: it would reach the display late (at 2 Mbaud a timed
#: frame takes 0.56 ms on the line, plus whatever is queued before it) and be dropped there.
SEND_MARGIN_S = 0.002
_MIN_WAIT_S = 20e-6  # shorter waits are not worth a system call (and never end on a manual clock's rounding)

#: fate codes of :attr:`BufferedPlaybackReport.fates` besides the Disposition values
FATE_NOT_SENT = -2  # skipped by the host: its play time had passed
FATE_UNKNOWN = -1  # sent, no receipt came back


class FirmwareClock:
    """Where the display's movie epoch lies on the host clock, from (host receive time, firmware time) pairs.

    A reply leaves the display after the firmware time it carries, so ``host_time - firmware_time`` is the epoch
    on the host clock plus the reply's transit, never less: the smallest difference seen is the estimate (a host
    stall only makes a difference larger). To follow a display crystal slower than the host's, the estimate may
    rise by ``drift_ppm`` of the elapsed time; a faster one pulls it down at once.

    >>> clock = FirmwareClock(10.0, -0.05)  # START_MOVIE's reply seen at 10 s; it arrived 50 ms before the epoch
    >>> clock.epoch_s
    10.05
    >>> clock.update(10.0298, -0.02)  # a frame that arrived 20 ms before the epoch, its reply seen at 10.0298 s
    >>> round(clock.epoch_s, 4)
    10.0498
    >>> clock.update(10.2, 0.1)  # a reply the host read late (stalled) changes nothing
    >>> round(clock.epoch_s, 4)
    10.0498
    """

    def __init__(self, host_time_s: float, firmware_time_s: float, *, drift_ppm: float = 200.0) -> None:
        if not (np.isfinite(drift_ppm) and 0 <= drift_ppm <= 10_000):
            raise InvalidInputError(f"drift_ppm must be in 0..10000, got {drift_ppm!r}")
        self.epoch_s = float(host_time_s - firmware_time_s)
        self._drift = drift_ppm * 1e-6
        self._last = float(host_time_s)

    def update(self, host_time_s: float, firmware_time_s: float) -> None:
        grow = max(host_time_s - self._last, 0.0) * self._drift
        self.epoch_s = min(self.epoch_s + grow, host_time_s - firmware_time_s)
        self._last = max(self._last, host_time_s)


@dataclass
class BufferedPlaybackReport(PlaybackReport):
    """A :class:`PlaybackReport` of timed, buffered playback, with what the display said about it.

    Times: ``deadlines_s`` are the frames' play times and ``send_times_s`` when the host sent them, both on the
    host clock relative to tick 0 (estimated, :class:`FirmwareClock`), so sends are ``lead_s`` early.
    ``measured_um[k]`` is the positions sampled at tick k before frame k took effect (the response to frame
    k - 1), from the display's tick reports; ``acked[k]`` says one came back. ``missed_deadlines`` counts frames
    that reached the display at or after their play time (the firmware's count) plus frames the host did not send
    because their play time had passed; a frame lost on the wire is not "late": it shows as an underrun.
    """

    lead_s: float = float("nan")
    low_water_s: float = float("nan")
    late_frames: int = 0  # reached the display at or after their play time (dropped there)
    underruns: int = 0  # ticks with nothing to play (position held), whatever the cause
    fifo_rejects: int = 0
    reports_lost: int = 0  # tick reports overwritten in the display's log before a reply carried them
    frames_flushed: int = 0  # queued, then flushed by a stop before their tick
    final_status: MovieStatus | None = field(default=None, repr=False)
    #: per frame: Disposition code, FATE_UNKNOWN (no receipt) or FATE_NOT_SENT (skipped by the host)
    fates: np.ndarray = field(default=None, repr=False)
    #: per frame: FIFO fill after it arrived (NaN: no receipt)
    fifo_fill: np.ndarray = field(default=None, repr=False)
    #: per frame: play time - arrival time on the display's clock, s (NaN: no receipt); < 0 is a missed deadline
    arrival_margin_s: np.ndarray = field(default=None, repr=False)
    #: per tick: display clock of the tick relative to the epoch (NaN: no report), and whether a frame played
    tick_times_s: np.ndarray = field(default=None, repr=False)
    tick_applied: np.ndarray = field(default=None, repr=False)

    @property
    def playout_periods_s(self) -> np.ndarray:
        """Intervals between consecutive frames applied by the display, on the display's clock (from its tick
        reports; an underrun between two applied frames makes a longer interval; intervals spanning an unreported
        tick are left out)."""
        known = np.isfinite(self.tick_times_s)
        applied = np.flatnonzero(known & self.tick_applied)
        if applied.size < 2:
            return np.empty(0)
        unknown_before = np.cumsum(~known)
        whole = unknown_before[applied[1:]] == unknown_before[applied[:-1]]
        return np.diff(self.tick_times_s[applied])[whole]

    @property
    def playout_jitter_p99_s(self) -> float:
        """99th percentile of |playout period - 1/rate| on the display's clock (NaN with fewer than 2 frames)."""
        p = self.playout_periods_s
        return float(np.percentile(np.abs(p - 1.0 / self.rate_hz), 99)) if p.size else float("nan")

    @property
    def min_arrival_margin_s(self) -> float:
        """The smallest lead a frame actually had at the display (NaN: no receipt)."""
        m = self.arrival_margin_s
        return float(np.nanmin(m)) if m is not None and np.any(np.isfinite(m)) else float("nan")


def stream_movie_buffered(display: TactileDisplay, movie_um, *, rate_hz: float = 700.0,
                          lead_s: float = DEFAULT_LEAD_S, low_water_s: float | None = None,
                          callback: FrameCallback | None = None, window: int = DEFAULT_WINDOW,
                          settle_frames: int = 5, rest_at_end: bool = True, end_timeout_s: float = 0.25,
                          clock: Callable[[], float] = time.perf_counter) -> BufferedPlaybackReport:
    """Play ``movie_um`` (frames, 10, 10) in micrometres as a timed movie, buffered by the display.

    The display is told the rate and an epoch (``start_movie``: tick 0 plays ``lead_s`` after it arrives); frame
    k goes out with its tick when its play time is ``lead_s`` away (on the display's clock, estimated from its
    replies), and the firmware applies it from its FIFO on its own timer. Whenever the buffered time falls to
    ``low_water_s`` the host refills it to ``lead_s``; after a host stall every frame due goes out at once (paced by
    ``window``). A frame whose play time is less than :data:`SEND_MARGIN_S` away is not sent (it would be dropped
    as late). When the display does drop a late frame it holds the one before, and the next frame, limited here
    against the dropped one, may be up to two slew steps away: the firmware's own clamp (CLAMPED) takes it then.

    Parameters
    ----------
    display : TactileDisplay
        Must support timed playback; armed here if it is not armed yet (better: arming here, just before the
        movie starts, leaves no gap for the display's watchdog). Its range / slew limits apply to every frame;
        the slew limit holds between consecutive *played* frames.
    movie_um : array_like, shape (frames, 10, 10)
        Requested positions: finite real numbers (InvalidTargetError naming frame and contactor otherwise); out
        of range or slew they are limited by the driver (see :mod:`skinstretch.drivers.display.safety`).
    rate_hz : float, keyword-only
        Frame rate, 1..700 Hz.
    lead_s : float, keyword-only
        High watermark: how far ahead of its play time a frame is sent (default :data:`DEFAULT_LEAD_S`, why is
        said there). Between 2 periods and FIFO_DEPTH - 8 periods.
    low_water_s : float, keyword-only
        Refill when the buffered time falls to this (default ``lead_s``: one frame a period). Lower values batch
        the refills: fewer wake-ups, callbacks called in bursts.
    callback : callable, keyword-only
        Called as each frame is prepared, ``lead_s`` before it plays, with (index, command, latest measurement
        ack); returns a corrected command or None. **Its corrections reach the skin ``lead_s`` later**, and the
        measurements it sees are those of ticks already played. Raise SafetyStop in it to stop: the display's
        FIFO is flushed and the contactors ramp to rest at once (REST is never queued).
    window : int, keyword-only
        Most frames in flight (sent, reply not back).
    settle_frames : int, keyword-only
        Frames left out of the position error statistics.
    rest_at_end : bool, keyword-only
        Send REST once the last frame has played. Without it the caller must send frames or rest within the
        display's watchdog time after the last tick.
    end_timeout_s : float, keyword-only
        How long past the last frame's estimated play time to wait for the display to report it played.
    clock : callable, keyword-only
        Must be the clock the display driver uses (``time.perf_counter``).

    Returns
    -------
    BufferedPlaybackReport
        Outcome, everything acquired, missed deadlines (late at the display + not sent), underruns, FIFO fill,
        the display-clock playout periods. On a link failure the movie stops (``outcome="link_failure"``); the
        display plays what it holds, at most ``lead_s``, then its watchdog rests the contactors.
    """
    movie = _checked_movie(movie_um, rate_hz=rate_hz, settle_frames=settle_frames)
    rate_mhz = rate_to_mhz(rate_hz)
    period = 1000.0 / rate_mhz
    if not (np.isfinite(lead_s) and 2 * period <= lead_s <= min((FIFO_DEPTH - 8) * period, 1.0)):
        raise InvalidInputError(f"lead_s must be between 2 and {FIFO_DEPTH - 8} frame periods (at most 1 s), "
                                f"got {lead_s!r}")
    low_water = float(lead_s) if low_water_s is None else float(low_water_s)
    if not (np.isfinite(low_water) and 0 < low_water <= lead_s):
        raise InvalidInputError(f"low_water_s must be in (0, lead_s], got {low_water_s!r}")
    if not (isinstance(window, int) and 1 <= window <= 200):
        raise InvalidInputError(f"window must be an int in 1..200, got {window!r}")
    if not (np.isfinite(end_timeout_s) and 0 <= end_timeout_s <= 10):
        raise InvalidInputError(f"end_timeout_s must be in 0..10 s, got {end_timeout_s!r}")
    if not display.supports_timed_playback:
        raise InvalidInputError(f"display ({type(display).__name__}) has no timed playback; use stream_movie")

    n = movie.shape[0]
    commands, measured, acked, skipped, phases, cpu = _frame_arrays(n)
    # the firmware's tick times (tick_time_us), exact integers: floor(k * 1e9 / rate_mhz) us
    play_offsets = (np.arange(n, dtype=np.int64) * 1_000_000_000 // rate_mhz) * 1e-6
    send_times = np.full(n, np.nan)
    fates = np.full(n, FATE_UNKNOWN, dtype=np.int8)
    fill = np.full(n, np.nan)
    margin = np.full(n, np.nan)
    tick_times = np.full(n, np.nan)
    tick_applied = np.full(n, False)
    thread_time = time.thread_time
    latest: list[FrameAck | None] = [None]
    lost_before = getattr(display, "lost_acks", 0)
    fw_clock: FirmwareClock | None = None

    def file_acks(acks: list[FrameAck]) -> None:
        for ack in acks:
            latest[0] = ack
            if isinstance(ack, TimedFrameAck) and 0 <= ack.tick < n:
                measured[ack.tick] = ack.measured_um
                acked[ack.tick] = True
                tick_times[ack.tick] = ack.time_s
                tick_applied[ack.tick] = ack.applied

    def file_receipts(receipts: list[TimedReceipt]) -> None:
        for r in receipts:
            if 0 <= r.tick < n:
                fates[r.tick] = int(r.disposition)
                fill[r.tick] = r.fifo_fill
                margin[r.tick] = play_offsets[r.tick] - r.rx_time_s
            if fw_clock is not None:
                fw_clock.update(r.received_at, r.rx_time_s)

    def pump(timeout_s: float) -> None:
        file_acks(display.collect_acks(timeout_s=max(timeout_s, 0.0)))
        file_receipts(display.take_receipts())

    k = 0
    final: MovieStatus | None = None
    t_stop = float("nan")
    with _MovieLoop(display) as loop:  # on an unexpected error the firmware plays out what it holds, then rests
        if not display.armed:
            display.arm()  # after the allocations above: the watchdog runs from here until a frame plays
        status = display.start_movie(rate_hz=rate_hz, n_frames=n, start_delay_s=float(lead_s))
        fw_clock = FirmwareClock(clock(), status.time_us * 1e-6)
        while k < n:
            now = clock()
            if np.isnan(cpu[k]):  # stamped once, before any wait for this frame
                phases[k, 0] = now - fw_clock.epoch_s
                cpu[k] = thread_time()
            due = fw_clock.epoch_s + play_offsets[k]
            if due - now - low_water > _MIN_WAIT_S:  # enough is buffered: wait for the low watermark, reading replies
                pump(due - low_water - now)
                continue
            if display.outstanding >= window:  # a burst: let the replies catch up (a dead link raises here)
                pump(min(period, max(due - now, 0.0)))
                continue
            phases[k, 1] = clock() - fw_clock.epoch_s
            if due - now < SEND_MARGIN_S:
                # its play time has (nearly) passed: the host was stalled longer than the lead and the display
                # would drop it as late; the next frame is limited against what the contactors last got
                skipped[k] = True
                fates[k] = FATE_NOT_SENT
                send_times[k] = now - fw_clock.epoch_s
                commands[k] = display.last_command_um
                k += 1
                continue
            command = movie[k]
            if callback is not None:
                corrected = callback(k, command.copy(), latest[0])
                if corrected is not None:
                    command = corrected
            prepared = display.prepare_frame(command)
            phases[k, 2] = phases[k, 3] = clock() - fw_clock.epoch_s
            display.send_timed(k, prepared)
            send_times[k] = phases[k, 3]
            commands[k] = display.last_command_um
            phases[k, 4] = clock() - fw_clock.epoch_s
            k += 1
            if display.outstanding > window // 2:
                pump(0.0)
        # every frame is out: until the last one has played, poll the movie status once a period; each reply
        # carries a tick report no frame reply is left to carry (the last lead_s of measurements)
        give_up = fw_clock.epoch_s + play_offsets[n - 1] + 2 * period + end_timeout_s
        while True:
            final = display.read_movie_status()
            pump(0.0)
            backlog = final.report.present and final.report.tick < final.next_tick - 1
            if (final.next_tick >= n or not final.running) and not final.report.present:
                break
            if clock() >= give_up:
                break
            if not backlog:
                pump(min(period, give_up - clock()))
        t_stop = clock()
    outcome, error = loop.outcome, loop.error
    if np.isnan(t_stop):
        t_stop = clock()
    if outcome == "completed" and not rest_at_end:
        try:
            final = display.stop_movie()  # over: the display holds the last frame; frames or rest must follow
        except DeviceError as exc:
            outcome, error = "link_failure", f"{type(exc).__name__}: {exc}"
    # REST flushes whatever is still buffered and starts the ramp now; when it fails, the firmware plays out what it
    # holds, then its watchdog rests the contactors.
    rested, error = _rest_unless(display, outcome == "completed" and not rest_at_end, error)
    if outcome == "safety_stop":
        try:
            # after the stop (never before it): the counters stay readable, and the tick reports still waiting
            for _ in range(TICK_LOG_DEPTH + 1):
                final = display.read_movie_status()
                file_acks(display.collect_acks(timeout_s=0.0))
                if not final.report.present:
                    break
        except DeviceError as exc:
            error = f"{error}; reading the movie status failed: {exc}"
    file_receipts(display.take_receipts())
    # frames whose tick came before the movie ended (the rest were flushed unplayed or never reached)
    if final is not None:
        played = min(k, final.next_tick)
    elif fw_clock is not None:
        played = min(k, int(np.searchsorted(play_offsets, t_stop - fw_clock.epoch_s, side="right")))
    else:
        played = 0
    origin = fw_clock.epoch_s if fw_clock is not None else float("nan")
    late = final.late_frames if final is not None else int(np.sum(fates[:k] == Disposition.LATE))
    return BufferedPlaybackReport(
        outcome=outcome, error=error, rested=rested, rate_hz=float(rate_hz), frames_total=n, frames_played=played,
        commands_um=commands[:played], measured_um=measured[:played], acked=acked[:played],
        deadlines_s=play_offsets[:played], send_times_s=send_times[:played], skipped=skipped[:played],
        missed_deadlines=int(late + skipped[:k].sum()), miss_tolerance_s=0.0,
        lost_acks=getattr(display, "lost_acks", 0) - lost_before, settle_frames=settle_frames,
        phase_times_s=phases[:played], thread_cpu_s=cpu[:played] - cpu[0] if played else cpu[:0],
        clock_origin_s=origin, lead_s=float(lead_s), low_water_s=low_water, late_frames=int(late),
        underruns=final.underruns if final is not None else 0,
        fifo_rejects=final.fifo_rejects if final is not None else 0,
        reports_lost=final.reports_lost if final is not None else 0,
        frames_flushed=max(final.frames_queued - final.frames_played, 0) if final is not None else 0,
        final_status=final, fates=fates[:played], fifo_fill=fill[:played], arrival_margin_s=margin[:played],
        tick_times_s=tick_times[:played], tick_applied=tick_applied[:played])
