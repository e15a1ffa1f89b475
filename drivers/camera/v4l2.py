"""Video4Linux2 cameras through OpenCV's ``CAP_V4L2`` backend, behind the :class:`Camera` interface.

OpenCV does not expose the V4L2 buffer sequence number, but it does expose the buffer time stamp
(``CAP_PROP_POS_MSEC``). Frame ids are therefore derived from the time stamps (``round(dt * fps)`` since the first
frame), so a frame the driver lost shows as a gap in the ids and is counted as dropped, as for the other cameras.
"""

from __future__ import annotations

import math
import os
import time

import cv2
import numpy as np

from skinstretch.drivers.camera.base import Camera, Frame
from skinstretch.drivers.camera_modes import CameraMode
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import InvalidInputError

__all__ = ["V4L2Camera", "v4l2_devices"]


def v4l2_devices() -> list[str]:
    """Paths of the V4L2 device nodes present (``/dev/video*``), sorted."""
    try:
        names = os.listdir("/dev")
    except OSError:
        return []
    return sorted(f"/dev/{n}" for n in names if n.startswith("video") and n[5:].isdigit())


class V4L2Camera(Camera):
    """A V4L2 camera (``/dev/videoN``) read through OpenCV.

    Parameters
    ----------
    device : int or str
        Device index N or path ``/dev/videoN``.
    fourcc : str
        Pixel format requested from the driver ("GREY" for 8-bit monochrome cameras, "YUYV", "MJPG"...);
        colour frames are converted to grey.
    queue_size : int
        Frames held between the acquisition thread and :meth:`read`.
    """

    def __init__(self, device: int | str = 0, *, fourcc: str = "GREY", queue_size: int = 256) -> None:
        super().__init__(queue_size=queue_size)
        if isinstance(device, str):
            if not device.startswith("/dev/video"):
                raise InvalidInputError(f"device must be an index or a /dev/videoN path, got {device!r}")
        elif not isinstance(device, int) or device < 0:
            raise InvalidInputError(f"device must be a non-negative index or a /dev/videoN path, got {device!r}")
        if not isinstance(fourcc, str) or len(fourcc) != 4:
            raise InvalidInputError(f"fourcc must be a 4-character code, got {fourcc!r}")
        self._device = device
        self._fourcc = fourcc
        self._cap: cv2.VideoCapture | None = None
        self._first_t: float | None = None
        self._count = 0

    def _do_open(self) -> None:
        cap = cv2.VideoCapture(self._device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise DeviceError(f"V4L2 device {self._device!r} cannot be opened (present: {v4l2_devices()})")
        self._cap = cap

    def _do_close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def _do_set_mode(self, mode: CameraMode) -> None:
        cap = self._cap
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*self._fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, mode.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, mode.height)
        cap.set(cv2.CAP_PROP_FPS, mode.fps)
        got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        if got != (mode.width, mode.height):
            raise InvalidInputError(
                f"V4L2 device {self._device!r} cannot do {mode.width}x{mode.height} (it set {got[0]}x{got[1]})"
            )
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        if fps > 0 and abs(fps - mode.fps) > 0.01 * mode.fps:
            raise InvalidInputError(f"V4L2 device {self._device!r} cannot do {mode.fps} fps (it set {fps})")

    def _do_start(self) -> None:
        self._first_t = None
        self._count = 0

    def _do_stop(self) -> None:
        pass

    def _do_grab(self) -> Frame | None:
        ok, image = self._cap.read()
        host_t = time.time()
        if not ok or image is None:
            self._count_failed()
            return None
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        image = np.ascontiguousarray(image)
        mode = self._mode
        if image.shape != (mode.height, mode.width):
            self._count_failed()
            return None
        device_t = float(self._cap.get(cv2.CAP_PROP_POS_MSEC)) * 1e-3
        if device_t > 0 and math.isfinite(device_t):
            if self._first_t is None:
                self._first_t = device_t
            frame_id = int(round((device_t - self._first_t) * mode.fps))
        else:
            device_t, frame_id = math.nan, self._count
        self._count += 1
        return Frame(image, frame_id, device_t, host_t)

    def __repr__(self) -> str:
        return f"V4L2Camera({self._device!r})"
