"""Readers never make a writer fail; ``view`` refuses what ``analyze`` refuses; one analysis per OUTDIR (issue 41,
items 1-4). Fast: small files, the command line in process where it refuses before serving."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from skinstretch.cli import main
from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.errors import SessionFileError
from skinstretch.drivers.session_file import (SessionTruth, SessionWriter, attach_truth, held_for_writing,
                                              open_session, write_calibration, write_session)
from skinstretch.experiments.output_paths import LOCK_FILE, OutputDirBusyError, hold_output_dir
from skinstretch.experiments.viewer.session_data import SessionSource
from skinstretch.processing.pixel_scale import Calibration

MODE = CAMERA_MODES["full"]
CAL = Calibration(px_per_mm=62.0)
READER = """
import sys, time
from skinstretch.experiments.viewer.session_data import SessionSource
source = SessionSource(sys.argv[1])  # what the live viewer holds while a recording ends
print(source.n_frames(), flush=True)
sys.stdin.readline()
"""


def _session(path, n=6, seed=0):
    frames = np.random.default_rng(seed).integers(0, 256, (n, MODE.height, MODE.width), dtype=np.uint8)
    return write_session(path, frames, timestamps=np.arange(n) / 60.0, camera_mode=MODE, calibration=CAL)


def _truth(n):
    k = 3
    rng = np.random.default_rng(1)
    return SessionTruth(
        feature_id=np.arange(k), feature_kind=np.zeros(k, np.int8), feature_x=rng.uniform(0, 600, (n, k)),
        feature_y=rng.uniform(0, 400, (n, k)), feature_visible=np.ones((n, k), bool), grid_x=np.arange(4.0),
        grid_y=np.arange(3.0), displacement=np.zeros((n, 3, 4, 2)), displacement_valid=np.ones((n, 3, 4), bool),
        rigid=np.zeros((n, 3)), rigid_center=np.zeros(2), strain=np.zeros((n, 3, 4, 3)), attrs={"scene": "test"})


@pytest.fixture
def reader_process(tmp_path):
    procs = []

    def start(path):
        proc = subprocess.Popen([sys.executable, "-c", READER, str(path)], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip().isdigit()
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        proc.communicate("\n", timeout=30)


def test_a_viewer_holding_the_session_never_makes_the_writes_after_a_trial_fail(tmp_path, reader_process):
    # Item 1: "recorded without its simulated ground truth: [Errno 11] ... unable to lock file" with --live.
    path = _session(tmp_path / "session.h5")
    reader_process(path)
    attach_truth(path, _truth(6))
    write_calibration(path, Calibration(px_per_mm=70.0))
    with open_session(path) as s:
        assert s.has_truth and s.calibration.px_per_mm == 70.0 and s.status == "complete"


RECORDER = """
import sys
import numpy as np
from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import SessionWriter, attach_truth
from skinstretch.processing.pixel_scale import Calibration
from tests.test_reliability_readers import _truth
mode = CAMERA_MODES["full"]
writer = SessionWriter(sys.argv[1], camera_mode=mode, calibration=Calibration(px_per_mm=62.0))
for k in range(4):
    writer.append_frame(np.full((mode.height, mode.width), k, np.uint8), timestamp=k / 60, frame_id=k)
