"""The session file: round trips, crash safety (SIGKILL), and clear errors on bad files."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import SessionTruth, SessionWriter, open_session, write_session
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import SessionFileError
from skinstretch.processing.errors import InvalidInputError

MODE = CAMERA_MODES["strip"]
CAL = Calibration(px_per_mm=62.0)


def _frames(n):
    return np.stack([np.full((MODE.height, MODE.width), i % 256, np.uint8) for i in range(n)])


def _truth(n, f=3):
    gx, gy = np.arange(0, 16, 8.0), np.arange(0, 24, 8.0)
    return SessionTruth(
        feature_id=np.arange(f),
        feature_kind=np.array([0, 1, 2][:f], np.int8),
        feature_x=np.zeros((n, f)),
        feature_y=np.ones((n, f)),
        feature_visible=np.ones((n, f), bool),
        grid_x=gx,
        grid_y=gy,
        displacement=np.zeros((n, gy.size, gx.size, 2), np.float32),
        displacement_valid=np.ones((n, gy.size, gx.size), bool),
        rigid=np.zeros((n, 3)),
        rigid_center=np.zeros(2),
        strain=np.zeros((n, gy.size, gx.size, 3), np.float32),
        attrs={"scene": "unit", "seed": 3},
    )


def test_write_session_round_trip(tmp_path):
    path = write_session(
        tmp_path / "s.h5",
        _frames(5),
        timestamps=np.arange(5) / MODE.fps,
        camera_mode=MODE,
        calibration=CAL,
        metadata={"subject": "S1", "surface": "flat"},
        truth=_truth(5),
    )
    with open_session(path) as s:
        assert s.complete and s.status == "complete"
        assert s.shape == (5, MODE.height, MODE.width)
        assert s.camera_mode == MODE
        assert s.calibration.px_per_mm == 62.0
        assert s.metadata == {"subject": "S1", "surface": "flat"}
        np.testing.assert_array_equal(s.read_frames(), _frames(5))
        np.testing.assert_array_equal(s.frame_ids, np.arange(5))
        truth = s.truth
        assert truth.attrs["seed"] == 3
        np.testing.assert_array_equal(truth.feature_kind, [0, 1, 2])


def test_write_session_refuses_bad_truth_shape(tmp_path):
    bad = _truth(4)
    with pytest.raises(InvalidInputError, match="feature_x"):
        write_session(tmp_path / "s.h5", _frames(5), timestamps=np.zeros(5), camera_mode=MODE, calibration=CAL, truth=bad)


def test_session_without_truth_says_so(tmp_path):
    path = write_session(tmp_path / "s.h5", _frames(2), timestamps=np.zeros(2), camera_mode=MODE, calibration=CAL)
    with open_session(path) as s:
        assert not s.has_truth
        with pytest.raises(SessionFileError, match="no ground truth"):
            s.truth


def test_writer_streams_and_failure_reason(tmp_path):
    path = tmp_path / "rec.h5"
    w = SessionWriter(path, camera_mode=MODE, calibration=CAL, streams={"force": ((6,), "f8")})
    for i in range(3):
        w.append_frame(_frames(1)[0], timestamp=i * 0.01, frame_id=i)
    w.append_samples("force", [0.0, 0.001], np.ones((2, 6)))
    with pytest.raises(InvalidInputError, match="not declared"):
        w.append_samples("torque", [0.0], np.ones((1, 6)))
    w.fail("camera stopped delivering")
    with open_session(path) as s:
        assert s.status == "failed" and not s.complete
        assert s.status_reason == "camera stopped delivering"
        assert s.n_frames == 3
        t, data = s.read_stream("force")
        assert t.shape == (2,) and data.shape == (2, 6)


def test_writer_never_overwrites(tmp_path):
    path = tmp_path / "rec.h5"
    path.write_bytes(b"precious")
    with pytest.raises(InvalidInputError, match="never overwritten"):
        SessionWriter(path, camera_mode=MODE, calibration=CAL)
    assert path.read_bytes() == b"precious"


@pytest.mark.parametrize(
    "content, message",
    [
        (b"just some text", "not an HDF5 file"),
        (b"", "not an HDF5 file"),
    ],
)
def test_foreign_files_give_clear_errors(tmp_path, content, message):
    path = tmp_path / "x.h5"
    path.write_bytes(content)
    with pytest.raises(SessionFileError, match=message):
        open_session(path)


def test_foreign_hdf5_and_missing_file(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["data"] = np.zeros(3)
    with pytest.raises(SessionFileError, match="not a skinstretch session"):
        open_session(path)
    with pytest.raises(SessionFileError, match="no such session file"):
        open_session(tmp_path / "missing.h5")


def test_truncated_file_gives_clear_error(tmp_path):
    path = write_session(tmp_path / "s.h5", _frames(20), timestamps=np.zeros(20), camera_mode=MODE, calibration=CAL)
    data = path.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(SessionFileError, match="truncated or corrupt"):
        with open_session(cut) as s:
            s.read_frames()


def test_unsupported_version(tmp_path):
    path = write_session(tmp_path / "s.h5", _frames(1), timestamps=np.zeros(1), camera_mode=MODE, calibration=CAL)
    with h5py.File(path, "r+") as f:
        f.attrs["format_version"] = 99
    with pytest.raises(SessionFileError, match="version 99"):
        open_session(path)


def test_sigkill_while_recording_loses_at_most_last_flush(tmp_path):
    """FACTS: SWMR with datasets created up front survives SIGKILL; the file opens and reads as incomplete."""
    path = tmp_path / "killed.h5"
    progress = tmp_path / "progress.txt"
    script = textwrap.dedent(
        f"""
        import numpy as np, time
        from skinstretch.drivers.camera_modes import CAMERA_MODES
        from skinstretch.drivers.session_file import SessionWriter
        from skinstretch.processing.pixel_scale import Calibration
        mode = CAMERA_MODES["strip"]
        w = SessionWriter({str(path)!r}, camera_mode=mode, calibration=Calibration(62.0), flush_interval_s=0.02)
        frame = np.zeros((mode.height, mode.width), np.uint8)
        i = 0
        while True:
            frame[:] = i % 256
            w.append_frame(frame, timestamp=time.monotonic(), frame_id=i)
            i += 1
            if i % 10 == 0:
                open({str(progress)!r}, "w").write(str(i))
            time.sleep(0.002)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            if progress.exists() and progress.read_text().strip() and int(progress.read_text()) >= 60:
                break
            time.sleep(0.05)
        else:
            pytest.fail("recorder subprocess made no progress")
        written = int(progress.read_text())
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    with open_session(path) as s:
        assert not s.complete and s.status == "recording"
        n = s.n_frames
        # The writer had appended at least `written` frames when the progress file was written; a 0.02 s flush
        # interval at ~2 ms per frame loses at most ~10-20 frames of those.
        assert n >= written - 20
        frames = s.read_frames()
        np.testing.assert_array_equal(frames[:, 0, 0], np.arange(n) % 256)
        np.testing.assert_array_equal(s.frame_ids, np.arange(n))


