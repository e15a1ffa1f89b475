"""The simulated camera: pacing on a manual clock, injected drops, stalls and device errors, queue overflow."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from skinstretch.drivers.camera.base import EndOfStreamError, FrameIdUnwrapper, ManualClock
from skinstretch.drivers.camera_modes import CAMERA_MODES, CameraMode
from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.simulated_camera import CameraFaults, SimulatedCamera
from tests.helpers import wait_until

MODE = CameraMode("tiny", 32, 24, 100.0)


def _source(k: int) -> np.ndarray:
    return np.full((24, 32), k % 256, np.uint8)


def _drain(cam, timeout_s: float = 0.2) -> list[int]:
    ids = []
    while True:
        try:
            ids.append(cam.read(timeout_s).frame_id)
        except DeviceTimeoutError:
            return ids


def test_frames_come_only_when_the_clock_says_so():
    clock = ManualClock()
    with SimulatedCamera(_source, MODE, clock=clock) as cam:
        cam.start()
        first = cam.read(2.0)  # frame 0 is due at t = 0
        assert first.frame_id == 0 and first.device_timestamp_s == 0.0
        with pytest.raises(DeviceTimeoutError):
            cam.read(0.05)
        clock.advance(2.5 * MODE.period_s)
        frames = cam.frames(2, timeout_s=2.0)
        assert [f.frame_id for f in frames] == [1, 2]
        assert [int(f.image[0, 0]) for f in frames] == [1, 2]
        assert frames[1].device_timestamp_s == pytest.approx(2 * MODE.period_s)
        assert frames[1].host_timestamp_s - first.host_timestamp_s == pytest.approx(2.5 * MODE.period_s, abs=1e-5)


def test_injected_drops_and_finite_stall_are_counted_as_dropped():
    clock = ManualClock()
    faults = CameraFaults(drop_frames={2, 3}, stall_at_frame=6, stall_s=3 * MODE.period_s)
    with SimulatedCamera(_source, MODE, clock=clock, faults=faults) as cam:
        cam.start()
        clock.advance(12.5 * MODE.period_s)
        wait_until(lambda: cam.stats.completed == 8)
        ids = _drain(cam)
        stats = cam.stats
    # 2 and 3 dropped; the stall at 6 loses frames 6, 7, 8; delivery resumes at 9.
    assert ids == [0, 1, 4, 5, 9, 10, 11, 12]
    assert stats.dropped == 5 and stats.completed == 8 and stats.delivered == 8


def test_random_drops_are_seeded():
    def run(seed):
        clock = ManualClock()
        with SimulatedCamera(_source, MODE, clock=clock, faults=CameraFaults(drop_probability=0.3), seed=seed) as cam:
            cam.start()
            clock.advance(40.5 * MODE.period_s)
            wait_until(lambda: cam.stats.completed + cam.stats.dropped == 41)
            return _drain(cam), cam.stats

    ids_a, stats_a = run(3)
    ids_b, _ = run(3)
    assert ids_a == ids_b
    assert 0 < stats_a.dropped < 41 and stats_a.dropped == 41 - len(ids_a)


def test_dead_camera_times_out_and_keeps_earlier_frames():
    clock = ManualClock()
    faults = CameraFaults(stall_at_frame=3, stall_s=math.inf)
    with SimulatedCamera(_source, MODE, clock=clock, faults=faults) as cam:
        cam.start()
        clock.advance(10 * MODE.period_s)
        wait_until(lambda: cam.stats.completed == 3)
        t = time.monotonic()
        ids = _drain(cam, timeout_s=0.1)
        assert time.monotonic() - t < 5.0  # bounded: no hang
        assert ids == [0, 1, 2]
        with pytest.raises(DeviceTimeoutError, match="no frame within"):
            cam.read(0.05)
    assert not cam.is_open  # closing a stalled camera does not hang either


def test_device_error_is_raised_after_the_frames_before_it():
    clock = ManualClock()
    with SimulatedCamera(_source, MODE, clock=clock, faults=CameraFaults(error_at_frame=2)) as cam:
        cam.start()
        clock.advance(5 * MODE.period_s)
        assert [cam.read(2.0).frame_id for _ in range(2)] == [0, 1]
        with pytest.raises(DeviceTimeoutError, match="simulated device timeout at frame 2"):
            cam.read(2.0)
        with pytest.raises(DeviceTimeoutError):  # the failure is sticky until restart
            cam.read(0.05)
        cam.stop()
        cam.inject(CameraFaults())
        cam.start()
        assert cam.read(2.0).frame_id == 0


def test_full_queue_drops_are_counted_not_silent():
    clock = ManualClock()
    with SimulatedCamera(_source, MODE, clock=clock, queue_size=2) as cam:
        cam.start()
        clock.advance(9.5 * MODE.period_s)
        wait_until(lambda: cam.stats.completed == 10)
        stats = cam.stats
        assert stats.dropped == 8
        assert [f.frame_id for f in cam.frames(2)] == [0, 1]


def test_finite_source_ends_or_loops():
    frames = np.stack([_source(k) for k in range(3)])
    clock = ManualClock()
    with SimulatedCamera.from_frames(frames, 100.0, clock=clock, loop=False) as cam:
        cam.start()
        clock.advance(10 * MODE.period_s)
        assert [cam.read(2.0).frame_id for _ in range(3)] == [0, 1, 2]
        with pytest.raises(EndOfStreamError):
            cam.read(2.0)
    clock = ManualClock()
    with SimulatedCamera.from_frames(frames, 100.0, clock=clock) as cam:
        cam.start()
        clock.advance(10 * MODE.period_s)
        got = cam.frames(7, timeout_s=2.0)
        assert [int(f.image[0, 0]) for f in got] == [0, 1, 2, 0, 1, 2, 0]
        assert [f.frame_id for f in got] == list(range(7))


def test_bad_sources_and_arguments():
    with pytest.raises(InvalidInputError, match="frame_source"):
        SimulatedCamera(42, MODE)
    with pytest.raises(InvalidInputError, match="drop_probability"):
        CameraFaults(drop_probability=1.5)
    with pytest.raises(InvalidInputError, match="stall_at_frame"):
        CameraFaults(stall_at_frame=-1)
    with pytest.raises(DeviceError, match="uint8 or uint16"):
        SimulatedCamera(lambda k: np.zeros((24, 32), np.float32), MODE).open()
    with pytest.raises(DeviceError, match="frame source failed"):
        SimulatedCamera(lambda k: 1 / 0, MODE).open()
    with SimulatedCamera(_source, MODE) as cam:
        with pytest.raises(InvalidInputError, match="frame source renders"):
            cam.set_mode(CAMERA_MODES["full"])
        cam.set_mode(CameraMode("burst", 32, 24, 500.0))  # same size, another rate is fine
        assert cam.mode.fps == 500.0


def test_frame_id_unwrapper_handles_gige_wrap_and_gaps():
    unwrap = FrameIdUnwrapper(modulus=65536, skip_zero=True)
    raw = [65533, 65534, 65535, 1, 2, 5, 6]
    assert [unwrap(r) for r in raw] == [65533, 65534, 65535, 65536, 65537, 65540, 65541]
    assert unwrap.gaps == 2
    plain = FrameIdUnwrapper(modulus=None)
    assert [plain(r) for r in (10, 11, 15)] == [10, 11, 15] and plain.gaps == 3
    with pytest.raises(InvalidInputError):
        FrameIdUnwrapper(modulus=1)


def test_from_scene_streams_the_scene_renderer():
    """The scene renderer's frames, in order, looped (renderer built once: it takes seconds to set up)."""
    scene_module = pytest.importorskip("skinstretch.simulators.scene")
    scene = scene_module.load_scene("flatL").model_copy(update={"n_frames": 3})
    renderer = scene_module.SceneRenderer(scene, seed=0)
    clock = ManualClock()
    with SimulatedCamera.from_scene(renderer, clock=clock, prerender=True) as cam:
        assert cam.mode == renderer.camera_mode
        cam.start()
        clock.advance(3.5 * cam.mode.period_s)
        frames = cam.frames(4, timeout_s=5.0)
    np.testing.assert_array_equal(frames[1].image, renderer.render_frame(1))
    np.testing.assert_array_equal(frames[3].image, frames[0].image)  # looped
