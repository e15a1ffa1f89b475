"""The STReSS 10x10 tactile display: interface, wire protocol, safety limits, transports, driver, playback.

- :mod:`.base`: :class:`TactileDisplay` (identify, arm, disarm, zero, rest, send_frame, submit_frame /
  collect_acks, read_status), :class:`FrameAck`, :class:`DisplayInfo`.
- :mod:`.stress_protocol`: the pure byte codec (``docs/protocols/stress.md``).
- :mod:`.safety`: :func:`limit_command`, the range and slew clamp every frame passes.
- :mod:`.transports`: :class:`SerialTransport` (pyserial URL / device) and :class:`UsbTransport` (pyusb bulk).
- :mod:`.stress`: :class:`StressDisplay` over any transport.
- :mod:`.playback`: :func:`stream_movie` at up to 700 Hz with deadline tracking -> :class:`PlaybackReport`.
"""

from .base import DisplayInfo, FrameAck, PreparedFrame, TactileDisplay
from .playback import PlaybackReport, stream_movie
from .safety import LimitedCommand, limit_command
from .stress import StressDisplay
from .transports import SerialTransport, Transport, UsbTransport

__all__ = ["DisplayInfo", "FrameAck", "PreparedFrame", "TactileDisplay", "PlaybackReport", "stream_movie",
           "LimitedCommand", "limit_command", "StressDisplay", "SerialTransport", "Transport", "UsbTransport"]