writer.flush()
print("recording", flush=True)
sys.stdin.readline()
writer.close()
print("closed", flush=True)
sys.stdin.readline()
attach_truth(sys.argv[1], _truth(4))
print("truth", flush=True)
"""


def test_the_viewer_sees_the_truth_attached_after_the_recording_closed(tmp_path):
    path = tmp_path / "session.h5"
    recorder = subprocess.Popen([sys.executable, "-c", RECORDER, str(path)], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True, cwd=os.path.dirname(os.path.dirname(__file__)))

    def step() -> str:
        recorder.stdin.write("\n")
        recorder.stdin.flush()
        return recorder.stdout.readline().strip()

    assert recorder.stdout.readline().strip() == "recording" and held_for_writing(path)
    source = SessionSource(path)
    try:
        assert source.status() == "recording" and source.n_frames() == 4
        assert not source.reopen_if_changed()  # still held by its recorder: not reopened
        assert step() == "closed" and not held_for_writing(path)
        assert source.reopen_if_changed() and source.status() == "complete" and source.truth() is None
        assert step() == "truth"  # written while the viewer holds the file (item 1)
        assert source.reopen_if_changed() and source.truth() is not None
        assert not source.reopen_if_changed()  # nothing changed since
    finally:
        source.close()
        recorder.communicate(timeout=30)
    assert recorder.returncode == 0


def _garble(path):
    with open(path, "r+b") as fh:
        fh.seek(8)
        fh.write(np.random.default_rng(0).integers(0, 256, 4088, dtype=np.uint8).tobytes())


@pytest.mark.parametrize("damage", ["corrupt", "truncated"])
def test_view_refuses_a_damaged_session_in_one_line_as_analyze_does(tmp_path, capsys, damage):
    # Items 2-3: a 26-line traceback (corrupt), a hang of minutes with no port (truncated: SWMR retries).
    path = _session(tmp_path / f"{damage}.h5", n=30)
    if damage == "corrupt":
        _garble(path)
    else:
        os.truncate(path, int(path.stat().st_size * 0.6))
    t0 = time.monotonic()
    rc = main(["view", str(path), "--no-browser", "--port", "0"])
    err = capsys.readouterr().err
    assert rc == 2 and time.monotonic() - t0 < 5
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"skinstretch view: error: {path}: HDF5 file cannot be opened, truncated or corrupt")
    assert main(["analyze", str(path), "-o", str(tmp_path / "out")]) == 2
    assert "truncated or corrupt" in capsys.readouterr().err


def test_a_truncated_copy_of_a_recording_in_progress_is_refused_at_once(tmp_path):
    # The file a killed recorder leaves is marked open for writing and read in SWMR mode, which does not check
    # the file's end: the superblock's end-of-file address does.
    path = tmp_path / "live.h5"
    writer = SessionWriter(path, camera_mode=MODE, calibration=CAL)
    for k in range(20):
        writer.append_frame(np.full((MODE.height, MODE.width), k, np.uint8), timestamp=k / 60, frame_id=k)
    writer.flush()
    copy = tmp_path / "copy.h5"
    shutil.copy(path, copy)
    writer.close()
    os.truncate(copy, int(copy.stat().st_size * 0.6))
    assert held_for_writing(copy)
    t0 = time.monotonic()
    for swmr in (False, True):
        with pytest.raises(SessionFileError, match="truncated or corrupt"):
            open_session(copy, swmr=swmr)
    assert time.monotonic() - t0 < 2


def test_a_second_writer_of_an_output_directory_is_refused_naming_the_first(tmp_path):
    out = tmp_path / "out"
    with hold_output_dir(out, holder="an analysis of a.h5"):
        with pytest.raises(OutputDirBusyError) as info:
            with hold_output_dir(out, holder="an analysis of b.h5"):
                pass  # pragma: no cover - refused
        message = str(info.value)
        assert message.startswith(f"{out}: in use by an analysis of a.h5 (pid {os.getpid()} on ")
        assert "\n" not in message
    assert not (out / LOCK_FILE).exists() and not out.exists()  # created for the run, empty: removed
    # a lock file its holder left behind when it was killed is stale (the kernel let go of its lock)
    out.mkdir()
    (out / LOCK_FILE).write_text("an analysis of c.h5 (pid 999999 on elsewhere, since then)\n")
    with hold_output_dir(out, holder="an analysis of d.h5"):
        assert "d.h5" in (out / LOCK_FILE).read_text()
    assert out.is_dir() and not any(out.iterdir())


def test_two_analyses_into_one_directory_one_refused_at_once_the_other_finishes(tmp_path):
    # Item 4: both failed, the later one deleting the first one's results.h5.partial.
    session = _session(tmp_path / "s.h5", n=12)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "skinstretch.cli", "analyze", str(session), "-o", str(out), "-q",
           "--parallel", "serial"]
    first = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (out / LOCK_FILE).exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    second = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    _, first_err = first.communicate(timeout=300)
    assert first.returncode == 0, first_err
    assert second.returncode == 2
    lines = [l for l in second.stderr.splitlines() if "error" in l]
    assert len(lines) == 1 and (f"{out}: in use by an analysis of s.h5" in lines[0]
                                or "holds the results of an analysis already" in lines[0])
    assert (out / "results.h5").exists() and (out / "summary.json").exists() and not (out / LOCK_FILE).exists()
