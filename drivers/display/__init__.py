"""The STReSS 10x10 tactile display: interface, wire protocol, safety limits, transports, driver, playback.

- :mod:`.base`: :class:`TactileDisplay` (identify, arm, disarm, zero, rest, send_frame, submit_frame /
  collect_acks, read_status; timed playback: start_movie, send_timed, take_receipts, stop_movie), :class:`FrameAck`,
  :class:`TimedFrameAck`, :class:`TimedReceipt`, :class:`DisplayInfo`.
- :mod:`.stress_protocol`: the pure byte codec (``docs/protocols/stress.md``).
- :mod:`.safety`: :func:`limit_command`, the range and slew clamp every frame passes.
- :mod:`.transports`: :class:`SerialTransport` (pyserial URL / device) and :class:`UsbTransport` (pyusb bulk).
- :mod:`.stress`: :class:`StressDisplay` over any transport.
- :mod:`.playback`: :func:`stream_movie_buffered` (timed frames played by the display's FIFO ->
  :class:`BufferedPlaybackReport`) and :func:`stream_movie` (immediate frames on deadlines -> :class:`PlaybackReport`),
  up to 700 Hz.
"""

from .base import DisplayInfo, FrameAck, PreparedFrame, TactileDisplay, TimedFrameAck, TimedReceipt
from .movie_stream import BufferedPlaybackReport, PlaybackReport, stream_movie, stream_movie_buffered
from .safety import LimitedCommand, limit_command
from .stress import StressDisplay
from .transports import SerialTransport, Transport, UsbTransport

__all__ = ["DisplayInfo", "FrameAck", "PreparedFrame", "TactileDisplay", "TimedFrameAck", "TimedReceipt",
           "PlaybackReport", "BufferedPlaybackReport", "stream_movie", "stream_movie_buffered", "LimitedCommand",
           "limit_command", "StressDisplay", "SerialTransport", "Transport", "UsbTransport"]
