"""The tactile display interface: one small ABC, public methods validate and clamp, ``_do_*`` talk to the device.

Every command passes :func:`skinstretch.drivers.display.safety.limit_command` in :meth:`TactileDisplay.send_frame` /
:meth:`TactileDisplay.submit_frame` / :meth:`TactileDisplay.send_timed` before a subclass sees it, so no concrete
driver can forget the limits.

Two ways to play frames: *immediate* (:meth:`~TactileDisplay.send_frame`, :meth:`~TactileDisplay.submit_frame`:
the display applies a frame when it arrives) and *timed* (:meth:`~TactileDisplay.start_movie` then
:meth:`~TactileDisplay.send_timed`: each frame carries its play tick, the display buffers it and applies it on its
own timer). A display without a firmware FIFO says so with :attr:`~TactileDisplay.supports_timed_playback`.
"""

from __future__ import annotations

import abc
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from skinstretch.drivers.errors import DeviceError, InvalidTargetError, ProtocolError

from skinstretch.processing.errors import InvalidInputError

from .safety import LimitedCommand, check_target, limit_command, validate_limits
from .stress_protocol import (COLS, DEFAULT_MAX_STEP_UM, DEFAULT_WATCHDOG_S, MAX_START_DELAY_US, RANGE_UM, ROWS,
                              Disposition, MovieStart, MovieStatus, Status, StatusReport, TimedFrameReply,
                              rate_to_mhz)


@dataclass(frozen=True)
class DisplayInfo:
    """What the display says it is."""

    model: str
    firmware: str
    protocol_version: int
    rows: int
    cols: int
    range_um: float
    max_rate_hz: int


@dataclass(frozen=True)
class FrameAck:
    """The display's answer to one frame: the contactors' measured positions when the frame arrived."""

    seq: int
    status: Status
    measured_um: np.ndarray = field(repr=False)  # (10, 10) um
    command_um: np.ndarray = field(repr=False)  # the (limited) command this ack answers
    sent_at: float  # host perf_counter when the frame was written
    received_at: float  # host perf_counter when the ack was decoded

    @property
    def round_trip_s(self) -> float:
        return self.received_at - self.sent_at


@dataclass(frozen=True)
class TimedFrameAck(FrameAck):
    """A measurement from timed playback: the positions sampled at movie tick ``tick``, just before that tick's
    frame took effect, i.e. the response to the command in force since tick - 1.

    The fields keep :class:`FrameAck`'s meaning for consumers that pair consecutive acks (``measured_um`` of one
    answers ``command_um`` of the one before, e.g. ``skinstretch.experiments.playback.ContactorCorrector``): ``seq`` is
    ``tick % 256`` (consecutive records are consecutive ticks), ``command_um`` the command in force after this
    tick (the tick's frame when ``applied``, otherwise the one held). ``sent_at`` is when the tick's frame left
    the host (NaN if it never did), ``received_at`` when the reply carrying this report arrived.
    """

    tick: int
    time_s: float  # firmware clock, seconds after the movie epoch
    applied: bool  # a frame was applied at this tick (else: underrun, position held)


@dataclass(frozen=True)
class TimedReceipt:
    """The display's reply to one timed frame: what became of it, the FIFO fill, when it arrived (firmware clock).

    ``reply`` is the decoded wire record (:class:`~skinstretch.drivers.display.stress_protocol.TimedFrameReply`).
    """

    seq: int  # wire sequence number of the frame
    tick: int
    command_um: np.ndarray = field(repr=False)
    reply: TimedFrameReply = field(repr=False)
    sent_at: float  # host clock
    received_at: float  # host clock

    @property
    def disposition(self) -> Disposition:
        return self.reply.disposition

    @property
    def late(self) -> bool:
        """The frame reached the display at or after its play time (dropped): a missed deadline."""
        return self.reply.disposition == Disposition.LATE

    @property
    def rx_time_s(self) -> float:
        """Firmware clock when the frame arrived, seconds after the movie epoch."""
        return self.reply.rx_time_us * 1e-6

    @property
    def fifo_fill(self) -> int:
        return self.reply.fifo_fill


