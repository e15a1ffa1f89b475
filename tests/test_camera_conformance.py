"""One conformance suite for every Camera implementation available here (STYLE: one suite per device kind).

Implementations: the simulated camera, the Aravis in-process fake camera, Aravis over loopback GigE Vision
(``arv-fake-gv-camera-0.8``), and the replay camera. Aravis cases are skipped when the bindings or the fake
GigE Vision binary are missing.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from skinstretch.drivers.camera.base import Camera, DeviceError, Frame
from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import write_session
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.simulated_camera import SimulatedCamera
from skinstretch.simulators.gige_fake_camera import FakeGigECamera
from tests.helpers import wait_until

STRIP = CAMERA_MODES["strip"]


def _aravis_or_skip():
    from skinstretch.drivers.camera.aravis import aravis_available

    if not aravis_available():
        pytest.skip("Aravis GObject bindings not importable (gir1.2-aravis-0.8 + PyGObject)")


@pytest.fixture(scope="module")
def gv_camera_address():
    """``arv-fake-gv-camera-0.8`` serving on loopback; stopped in the finalizer."""
    _aravis_or_skip()
    server = FakeGigECamera("127.0.0.1")
    try:
        address = server.start()
    except DeviceError as exc:
        pytest.skip(str(exc))
    try:
        yield address
    finally:
        server.stop()


def _ramp_source(k: int) -> np.ndarray:
    image = np.zeros((STRIP.height, STRIP.width), np.uint8)
    image[:] = (np.arange(STRIP.width) + k) % 256
    return image


@pytest.fixture(
    params=[
        "simulated",
        pytest.param("aravis-fake", marks=pytest.mark.aravis),
        pytest.param("aravis-gv-loopback", marks=pytest.mark.aravis),
        "replay-session",
    ]
)
def camera(request, tmp_path) -> Camera:
    kind = request.param
    if kind == "simulated":
        cam = SimulatedCamera(_ramp_source, STRIP)
    elif kind == "aravis-fake":
        _aravis_or_skip()
        from skinstretch.drivers.camera.aravis import AravisCamera

        cam = AravisCamera.fake()
    elif kind == "aravis-gv-loopback":
        from skinstretch.drivers.camera.aravis import AravisCamera

        cam = AravisCamera(request.getfixturevalue("gv_camera_address"))
    else:
        from skinstretch.drivers.camera.replay import ReplayCamera

        frames = np.stack([_ramp_source(k) for k in range(40)])
        path = write_session(
            tmp_path / "strip.h5",
            frames,
            timestamps=np.arange(40) / STRIP.fps,
            camera_mode=STRIP,
            calibration=Calibration(px_per_mm=62.0),
        )
        cam = ReplayCamera(path, loop=True)
    yield cam
    cam.close()


def test_streams_frames_of_the_mode(camera, request):
    with camera:
        assert camera.is_open
        camera.set_mode(STRIP)
        assert camera.mode == STRIP
        camera.start()
        frames = camera.frames(30, timeout_s=5.0)
        camera.stop()
        stats = camera.stats
    assert not camera.is_open
    assert all(isinstance(f, Frame) for f in frames)
    assert all(f.image.shape == (STRIP.height, STRIP.width) and f.image.dtype == np.uint8 for f in frames)
    ids = np.array([f.frame_id for f in frames])
    assert np.all(np.diff(ids) >= 1)
    host = np.array([f.host_timestamp_s for f in frames])
    assert np.all(np.diff(host) >= 0) and abs(host[0] - time.time()) < 600
    assert stats.completed >= 30 and stats.delivered == 30
    if request.node.callspec.params["camera"].startswith("aravis"):
        # A real device (Aravis's fake runs on its own clock, over UDP or in process): a CPU-starved machine can
        # lose a frame; it must then be counted, never hidden. Zero loss is a benchmark target, not a test.
        assert stats.dropped + stats.failed >= int(np.sum(np.diff(ids) - 1))
    else:
        assert stats.dropped == 0 and stats.failed == 0


def test_frames_survive_stop_then_reads_fail_cleanly(camera):
    with camera:
        camera.set_mode(STRIP)
        camera.start()
        camera.read(5.0)
        wait_until(lambda: camera.stats.completed >= 5)
        camera.stop()
        queued = camera.stats.completed - camera.stats.delivered
        assert queued >= 4
        for _ in range(queued):
            camera.read(1.0)
        with pytest.raises(DeviceError):
            camera.read(0.05)


def test_restart_resets_stats(camera):
    with camera:
        camera.set_mode(STRIP)
        camera.start()
        camera.frames(3, timeout_s=5.0)
        camera.stop()
        camera.start()
        assert camera.stats.delivered == 0
        camera.frames(3, timeout_s=5.0)
        camera.stop()
        assert camera.stats.delivered == 3


def test_bad_use_raises_named_errors(camera):
    with pytest.raises(DeviceError):
        camera.set_mode(STRIP)  # not open
    with camera:
        with pytest.raises(InvalidInputError, match="unknown camera mode"):
            camera.set_mode("nonsense")
        camera.set_mode(STRIP)
        with pytest.raises(DeviceError, match="not streaming"):
            camera.read(0.05)
        with pytest.raises(InvalidInputError, match="timeout_s"):
            camera.read(0)
        camera.start()
        with pytest.raises(DeviceError, match="while streaming"):
            camera.set_mode(STRIP)
        camera.stop()
