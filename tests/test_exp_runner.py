"""The protocol runner: data layout, document log, failures (disk full, device fault), SIGKILL and --resume.

The fake devices below stand in for the rig so the runner's own logic is tested alone (the real simulated rig
is exercised by the demo test). The subprocess in the SIGKILL test imports them from this module.
"""

import errno
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from skinstretch.drivers.session_file import SessionWriter, open_session
from skinstretch.experiments.protocol import parse_protocol
from skinstretch.experiments.runner import finished_trials, read_events, run_protocol, session_dir
from skinstretch.experiments.protocol import Rig
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]

PROTOCOL = """\
name: unit
subject: {id: s01}
camera_mode: strip
trials:
  - {name: flat, duration_s: %(d)s}
  - {name: ridge, duration_s: %(d)s, surface: {kind: ridge}}
  - {name: valley, duration_s: %(d)s, surface: {kind: valley}}
analysis: {enabled: false}
"""


@dataclass
class FakeFrame:
    image: np.ndarray
    frame_id: int
    device_timestamp_s: float
    host_timestamp_s: float


class FakeCamera:
    def __init__(self, mode, *, fail_at=None, paced=False, report=False, tag=""):
        self.mode, self.fail_at, self.paced, self.report, self.tag = mode, fail_at, paced, report, tag
        self.k = 0
        self.running = False

    def start(self):
        self.running = True
        self.t0 = time.monotonic()

    def stop(self):
        self.running = False

    def read(self, timeout_s):
        if self.fail_at is not None and self.k >= self.fail_at:
            raise DeviceError("camera link lost (fake)")
        if self.paced:  # a real-time camera (only in the subprocess of the SIGKILL test)
            delay = self.t0 + self.k * self.mode.period_s - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        t = self.t0 + self.k * self.mode.period_s if not self.paced else time.monotonic()
        img = np.full((self.mode.height, self.mode.width), self.k % 256, np.uint8)
        frame = FakeFrame(img, self.k, self.k * self.mode.period_s, t)
        if self.report:
            print(f"acq {self.tag} {self.k} {t!r}", flush=True)
        self.k += 1
        return frame


class FakeForce:
    def __init__(self):
        self.t = 0.0

    def begin(self):
        pass

    def end(self):
        pass

    def read_block(self, timeout_s):
        time.sleep(0.01)  # bounded wait standing for the sensor's blocking read on its socket (500 Hz, blocks)
        t = self.t + 0.002 * np.arange(1, 6)
        self.t = t[-1]
        return t, np.tile([0.0, 0.0, 1.5, 0.0, 0.0, 0.0], (5, 1))


class FakeDisplay:
    def __init__(self):
        self.rest_calls = 0
        self.positions = np.zeros((10, 10))

    def rest(self):
        self.rest_calls += 1
        self.positions[:] = 0

    def measured_positions_um(self):
        return self.positions.copy()

    @property
    def at_rest(self):
        return not np.any(self.positions)


class FakeDevices:
    def __init__(self, *, fail_trial=None, fail_at=None, paced=False, report=False):
        self.force = FakeForce()
        self.display = FakeDisplay()
        self.fail_trial, self.fail_at, self.paced, self.report = fail_trial, fail_at, paced, report

    def describe(self):
        return {"camera": "fake", "force": "fake", "display": "fake"}

    def camera_for(self, *, trial, protocol, n_frames):
        from skinstretch.drivers.camera_modes import CAMERA_MODES

        fail = self.fail_at if trial.index == self.fail_trial else None
        return FakeCamera(CAMERA_MODES[protocol.camera_mode], fail_at=fail, paced=self.paced, report=self.report,
                          tag=str(trial.index))

    def close(self):
        pass


def _run(tmp_path, *, d=0.1, **kw):
    protocol = parse_protocol(PROTOCOL % {"d": d})
    devices = kw.pop("devices", None) or FakeDevices()
    msgs = []
    result = run_protocol(protocol, Rig(), tmp_path, devices=devices, progress=msgs.append, **kw)
    return protocol, devices, result, msgs


def test_layout_log_and_summaries(tmp_path):
    protocol, devices, result, msgs = _run(tmp_path)
    sdir = session_dir(protocol, tmp_path)
    assert sdir == tmp_path / "s01" / "unit" and result.ok
    assert [t.status for t in result.trials] == ["complete"] * 3
    for t in result.trials:
        with open_session(t.path) as s:
            assert s.complete and s.n_frames == 22  # 0.1 s at 220 Hz
            assert s.metadata["subject"]["id"] == "s01" and "force" in s.stream_names()
        assert t.summary["frames"] == 22 and t.summary["dropped_frames"] == 0
        assert t.summary["normal_force_mean_n"] == pytest.approx(1.5)
    assert result.trials[1].path == sdir / "001-ridge-r1" / "session.h5"
    events = read_events(sdir / "events.jsonl")
    names = [n for n, _ in events]
    assert names.count("start") == names.count("stop") == names.count("descriptor") == 3
    assert all(d["exit_status"] == "success" for n, d in events if n == "stop")
    assert set(finished_trials(events)) == {"000-flat-r1", "001-ridge-r1", "002-valley-r1"}
    assert any("22/22 frames" in m for m in msgs)
    assert devices.display.at_rest and devices.display.rest_calls >= 6