@dataclass(frozen=True)
class PreparedFrame:
    """A limited, encoded frame ready to go at its deadline (see :meth:`TactileDisplay.prepare_frame`).

    ``command_um`` is read-only. When it is sent, the driver decodes ``wire`` and refuses the frame unless the
    bytes carry exactly ``command_um`` and are safe; the command it then remembers is the one the bytes carried.
    """

    command_um: np.ndarray = field(repr=False)
    wire: object = field(repr=False)  # whatever the driver needs to send it fast (e.g. the encoded payload)
    epoch: int  # the driver's command epoch it was limited against
    clamped: bool = False  # the request had to be clamped (range or slew) to make this command


class TactileDisplay(abc.ABC):
    """A 10x10 lateral skin-stretch display.

    Subclasses implement the ``_do_*`` methods; the public methods validate arguments, enforce the range and
    slew limits, and keep the last command and the acks.

    Parameters
    ----------
    range_um : float, keyword-only
        Largest commanded deflection (<= 50 um).
    max_step_um : float, keyword-only
        Largest change of one contactor between consecutive frames.
    watchdog_s : float, keyword-only
        The firmware returns every contactor to rest when no frame arrived for this long.

    Attributes
    ----------
    acks : deque of FrameAck
        The most recent :data:`ACK_HISTORY` acks (bounded: a 10-minute movie at 700 Hz would otherwise hold 420 000
        acks and their position arrays). :attr:`acks_received` counts every ack ever collected, so a consumer can
        tell how many are new since it last looked.
    """

    ACK_HISTORY = 4096

    def __init__(self, *, range_um: float = RANGE_UM, max_step_um: float = DEFAULT_MAX_STEP_UM,
                 watchdog_s: float = DEFAULT_WATCHDOG_S) -> None:
        self.range_um, self.max_step_um = validate_limits(range_um=range_um, max_step_um=max_step_um)
        if not (np.isfinite(watchdog_s) and 0.001 <= watchdog_s <= 65.0):
            raise InvalidInputError(f"watchdog_s must be in 0.001..65 s, got {watchdog_s!r}")
        self.watchdog_s = float(watchdog_s)
        self._last_command = np.zeros((ROWS, COLS))
        self._epoch = 0  # bumped whenever _last_command changes: a prepared frame is only valid in its epoch
        self._armed = False
        self._movie: MovieStart | None = None  # the timed movie this host started (None: immediate mode)
        self._next_tick = 0  # timed frames go out in increasing tick order
        self.acks: deque[FrameAck] = deque(maxlen=self.ACK_HISTORY)
        self.acks_received = 0
        self.frames_clamped = 0  # prepared frames whose request had to be clamped (range or slew)

    # ---- public API ------------------------------------------------------------------------------------------

    @property
    def last_command_um(self) -> np.ndarray:
        """The last command that left the driver (a copy)."""
        return self._last_command.copy()

    @property
    def armed(self) -> bool:
        return self._armed

    def identify(self) -> DisplayInfo:
        """Ask the display what it is."""
        return self._do_identify()

    def arm(self) -> None:
        """Configure the watchdog and slew limit on the display, then enable the contactors."""
        self._do_configure(watchdog_s=self.watchdog_s, max_step_um=self.max_step_um)
        self._movie = None
        self._do_arm()
        self._set_last(np.zeros((ROWS, COLS)))
        self._armed = True

    def disarm(self) -> None:
        """Disable the contactors (the firmware brings them to rest first; a timed movie is flushed)."""
        self._armed = False
        self._movie = None
        self._do_disarm()
        self._set_last(np.zeros((ROWS, COLS)))

    def zero(self) -> None:
        """Re-reference the position sensors with the contactors at rest. Only while disarmed."""
        if self._armed:
            raise DeviceError("zero() needs a disarmed display; call disarm() first")
        self._do_zero()

    def rest(self) -> None:
        """Send every contactor back to 0 with the firmware's soft ramp, at once (a timed movie is flushed)."""
        self._movie = None
        self._do_rest()
        self._set_last(np.zeros((ROWS, COLS)))

    def read_status(self) -> StatusReport:
        """Status bits, measured positions and the firmware's counters."""
        return self._do_read_status()

    def measured_positions_um(self) -> np.ndarray:
        """The contactors' measured positions now (10, 10) um (one status round trip)."""
        return self.read_status().positions_um

    def limit(self, positions_um) -> LimitedCommand:
        """What :meth:`send_frame` would actually send for ``positions_um`` (does not send).

        Raises :class:`~skinstretch.drivers.errors.InvalidTargetError` naming the contactor for NaN, inf, complex
        or non-numeric values and for a wrong shape (see :func:`skinstretch.drivers.display.safety.check_target`).
        """
        return limit_command(positions_um, self._last_command, range_um=self.range_um,
                             max_step_um=self.max_step_um)

    def send_frame(self, positions_um, *, timeout_s: float = 0.1) -> FrameAck:
        """Clamp, send one (10, 10) frame in micrometres and wait for its ack (recorded in :attr:`acks`)."""
        seq = self.submit_frame(positions_um)
        for ack in self.collect_acks(wait_for=seq, timeout_s=timeout_s):
            if ack.seq == seq:
                return ack
        raise AssertionError("collect_acks returned without the awaited ack")  # pragma: no cover

    def submit_frame(self, positions_um) -> int:
        """Clamp and send one frame without waiting; returns its sequence number. Pair with collect_acks."""
        return self.send_prepared(self.prepare_frame(positions_um))

    def prepare_frame(self, positions_um) -> PreparedFrame:
        """Limit and encode a frame ahead of its deadline; :meth:`send_prepared` then only writes bytes."""
        limited = self.limit(positions_um)
        command = limited.command_um
        command.flags.writeable = False  # what the wire bytes were made from must not change behind them
        if limited.modified:
            self.frames_clamped += 1
        return PreparedFrame(command, self._do_prepare_frame(command), self._epoch, limited.modified)

    def send_prepared(self, frame: PreparedFrame) -> int:
        """Send a prepared frame; re-limited first if another command left since it was prepared."""
        if not self._armed:
            raise DeviceError("the display is not armed; call arm() before sending frames")
        if self._movie is not None:
            raise DeviceError("a timed movie is running: send_timed() its frames, or stop_movie() / rest() first")
        wire, carried = self._verified(frame)
        seq = self._do_send_prepared(wire, carried)
        self._set_last(carried)
        return seq

    def _verified(self, frame: PreparedFrame) -> tuple[object, np.ndarray]:
        """The wire bytes of ``frame`` and the command they carry, decoded from the bytes themselves; refused
        (InvalidTargetError, nothing sent) when they disagree with ``frame.command_um`` or break the limits."""
        if not isinstance(frame, PreparedFrame):
            raise InvalidInputError(f"frame must be a PreparedFrame, got {type(frame).__name__}")
        if frame.epoch != self._epoch:  # limited against a stale previous command: the slew bound would not hold
            frame = self.prepare_frame(frame.command_um)
        declared = frame.command_um
        if not (isinstance(declared, np.ndarray) and declared.dtype == np.float64 and declared.shape == (ROWS, COLS)):
            declared = check_target(declared, name="PreparedFrame.command_um")
        try:
            carried = np.asarray(self._do_wire_command(frame.wire), dtype=float)
        except (ProtocolError, InvalidInputError, TypeError, ValueError) as exc:
            raise InvalidTargetError(f"PreparedFrame.wire is not a frame of this display ({exc}); not sent") from None
        # this runs at the frame's deadline: the cheap whole-array tests first, the contactor only on failure
        if carried.shape != (ROWS, COLS) or not np.array_equal(carried, declared):
            if carried.shape != (ROWS, COLS):
                raise InvalidTargetError(f"PreparedFrame.wire carries shape {carried.shape}; not sent")
            where = tuple(int(v) for v in np.argwhere(carried != declared)[0])
            raise InvalidTargetError(f"PreparedFrame's command and its wire bytes disagree at contactor {where}: "
                                     f"command {declared[where]} um, wire {carried[where]} um; not sent",
                                     contactor=where)
        if np.abs(carried).max() > self.range_um or np.abs(carried - self._last_command).max() > self.max_step_um:
            unsafe = (np.abs(carried) > self.range_um) | (np.abs(carried - self._last_command) > self.max_step_um)
            where = tuple(int(v) for v in np.argwhere(unsafe)[0])
            raise InvalidTargetError(f"PreparedFrame at contactor {where} ({carried[where]} um after "
                                     f"{self._last_command[where]} um) breaks the range or slew limit; not sent",
                                     contactor=where)
        return frame.wire, carried

    # ---- timed playback ----------------------------------------------------------------------------------------

    @property
    def supports_timed_playback(self) -> bool:
        """Whether the display buffers timed frames (:meth:`start_movie`, :meth:`send_timed`)."""
        return False

    @property
    def movie(self) -> MovieStart | None:
        """The timed movie started by :meth:`start_movie` and not yet stopped (None: immediate mode)."""
        return self._movie

    def start_movie(self, *, rate_hz: float, n_frames: int, start_delay_s: float) -> MovieStatus:
        """Start a timed movie: tick k plays ``start_delay_s + k / rate_hz`` after the display receives this.

        Any frames still buffered from an earlier movie are flushed. The display must be armed. ``n_frames`` 0
        means open-ended.
        """
        if not self._armed:
            raise DeviceError("the display is not armed; call arm() before starting a movie")
        if not self.supports_timed_playback:
            raise DeviceError(f"{type(self).__name__} has no timed playback; stream frames immediately instead")
        if not (isinstance(n_frames, (int, np.integer)) and 0 <= n_frames <= 0xFFFFFFFF):
            raise InvalidInputError(f"n_frames must be an int in 0..2**32-1, got {n_frames!r}")
        if not (np.isfinite(start_delay_s) and 0 <= start_delay_s <= MAX_START_DELAY_US * 1e-6):
            raise InvalidInputError(f"start_delay_s must be in 0..{MAX_START_DELAY_US * 1e-6:g} s, "
                                    f"got {start_delay_s!r}")
        start = MovieStart(rate_to_mhz(rate_hz), int(n_frames), int(round(start_delay_s * 1e6)))
        self._movie = None
        status = self._do_start_movie(start)
        self._movie = start
        self._next_tick = 0
        return status

    def send_timed(self, tick: int, frame: PreparedFrame) -> int:
        """Send a prepared frame to be played at movie tick ``tick``; returns its sequence number.

        Ticks must increase (a skipped tick holds the previous frame on the display), so the slew limit the
        frame was prepared against is the limit between consecutive *played* frames.
        """
        if not self._armed:
            raise DeviceError("the display is not armed; call arm() before sending frames")
        if self._movie is None:
            raise DeviceError("no timed movie is running; call start_movie() first")
        if not (isinstance(tick, (int, np.integer)) and tick >= self._next_tick):
            raise InvalidInputError(f"tick must be an int >= {self._next_tick} (ticks increase), got {tick!r}")
        if self._movie.n_frames and tick >= self._movie.n_frames:
            raise InvalidInputError(f"tick must be below the movie's n_frames {self._movie.n_frames}, got {tick}")
        wire, carried = self._verified(frame)
        seq = self._do_send_timed(int(tick), wire, carried)
        self._set_last(carried)
        self._next_tick = int(tick) + 1
        return seq

    def submit_timed_frame(self, tick: int, positions_um) -> int:
        """Clamp and send one frame for movie tick ``tick`` (see :meth:`send_timed`)."""
        return self.send_timed(tick, self.prepare_frame(positions_um))

    def take_receipts(self) -> list[TimedReceipt]:
        """Receipts of timed frames decoded since the last call (the replies are read by :meth:`collect_acks`)."""
        return self._do_take_receipts()

    def stop_movie(self) -> MovieStatus:
        """Flush the display's FIFO and end the movie at once; the contactors hold their position."""
        self._movie = None
        return self._do_stop_movie()

    def read_movie_status(self) -> MovieStatus:
        """The movie's counters (kept after it ends) and one pending tick report (collected as an ack)."""
        return self._do_read_movie_status()

    def _set_last(self, command_um: np.ndarray) -> None:
        self._last_command = command_um
        self._epoch += 1

    def collect_acks(self, *, wait_for: int | None = None, timeout_s: float = 0.0) -> list[FrameAck]:
        """Acks that arrived since the last call (also appended to the bounded :attr:`acks` history).

        With ``wait_for`` a sequence number, wait up to ``timeout_s`` for that ack (DeviceTimeoutError if it does
        not come); otherwise return what is there without waiting beyond ``timeout_s``.
        """
        if not (np.isfinite(timeout_s) and timeout_s >= 0):
            raise InvalidInputError(f"timeout_s must be >= 0, got {timeout_s!r}")
        got = self._do_collect_acks(wait_for=wait_for, timeout_s=float(timeout_s))
        self.acks.extend(got)
        self.acks_received += len(got)
        return got

    @property
    @abc.abstractmethod
    def outstanding(self) -> int:
        """Frames sent whose ack has not arrived yet."""

    def declare_link_lost(self, reason: str) -> None:
        """The caller has found the link dead (e.g. too many frames unacknowledged): later commands (REST,
        DISARM) are sent once without waiting long for their replies; the firmware watchdog rests the contactors."""
        self._do_declare_link_lost(str(reason))

    def close(self) -> None:
        """Rest (when the link still works) and release the transport."""
        self._do_close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- device specifics -----------------------------------------------------------------------------------

    @abc.abstractmethod
    def _do_identify(self) -> DisplayInfo: ...

    @abc.abstractmethod
    def _do_configure(self, *, watchdog_s: float, max_step_um: float) -> None: ...

    @abc.abstractmethod
    def _do_arm(self) -> None: ...

    @abc.abstractmethod
    def _do_disarm(self) -> None: ...

    @abc.abstractmethod
    def _do_zero(self) -> None: ...

    @abc.abstractmethod
    def _do_rest(self) -> None: ...

    @abc.abstractmethod
    def _do_read_status(self) -> StatusReport: ...

    @abc.abstractmethod
    def _do_submit_frame(self, command_um: np.ndarray) -> int:
        """Send an already limited command; return its sequence number."""

    def _do_prepare_frame(self, command_um: np.ndarray) -> object:
        """Precompute what sending ``command_um`` needs (default: a copy of the command)."""
        return command_um.copy()

    def _do_wire_command(self, wire: object) -> np.ndarray:
        """The command a prepared ``wire`` carries (the inverse of :meth:`_do_prepare_frame`)."""
        return np.array(wire, dtype=float)

    def _do_send_prepared(self, wire: object, command_um: np.ndarray) -> int:
        """Send a prepared frame (default: :meth:`_do_submit_frame`)."""
        return self._do_submit_frame(command_um)

    @abc.abstractmethod
    def _do_collect_acks(self, *, wait_for: int | None, timeout_s: float) -> list[FrameAck]: ...

    # timed playback: only displays with a firmware FIFO implement these (supports_timed_playback)
    def _do_start_movie(self, start: MovieStart) -> MovieStatus:
        raise DeviceError(f"{type(self).__name__} has no timed playback")

    def _do_send_timed(self, tick: int, wire: object, command_um: np.ndarray) -> int:
        raise DeviceError(f"{type(self).__name__} has no timed playback")

    def _do_take_receipts(self) -> list[TimedReceipt]:
        return []

    def _do_stop_movie(self) -> MovieStatus:
        raise DeviceError(f"{type(self).__name__} has no timed playback")

    def _do_read_movie_status(self) -> MovieStatus:
        raise DeviceError(f"{type(self).__name__} has no timed playback")

    def _do_declare_link_lost(self, reason: str) -> None:
        """Default: nothing (a display without replies to wait for)."""

    @abc.abstractmethod
    def _do_close(self) -> None: ...
