"""Cameras: the :class:`~skinstretch.drivers.camera.base.Camera` interface and its drivers.

* :class:`skinstretch.drivers.camera.aravis.AravisCamera`: GigE Vision / USB3 Vision cameras through Aravis (optional
  system package; import it from its module).
* :class:`skinstretch.drivers.camera.v4l2.V4L2Camera`: Video4Linux2 devices through OpenCV.
* :class:`skinstretch.drivers.camera.replay.ReplayCamera`: session files, image sequences and video files, replayed.

The simulated camera lives in :mod:`skinstretch.simulators.simulated_camera` (drivers never import simulators).
"""

from skinstretch.drivers.camera.base import (
    Camera,
    CameraStats,
    Clock,
    EndOfStreamError,
    Frame,
    FrameIdUnwrapper,
    ManualClock,
    MonotonicClock,
)

__all__ = [
    "Camera",
    "CameraStats",
    "Clock",
    "EndOfStreamError",
    "Frame",
    "FrameIdUnwrapper",
    "ManualClock",
    "MonotonicClock",
]