def test_disk_full_fails_that_trial_keeps_its_data_and_ends_the_run(tmp_path):
    class FullAfterFive(SessionWriter):  # an injected ENOSPC: the real disk is in test_reliability_disk_full
        def append_frame(self, frame, **kw):
            if "001-ridge" in str(self.path) and self.n_frames >= 5:
                raise OSError(errno.ENOSPC, "No space left on device")
            super().append_frame(frame, **kw)

        def append_frames(self, frames, *, timestamps, frame_ids, device_timestamps):
            for f, t, i, d in zip(frames, timestamps, frame_ids, device_timestamps):  # the same fault, frame by frame
                self.append_frame(f, timestamp=t, frame_id=i, device_timestamp=d)

    protocol, devices, result, msgs = _run(tmp_path, writer_factory=FullAfterFive)
    flat, ridge, valley = result.trials
    assert flat.status == "complete" and valley.status == "not run"
    assert ridge.status == "failed" and "disk full" in ridge.reason and ridge.disk_full
    with open_session(ridge.path) as s:
        assert s.status == "failed" and "ENOSPC" in s.status_reason and s.n_frames == 5
    events = read_events(session_dir(protocol, tmp_path) / "events.jsonl")
    stops = [d for n, d in events if n == "stop"]
    assert [d["exit_status"] for d in stops] == ["success", "fail"] and "disk full" in stops[1]["reason"]
    assert any(d.get("name") == "run_stopped" for n, d in events if n == "event")
    assert devices.display.at_rest
    assert not result.ok and "disk full" in result.stopped
    assert result.summary_line().startswith("1 of 3 trials failed, 1 not run, 0 of 0 analyses failed; run stopped")
    assert not (tmp_path / "s01" / "unit" / "002-valley-r1").exists()


def test_device_fault_fails_trial_with_reason_and_keeps_data(tmp_path):
    devices = FakeDevices(fail_trial=0, fail_at=9)
    _, devices, result, _ = _run(tmp_path, devices=devices)
    assert result.trials[0].status == "failed"
    assert "device fault" in result.trials[0].reason and "camera link lost" in result.trials[0].reason
    with open_session(result.trials[0].path) as s:
        assert s.status == "failed" and s.n_frames == 9
    assert result.trials[1].status == "complete"
    assert devices.display.at_rest


def test_existing_session_needs_resume(tmp_path):
    _run(tmp_path)
    with pytest.raises(ConfigError, match="is not empty; pass resume=True to carry on"):
        _run(tmp_path)
    _, _, again, _ = _run(tmp_path, resume=True)
    assert [t.status for t in again.trials] == ["skipped"] * 3


_CHILD = """
import sys
sys.path.insert(0, {root!r})
from tests.test_exp_runner import FakeDevices, PROTOCOL
from skinstretch.experiments.protocol import parse_protocol, Rig
from skinstretch.experiments.runner import run_protocol
p = parse_protocol(PROTOCOL % {{"d": 2.0}})
run_protocol(p, Rig(), {out!r}, devices=FakeDevices(paced=True, report=True), progress=lambda m: None)
"""


def test_sigkill_loses_at_most_a_tenth_of_a_second_and_resume_carries_on(tmp_path):
    code = _CHILD.format(root=str(ROOT), out=str(tmp_path))
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    line = ""
    try:
        for line in child.stdout:  # bounded by pytest-timeout; the child is a real-time camera
            parts = line.split()
            if parts[:2] == ["acq", "1"] and int(parts[2]) >= 120:  # well inside the second trial
                break
        os.kill(child.pid, signal.SIGKILL)
        rest = child.stdout.read()
    finally:
        child.wait(10)
        child.stdout.close()
    acquired = [ln.split() for ln in (line + rest).splitlines() if ln.startswith("acq 1 ")]
    t_last_acquired = float(acquired[-1][3])
    sdir = tmp_path / "s01" / "unit"
    killed = sdir / "001-ridge-r1" / "session.h5"
    with open_session(killed) as s:
        assert not s.complete and s.status == "recording"  # opens, says it is incomplete
        assert s.n_frames >= 60
        lost_s = t_last_acquired - s.timestamps[-1]
    assert lost_s <= 0.1, f"lost {lost_s:.3f} s of data"
    with open_session(sdir / "000-flat-r1" / "session.h5") as s:
        assert s.complete
    assert not (sdir / "002-valley-r1").exists()

    protocol = parse_protocol(PROTOCOL % {"d": 0.1})
    result = run_protocol(protocol, Rig(), tmp_path, devices=FakeDevices(), resume=True, progress=lambda m: None)
    assert [t.status for t in result.trials] == ["skipped", "skipped", "complete"]
    assert "aborted" in result.trials[1].reason
    events = read_events(sdir / "events.jsonl")
    done = finished_trials(events)
    assert done["001-ridge-r1"]["exit_status"] == "abort"
    assert done["002-valley-r1"]["exit_status"] == "success"
    with open_session(sdir / "002-valley-r1" / "session.h5") as s:
        assert s.complete and s.n_frames == 22
