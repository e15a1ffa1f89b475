"""V4L2 camera through OpenCV: argument checks everywhere, streaming only where a /dev/video* device exists."""

from __future__ import annotations

import numpy as np
import pytest

from skinstretch.drivers.camera.v4l2 import V4L2Camera, v4l2_devices
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import InvalidInputError


def test_arguments_are_checked():
    with pytest.raises(InvalidInputError, match="device"):
        V4L2Camera("/tmp/not-a-camera")
    with pytest.raises(InvalidInputError, match="device"):
        V4L2Camera(-1)
    with pytest.raises(InvalidInputError, match="fourcc"):
        V4L2Camera(0, fourcc="GREY8")
    assert all(d.startswith("/dev/video") for d in v4l2_devices())


def test_absent_device_is_a_device_error():
    free = next(f"/dev/video{n}" for n in range(60, 100) if f"/dev/video{n}" not in v4l2_devices())
    with pytest.raises(DeviceError, match="cannot be opened"):
        V4L2Camera(free).open()


@pytest.mark.hardware
@pytest.mark.skipif(not v4l2_devices(), reason="no /dev/video* device on this machine")
def test_streams_from_the_first_device():
    with V4L2Camera(v4l2_devices()[0], fourcc="YUYV") as cam:
        cam.set_mode("full")
        cam.start()
        frames = cam.frames(5, timeout_s=5.0)
        cam.stop()
    assert all(f.image.dtype == np.uint8 and f.image.shape == (484, 640) for f in frames)