def test_a_session_opened_twice_in_one_process_reads_the_right_frames(tmp_path):
    """Once one of two handles of a dataset in a process was refreshed, HDF5 read zeros through both (a second
    open_session of a file read black frames), and it refused a plain and a SWMR open of one file at once: every
    Session of a file in the process now reads through one shared handle, closed with the last Session."""
    path = write_session(tmp_path / "s.h5", _frames(12), timestamps=np.arange(12) / MODE.fps, camera_mode=MODE,
                         calibration=CAL)
    link = tmp_path / "link.h5"
    link.symlink_to(path)
    sessions = [open_session(path), open_session(link)]
    for s in sessions * 2:  # n_frames refreshes the frame datasets
        assert s.n_frames == 12
        np.testing.assert_array_equal(s.read_frames(), _frames(12))
    sessions.append(open_session(path, swmr=True))
    np.testing.assert_array_equal(sessions[2].read_frames(), _frames(12))
    sessions[0].close()
    sessions[0].close()  # closing twice releases once
    np.testing.assert_array_equal(sessions[1].frame(11), _frames(12)[11])
    for s in sessions[1:]:
        s.close()
    with h5py.File(path, "r+"):  # no handle of it is left open in this process (HDF5 would refuse write access)
        pass


def test_two_sessions_follow_a_growing_file_and_see_it_close(tmp_path):
    """Two SWMR readers in one process (the viewer's, a live analysis') follow a file another process writes."""
    path = tmp_path / "growing.h5"
    script = textwrap.dedent(
        f"""
        import sys
        import numpy as np
        from skinstretch.drivers.camera_modes import CAMERA_MODES
        from skinstretch.drivers.session_file import SessionWriter
        from skinstretch.processing.pixel_scale import Calibration
        mode = CAMERA_MODES["strip"]
        w = SessionWriter({str(path)!r}, camera_mode=mode, calibration=Calibration(62.0), flush_interval_s=0.0)
        for i in range(40):
            w.append_frame(np.full((mode.height, mode.width), i, np.uint8), timestamp=i / 220, frame_id=i)
            if i in (9, 29):
                w.flush()
                print(i + 1, flush=True)
                sys.stdin.readline()
        w.close()
        print("closed", flush=True)
        """
    )
    writer = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert writer.stdout.readline().strip() == "10"
        a = open_session(path, swmr=True)
        b = open_session(path, swmr=True)
        assert a.n_frames == b.n_frames == 10 and a.refresh_status() == "recording"
        writer.stdin.write("go\n")
        writer.stdin.flush()
        assert writer.stdout.readline().strip() == "30"
        for s in (a, b):
            assert s.n_frames >= 30
            np.testing.assert_array_equal(s.read_frames(0, 30)[:, 0, 0], np.arange(30))
            assert s.timestamp(29) == pytest.approx(29 / 220)
        writer.stdin.write("go\n")
        writer.stdin.flush()
        assert writer.stdout.readline().strip() == "closed"
        assert b.refresh_status() == "complete" and a.n_frames == 40
        np.testing.assert_array_equal(a.read_frames()[:, 0, 0], np.arange(40))
        a.close()
        b.close()
    finally:
        writer.stdin.close()
        writer.wait(timeout=30)
        writer.stdout.close()
