"""The threaded recorder: everything queued is written; disk full fails the session cleanly with data kept."""

import errno

import numpy as np
import pytest

from skinstretch.drivers.camera_modes import CAMERA_MODES, CameraMode
from skinstretch.drivers.session_file import SessionWriter, open_session
from skinstretch.experiments.recorder import Recorder
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InvalidInputError

MODE = CameraMode("tiny", 32, 24, 100.0)
CAL = Calibration(px_per_mm=62.0)


class DiskFullWriter(SessionWriter):
    """Fault injection: the disk fills up after ``limit`` frames (OSError ENOSPC, as the kernel reports it)."""

    limit = 7

    def append_frame(self, frame, **kw):
        if self.n_frames >= self.limit:
            raise OSError(errno.ENOSPC, "No space left on device")
        super().append_frame(frame, **kw)

    def append_frames(self, frames, *, timestamps, frame_ids, device_timestamps):
        for f, t, i, d in zip(frames, timestamps, frame_ids, device_timestamps):  # the same fault, frame by frame
            self.append_frame(f, timestamp=t, frame_id=i, device_timestamp=d)


def _frame(k):
    return np.full((MODE.height, MODE.width), k % 256, np.uint8)


def test_everything_queued_is_written(tmp_path):
    rec = Recorder(tmp_path / "s.h5", camera_mode=MODE, calibration=CAL, metadata={"trial": "a"},
                   streams={"force": ((6,), "f8")}, queue_size=4).start()
    for k in range(40):
        assert rec.put_frame(_frame(k), timestamp=k / 100, frame_id=k)
        assert rec.put_samples("force", [k / 100, k / 100 + 0.005], np.full((2, 6), k, float))
    stats = rec.finish()
    assert stats.status == "complete" and stats.frames_written == 40 and stats.frames_dropped == 0
    assert stats.samples_written == {"force": 80} and stats.bytes_written > 40 * 32 * 24
    with open_session(tmp_path / "s.h5") as s:
        assert s.complete and s.n_frames == 40 and s.metadata["trial"] == "a"
        np.testing.assert_array_equal(s.frame_ids, np.arange(40))
        assert s.frame(39)[0, 0] == 39
        t, f = s.read_stream("force")
        assert t.shape == (80,) and f[-1, 0] == 39
    assert rec.finish() is stats  # idempotent


def test_disk_full_marks_session_failed_and_keeps_data(tmp_path):
    rec = Recorder(tmp_path / "s.h5", camera_mode=MODE, calibration=CAL, writer_factory=DiskFullWriter).start()
    accepted = 0
    for k in range(30):
        if rec.failed.is_set():
            break
        accepted += rec.put_frame(_frame(k), timestamp=k / 100, frame_id=k)
        rec.failed.wait(0.01)  # bounded wait on the real writer thread
    assert rec.failed.wait(5.0)
    assert "disk full" in rec.failure and "ENOSPC" in rec.failure
    assert not rec.put_frame(_frame(99), timestamp=1.0, frame_id=99)  # producers are told to stop
    stats = rec.finish()
    assert stats.status == "failed" and "disk full" in stats.reason
    with open_session(tmp_path / "s.h5") as s:
        assert s.status == "failed" and "ENOSPC" in s.status_reason
        assert s.n_frames == DiskFullWriter.limit
        np.testing.assert_array_equal(s.frame_ids, np.arange(DiskFullWriter.limit))


def test_finish_with_reason_marks_failed(tmp_path):
    rec = Recorder(tmp_path / "s.h5", camera_mode=MODE, calibration=CAL).start()
    rec.put_frame(_frame(0), timestamp=0.0, frame_id=0)
    stats = rec.finish(failed_reason="device fault: camera link lost")
    assert stats.status == "failed"
    with open_session(tmp_path / "s.h5") as s:
        assert s.status == "failed" and s.status_reason == "device fault: camera link lost" and s.n_frames == 1


def test_invalid_arguments_name_the_parameter(tmp_path):
    with pytest.raises(InvalidInputError, match="queue_size"):
        Recorder(tmp_path / "a.h5", camera_mode=CAMERA_MODES["full"], calibration=CAL, queue_size=0)
    rec = Recorder(tmp_path / "b.h5", camera_mode=MODE, calibration=CAL)
    with pytest.raises(InvalidInputError, match="start"):
        rec.put_frame(_frame(0), timestamp=0.0, frame_id=0)
    with pytest.raises(InvalidInputError, match="stream 'force'"):
        rec.put_samples("force", 0.0, np.zeros(6))
    assert rec.finish().status == "complete"


def test_queued_sample_blocks_are_coalesced_in_order(tmp_path):
    rec = Recorder(tmp_path / "s.h5", camera_mode=MODE, calibration=CAL, streams={"force": ((6,), "f8")})
    # queue everything before the writer starts, so the writer finds runs of sample blocks to join
    rec._started = True
    for k in range(10):
        rec.put_samples("force", [2 * k, 2 * k + 1], np.full((2, 6), k, float))
        rec.put_samples("force", 2 * k + 1.5, np.full(6, k, float))  # a single sample
        if k % 3 == 0:
            rec.put_frame(_frame(k), timestamp=k, frame_id=k)
    rec._started = False
    rec.start()
    stats = rec.finish()
    assert stats.samples_written == {"force": 30} and stats.frames_written == 4
    with open_session(tmp_path / "s.h5") as s:
        t, f = s.read_stream("force")
        assert np.all(np.diff(t) > 0) and t.shape == (30,)
        np.testing.assert_array_equal(f[:, 0], np.repeat(np.arange(10), 3))
        np.testing.assert_array_equal(s.frame_ids, [0, 3, 6, 9])


def test_frames_queued_behind_each_other_are_written_in_one_append(tmp_path):
    rec = Recorder(tmp_path / "s.h5", camera_mode=MODE, calibration=CAL, queue_size=64)
    rec._started = True  # queue a backlog before the writer runs, as on a host that starved the writer
    for k in range(40):
        rec.put_frame(_frame(k), timestamp=k / 100, frame_id=k, device_timestamp=k / 100 + 1)
    rec._started = False
    stats = rec.start().finish()
    assert stats.frames_written == 40 and stats.frames_dropped == 0
    with open_session(tmp_path / "s.h5") as s:
        np.testing.assert_array_equal(s.frame_ids, np.arange(40))
        np.testing.assert_allclose(s.device_timestamps, np.arange(40) / 100 + 1)
        assert [int(s.frame(k)[0, 0]) for k in (0, 31, 32, 39)] == [0, 31, 32, 39]
