"""The replay camera: session files, PNG/TIFF sequences, video files; pacing and end of stream."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from skinstretch.drivers.camera.base import EndOfStreamError, ManualClock
from skinstretch.drivers.camera.replay import ReplayCamera
from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import write_session
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import DeviceTimeoutError, FrameFileError, SessionFileError
from skinstretch.processing.errors import InvalidInputError

STRIP = CAMERA_MODES["strip"]


def _frames(n: int, h: int = 100, w: int = 640, dtype=np.uint8) -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.integers(0, np.iinfo(dtype).max, size=(n, h, w), dtype=dtype)


def _read_all(cam) -> list:
    out = []
    while True:
        try:
            out.append(cam.read(2.0))
        except EndOfStreamError:
            return out


@pytest.fixture
def session_path(tmp_path):
    ts = 1000.0 + np.array([0.0, 0.01, 0.02, 0.05, 0.06])  # an irregular recording, a gap in the ids
    return write_session(
        tmp_path / "rec.h5",
        _frames(5),
        timestamps=ts,
        frame_ids=np.array([7, 8, 9, 12, 13]),
        camera_mode=STRIP,
        calibration=Calibration(px_per_mm=62.0),
    )


def test_session_replay_keeps_ids_and_images(session_path):
    with ReplayCamera(session_path, rate_hz=math.inf) as cam:
        assert cam.mode.name == "strip" and (cam.mode.width, cam.mode.height) == (640, 100)
        cam.start()
        frames = _read_all(cam)
        stats = cam.stats
    np.testing.assert_array_equal(np.stack([f.image for f in frames]), _frames(5))
    assert [f.frame_id for f in frames] == [7, 8, 9, 12, 13]
    assert stats.dropped == 2  # the recording's own gap
    assert stats.delivered == 5


def test_session_replay_follows_the_recorded_times(session_path):
    clock = ManualClock()
    with ReplayCamera(session_path, clock=clock) as cam:
        cam.start()
        clock.advance(0.025)
        assert [cam.read(2.0).frame_id for _ in range(3)] == [7, 8, 9]
        with pytest.raises(DeviceTimeoutError):  # frame 3 was recorded at +0.05 s
            cam.read(0.05)
        clock.advance(0.03)
        assert cam.read(2.0).frame_id == 12


def test_chosen_rate_and_loop(session_path):
    clock = ManualClock()
    with ReplayCamera(session_path, rate_hz=10.0, loop=True, clock=clock) as cam:
        assert cam.mode.fps == 10.0
        cam.start()
        clock.advance(0.75)  # frames 0..7 due
        ids = [cam.read(2.0).frame_id for _ in range(8)]
        assert ids == [7, 8, 9, 12, 13, 14, 15, 16]


def test_image_sequences_png_tiff_and_glob(tmp_path):
    frames8 = _frames(4, 20, 30)
    for k, f in enumerate(frames8):
        cv2.imwrite(str(tmp_path / f"f{k:03d}.png"), f)
    with ReplayCamera(tmp_path, rate_hz=math.inf) as cam:
        cam.start()
        got = _read_all(cam)
    np.testing.assert_array_equal(np.stack([f.image for f in got]), frames8)
    tif = tmp_path / "tif"
    tif.mkdir()
    frames16 = _frames(3, 20, 30, np.uint16)
    for k, f in enumerate(frames16):
        cv2.imwrite(str(tif / f"g{k}.tiff"), f)
    with ReplayCamera(str(tif / "g*.tiff"), rate_hz=math.inf) as cam:
        cam.start()
        got = _read_all(cam)
    assert got[0].image.dtype == np.uint16
    np.testing.assert_array_equal(np.stack([f.image for f in got]), frames16)
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), np.dstack([frames8[0]] * 3))
    with ReplayCamera([colour], rate_hz=math.inf) as cam:
        cam.start()
        np.testing.assert_array_equal(cam.read(2.0).image, frames8[0])


def test_video_file_like_the_seed_avi(tmp_path):
    path = tmp_path / "movie.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48), isColor=False)
    for k in range(6):
        writer.write(np.full((48, 64), 40 * k, np.uint8))
    writer.release()
    with ReplayCamera(path, rate_hz=math.inf) as cam:
        assert cam.mode.fps == pytest.approx(30.0) and (cam.mode.width, cam.mode.height) == (64, 48)
        cam.start()
        got = _read_all(cam)
    assert len(got) == 6
    assert [round(float(f.image.mean()) / 40) for f in got] == [0, 1, 2, 3, 4, 5]  # MJPEG is lossy
    assert got[3].device_timestamp_s == pytest.approx(3 / 30.0)


def test_bad_sources(tmp_path):
    with pytest.raises(InvalidInputError, match="does not exist"):
        ReplayCamera(tmp_path / "missing.h5").open()
    with pytest.raises(InvalidInputError, match="rate_hz"):
        ReplayCamera(tmp_path, rate_hz=-1.0)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all")
    with pytest.raises(SessionFileError):
        ReplayCamera(tmp_path / "junk.h5").open()
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(InvalidInputError, match="no recorded frame rate"):
        ReplayCamera(tmp_path).open()
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(FrameFileError, match="no images found"):
        ReplayCamera(empty, rate_hz=10.0).open()
    with ReplayCamera(tmp_path, rate_hz=10.0) as cam:
        with pytest.raises(InvalidInputError, match="is 4x4"):
            cam.set_mode(STRIP)
