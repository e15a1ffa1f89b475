"""Stream a tactile movie to a display at a fixed rate (up to 700 Hz) with deadline tracking.

Frames are pipelined: frame k is sent at its deadline ``t0 + k / rate`` without waiting for the ack of frame
k - 1 (at 2 Mbaud a request/ack round trip is ~1.1 ms of the 1.43 ms period, so a lock-step loop has no margin).
The wait for a deadline reads acks (the transport's blocking read, which releases the GIL) until ``spin_s``
before the deadline, then spins on ``perf_counter`` (sleep alone overshoots by 50-100 us on Linux).

On a link failure (write error, silent link, too many unacknowledged frames) the movie stops, the driver sends
rest when it can (the firmware watchdog does it otherwise) and the report, with everything acquired so far, is
returned flagged ``outcome="link_failure"``. A callback may correct each command (closed loop) and may stop the
movie by raising :class:`processing.errors.SafetyStop` (force ceiling): ``outcome="safety_stop"``.

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

from processing.errors import DeviceError, DeviceTimeoutError, InvalidInputError, SafetyStop

from .base import FrameAck, TactileDisplay
from .stress_protocol import COLS, ROWS

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
        Requested positions; anything unsafe is limited by the driver (see :mod:`drivers.display.safety`).
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
    movie = np.asarray(movie_um, dtype=float)
    if movie.ndim != 3 or movie.shape[1:] != (ROWS, COLS) or movie.shape[0] < 1:
        raise InvalidInputError(f"movie_um must have shape (frames, 10, 10), got {movie.shape}")
    if not (np.isfinite(rate_hz) and 1.0 <= rate_hz <= 700.0):
        raise InvalidInputError(f"rate_hz must be in 1..700 Hz, got {rate_hz!r}")
    period = 1.0 / rate_hz
    if not (np.isfinite(spin_s) and 0 <= spin_s < period):
        raise InvalidInputError(f"spin_s must be in [0, period), got {spin_s!r}")
    if not (isinstance(max_outstanding, int) and 1 <= max_outstanding <= 200):
        raise InvalidInputError(f"max_outstanding must be an int in 1..200, got {max_outstanding!r}")
    tolerance = period / 4 if miss_tolerance_s is None else float(miss_tolerance_s)
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise InvalidInputError(f"miss_tolerance_s must be >= 0, got {miss_tolerance_s!r}")
    if not (isinstance(settle_frames, int) and settle_frames >= 0):
        raise InvalidInputError(f"settle_frames must be an int >= 0, got {settle_frames!r}")

    n = movie.shape[0]
    # every per-frame array is written once here: np.zeros maps untouched pages, and a first touch inside the
    # loop would be a page fault on the deadline path
    commands = np.empty((n, ROWS, COLS))
    commands.fill(0.0)
    measured = np.full((n, ROWS, COLS), np.nan)
    acked = np.full(n, False)
    deadlines = np.arange(n) * period
    send_times = np.full(n, 0.0)
    skipped = np.full(n, False)
    phases = np.full((n, len(PHASES)), np.nan)
    cpu = np.full(n, np.nan)
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

    outcome, error, sent = "completed", "", 0
    t0 = float("nan")
    # a full garbage collection over thousands of acks takes milliseconds: none during the movie
    gc_was_enabled = gc.isenabled()
    gc.disable()
    try:
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
                raise DeviceTimeoutError(f"{display.outstanding} frames unacknowledged "
                                         f"({display.outstanding * period * 1000:.0f} ms of movie)")
        file_acks(display.collect_acks(timeout_s=0.0))
        end = clock() + final_ack_timeout_s
        while display.outstanding and clock() < end:
            file_acks(display.collect_acks(timeout_s=max(end - clock(), 0.0)))
    except SafetyStop as exc:
        outcome, error = "safety_stop", str(exc)
    except DeviceError as exc:
        outcome, error = "link_failure", f"{type(exc).__name__}: {exc}"
    except BaseException:
        # a bug in a callback, a bad corrected command, Ctrl-C: still leave the skin at rest, then re-raise
        try:
            display.rest()
        except DeviceError:
            pass  # the firmware watchdog does it
        raise
    finally:
        if gc_was_enabled:
            gc.enable()
    rested = True
    if outcome != "completed" or rest_at_end:
        try:
            display.rest()
        except DeviceError as exc:
            rested = False  # the firmware watchdog returns the contactors to rest
            error = error or f"rest failed: {exc}"
    lateness = (send_times[:sent] - deadlines[:sent])[~skipped[:sent]]
    return PlaybackReport(
        outcome=outcome, error=error, rested=rested, rate_hz=float(rate_hz), frames_total=n, frames_played=sent,
        commands_um=commands[:sent], measured_um=measured[:sent], acked=acked[:sent],
        deadlines_s=deadlines[:sent], send_times_s=send_times[:sent], skipped=skipped[:sent],
        missed_deadlines=int(np.sum(lateness > tolerance) + skipped[:sent].sum()), miss_tolerance_s=tolerance,
        lost_acks=getattr(display, "lost_acks", 0) - lost_before, settle_frames=settle_frames, clock_origin_s=t0,
        phase_times_s=phases[:sent], thread_cpu_s=cpu[:sent] - cpu[0] if sent else cpu[:0])
