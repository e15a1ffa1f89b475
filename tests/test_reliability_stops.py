"""A silent force sensor, a bad movie, SIGTERM/SIGINT, and --resume's count (issue 41, items 5-8): each stops or
refuses in one line, closes what it opened and says so. On a replay camera (no scene rendering), fast."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import psutil
import pytest

from skinstretch.cli import main
from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError
from skinstretch.drivers.forcesensor.netft import NetFTSensor
from skinstretch.drivers.session_file import open_session, write_session
from skinstretch.experiments.output_paths import OutputPathError
from skinstretch.experiments.playback import play_movie
from skinstretch.experiments.protocol import DeviceSpec, Rig, load_protocol
from skinstretch.experiments.rig import ForceSource
from skinstretch.experiments.runner import SessionRun, TrialResult, read_events, run_protocol
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.simulators.netft_box import NetFTFaults, NetFTSimulator
from tests.test_exp_playback import PlantDisplay

MODE = CAMERA_MODES["full"]
SILENT_HOST = "127.0.0.3"  # a loopback address of its own: nothing else answers there


def _replay_source(tmp_path, n=90):
    frames = np.random.default_rng(0).integers(0, 256, (n, MODE.height, MODE.width), dtype=np.uint8)
    return write_session(tmp_path / "source.h5", frames, timestamps=np.arange(n) / 60.0, camera_mode=MODE,
                         calibration=Calibration(px_per_mm=62.0))


def _protocol(tmp_path, trials=(("a", 1.0),), *, force=True):
    body = "\n".join(f"  - {{name: {n}, duration_s: {d}}}" for n, d in trials)
    path = tmp_path / "p.yaml"
    path.write_text(f"name: p\nsubject: {{id: s01}}\ncamera_mode: full\ntrials:\n{body}\n"
                    f"record: {{force: {str(force).lower()}}}\nanalysis: {{enabled: false}}\n")
    return path


@pytest.fixture
def silent_box():
    with NetFTSimulator(host=SILENT_HOST, faults=NetFTFaults(silent=True)) as box:
        yield box


def test_a_net_ft_that_never_answers_is_a_timeout_not_a_quiet_sensor(silent_box):
    host, port = silent_box.address
    with NetFTSensor(host, port=port, silence_timeout_s=0.3) as sensor:
        sensor.start()
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match=r"no data for 0\.\d s \(0 samples received") as info:
            sensor.read(timeout_s=5.0)
        assert time.monotonic() - t0 < 1.5 and not isinstance(info.value, DeviceTimeoutError)  # not "try again"
        sensor.stop()
    assert silent_box.stats.requests >= 1 and silent_box.stats.sent == 0


def test_a_trial_on_a_silent_force_sensor_fails_in_one_line(tmp_path, silent_box):
    # Item 5: the trial was "complete", the run "all 1 trials recorded", rc 0, with 0 force samples.
    host, port = silent_box.address
    rig = Rig(camera=DeviceSpec(kind="replay", device=str(_replay_source(tmp_path))),
              force=DeviceSpec(kind="netft", address=host, options={"port": port, "silence_timeout_s": 0.3}),
              display=DeviceSpec(kind="none"))
    run = run_protocol(load_protocol(_protocol(tmp_path)), rig, tmp_path / "data", progress=lambda m: None,
                       play_movie=False)
    trial = run.trials[0]
    assert trial.status == "failed" and not run.ok
    assert trial.reason.startswith("force sensor: DeviceError: NetFTSensor(127.0.0.3:")
    assert "\n" not in trial.reason
    with open_session(trial.path) as s:
        assert s.status == "failed" and "no data for" in s.status_reason
    assert run.summary_line().startswith("1 of 1 trials failed")


def test_a_movie_with_a_force_ceiling_never_starts_on_a_silent_sensor(silent_box):
    host, port = silent_box.address
    force = ForceSource(NetFTSensor(host, port=port, silence_timeout_s=0.3), description=f"Net F/T at {host}")
    display = PlantDisplay()
    try:
        with pytest.raises(DeviceTimeoutError, match="the force ceiling cannot be enforced"):
            play_movie(display, np.zeros((50, 10, 10)), force=force, force_ceiling_n=5.0)
    finally:
        force.close()
    assert not display.armed and display.frames == 0


@pytest.mark.parametrize("kind", ["complex", "nan"])
def test_play_refuses_a_complex_or_nan_movie_before_arming(tmp_path, capsys, kind):
    # Item 6: a complex movie played 2100 of 2100 frames with only numpy's ComplexWarning.
    movie = np.zeros((30, 10, 10))
    if kind == "nan":
        movie[5, 2, 7] = np.nan
    else:
        movie = movie + 1j
    np.save(tmp_path / "m.npy", movie)
    assert main(["play", str(tmp_path / "m.npy"), "-o", str(tmp_path / "out.h5")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and not (tmp_path / "out.h5").exists()
    expected = "frame 5, contactor (2, 7) is nan" if kind == "nan" else "m.npy is complex (complex128"
    assert expected in err


def _descendants_left(pid_set):
    alive = []
    for pid in pid_set:
        try:
            proc = psutil.Process(pid)
            if proc.status() != psutil.STATUS_ZOMBIE:
                alive.append(proc)
        except psutil.NoSuchProcess:
            continue
    return alive


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_closes_the_trial_as_aborted_and_record_exits_within_a_second(tmp_path, signum):
    # Item 7: SIGTERM ended record like SIGKILL: the trial stayed "recording" with its .reserve file.
    source = _replay_source(tmp_path, n=600)
    rig = tmp_path / "rig.yaml"
    rig.write_text(f"name: replay\ncamera: {{kind: replay, device: {str(source)!r}}}\nforce: {{kind: sim}}\n"
                   "display: {kind: sim}\n")
    proto = _protocol(tmp_path, (("a", 8.0), ("b", 1.0)))
    child = subprocess.Popen([sys.executable, "-m", "skinstretch.cli", "record", str(proto), "--rig", str(rig),
                              "-o", str(tmp_path / "data"), "--no-movie"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    for line in child.stderr:  # the progress lines
        if "/480 frames" in line:
            break
    family = {p.pid for p in psutil.Process(child.pid).children(recursive=True)}
    t0 = time.monotonic()
    child.send_signal(signum)
    out, err = child.communicate(timeout=30)
    took = time.monotonic() - t0
    assert child.returncode == 128 + signum, err
    assert took < 3.0  # a second on an idle machine; a loaded 2-core one is given some room
    last = err.strip().splitlines()[-1]
    name = signal.Signals(signum).name
    assert last == f"skinstretch record: 1 of 2 trials failed, 1 not run, 0 of 0 analyses failed; run stopped: " \
                   f"{name} received"
    trial = tmp_path / "data" / "s01" / "p" / "000-a-r1"
    with open_session(trial / "session.h5") as s:
        assert s.status == "failed" and s.status_reason == f"aborted: {name} received" and 0 < s.n_frames < 480
    assert not list(trial.glob(".*.reserve"))
    stops = [d for n, d in read_events(trial.parent / "events.jsonl") if n == "stop"]
    assert [d["exit_status"] for d in stops] == ["abort"] and stops[0]["reason"] == f"{name} received"
    deadline = time.monotonic() + 5  # the tree watcher ends whatever is left once record is gone
    while _descendants_left(family) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _descendants_left(family)


def test_resume_counts_a_trial_an_earlier_run_failed(tmp_path):
    # Item 8: "all 3 trials recorded" after --resume when one of them had failed.
    trials = [TrialResult("000-a-r1", tmp_path, "skipped", reason="already complete"),
              TrialResult("001-b-r1", tmp_path, "skipped", reason="already failed"),
              TrialResult("002-c-r1", tmp_path, "complete")]
    run = SessionRun(tmp_path, trials)
    assert not run.ok
    assert run.summary_line() == "1 of 3 trials failed (1 in an earlier run), 0 of 0 analyses failed"
    assert SessionRun(tmp_path, [trials[0], trials[2]]).summary_line() == "all 2 trials recorded"


def test_import_names_an_unwritable_output_before_reading_the_source(tmp_path):
    # Item 8: exit 1 naming the hidden temporary file, after reading the whole source.
    (tmp_path / "file").write_text("")
    with pytest.raises(OutputPathError, match=r"file: is a file, not a directory \(on the way to .*x\.h5\)"):
        from skinstretch.experiments.frame_import import import_frames  # noqa: PLC0415

        import_frames(tmp_path / "no-such-video.avi", tmp_path / "file" / "x.h5", px_per_mm=62.0)


def test_nan_and_decreasing_time_stamps_are_flagged(tmp_path):
    frames = np.zeros((8, MODE.height, MODE.width), np.uint8)
    ts = np.arange(8) / 60.0
    ts[2], ts[6] = np.nan, 0.0
    path = write_session(tmp_path / "s.h5", frames, timestamps=ts, camera_mode=MODE,
                         calibration=Calibration(px_per_mm=62.0))
    with open_session(path) as s:
        faults = s.timestamp_faults()
    assert faults[0].startswith("1 of the 8 frame time stamps are not finite (the first: frame 2, nan)")
    assert faults[1].startswith("the frame time stamps go back in time 1 time(s) (the first: frame 6")
    with open_session(_replay_source(tmp_path, n=4)) as s:
        assert s.timestamp_faults() == []
