"""The real simulated rig end to end: scene camera -> recorder (with truth and force), and playback on the
STReSS firmware twin with the Net F/T twin: closed loop beats open loop, force ceiling and link loss stop it."""

import numpy as np
import pytest

from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.playback import play_movie
from skinstretch.experiments.protocol import DeviceSpec, Rig, parse_protocol
from skinstretch.experiments.rig import ForceSource, RigDevices, make_display, sim_display_url
from skinstretch.experiments.runner import read_events, run_protocol
from skinstretch.drivers.errors import DeviceError

PROTOCOL = """\
name: rigtest
subject: {id: s02}
camera_mode: strip
trials:
  - {name: ridge, duration_s: 0.08, surface: {kind: ridge}}
analysis: {enabled: false}
record: {force: true, display: true}
"""


def _movie(n, seed=1):
    t = np.arange(n) / 700.0
    rng = np.random.default_rng(seed)
    return rng.uniform(10, 25, (10, 10)) * np.sin(2 * np.pi * 2.0 * t[:, None, None] + rng.uniform(0, 6, (10, 10)))


def test_simulated_rig_records_frames_truth_force_and_display(tmp_path):
    protocol = parse_protocol(PROTOCOL)
    result = run_protocol(protocol, Rig(), tmp_path, progress=lambda m: None)
    (trial,) = result.trials
    assert trial.status == "complete", trial.reason
    with open_session(trial.path) as s:
        assert s.complete and s.camera_mode.name == "strip" and s.n_frames == 18  # 0.08 s at 220 Hz
        assert s.has_truth and s.truth.feature_x.shape[0] == 18
        assert s.metadata["scene"] == "ridgeL" and s.metadata["rig"]["display"].startswith("sim")
        t, f = s.read_stream("force")
        assert f.shape[0] > 0 and np.all(np.abs(f[:, 2] - 1.5) < 0.2)  # the twin's 1.5 N normal force
        _, d = s.read_stream("display_state")
        assert d.shape == (18, 10, 10) and np.all(d == 0)  # at rest during recording
        assert np.all(np.diff(s.frame_ids) == 1)
    names = [n for n, _ in read_events(result.directory / "events.jsonl")]
    assert names[0] == "start" and names[-1] == "stop"


def test_closed_loop_beats_open_loop_five_times_on_the_twin():
    # 350 Hz rather than the display's 700 Hz: a starved CI host must not turn this into a link-failure test
    # (the bench section `playback` measures 700 Hz).
    movie = _movie(700)[::2]
    rms = {}
    for closed in (False, True):
        # The twin runs in this process: a host starved for > 0.2 s (a loaded CI machine) makes the driver declare
        # the link dead, which is right but not what this test is about, so such a run is repeated (at most 3).
        for _attempt in range(3):
            display = make_display(sim_display_url(seed=3, load_n_per_mm=0.15))
            try:
                display.zero()
                r = play_movie(display, movie, rate_hz=350.0, closed_loop=closed, settle_frames=100)
            finally:
                display.close()
            if "link failed" not in r.stopped:
                break
        assert r.complete and r.rested, r.stopped
        rms[closed] = r.rms_error_um
    assert rms[True] * 5 <= rms[False], rms


def test_force_ceiling_on_the_twins_stops_with_contactors_at_rest(tmp_path):
    rig = Rig(camera=DeviceSpec(kind="sim"), force=DeviceSpec(kind="sim", options={"normal_force_n": 7.0}))
    devices = RigDevices(rig)
    try:
        display = devices.display_device()
        r = play_movie(display, _movie(300), force=devices.force, force_ceiling_n=5.0, path=tmp_path / "pb.h5")
        assert r.stopped.startswith("safety stop") and "ceiling" in r.stopped and r.frames_played < 300
        assert r.rested and not display.armed
        assert np.all(np.abs(display.read_status().positions_um) < 2.0)  # back at rest (ramp just finishing)
        with open_session(tmp_path / "pb.h5") as s:
            assert s.status == "failed" and "ceiling" in s.status_reason
    finally:
        devices.close()


def test_link_loss_stops_the_movie():
    display = make_display(sim_display_url(seed=4, faults="vanish_after:100"))
    try:
        display.zero()
        r = play_movie(display, _movie(400))
    finally:
        display.close()
    assert "display link failed" in r.stopped and r.frames_played < 400
    assert not display.armed


def test_force_source_reads_blocks_and_latest():
    devices = RigDevices(Rig(display=DeviceSpec(kind="none")))
    try:
        force: ForceSource = devices.force
        force.begin()
        t, data = force.read_block(timeout_s=1.0)
        assert len(t) >= 1 and data.shape[1] == 6
        assert force.latest() is not None and abs(force.latest()[2] - 1.5) < 0.2
    finally:
        devices.close()


def test_v4l2_camera_in_a_rig_file():
    rig = Rig.model_validate({"camera": {"kind": "v4l2", "device": "/dev/video99"}})
    assert rig.camera.kind == "v4l2" and not rig.all_simulated
    proto = parse_protocol(PROTOCOL, source="<test>")
    cam = RigDevices(rig).camera_for(trial=None, protocol=proto, n_frames=2)
    from skinstretch.drivers.camera.v4l2 import V4L2Camera

    assert isinstance(cam.camera, V4L2Camera)
    # No such device here: a clear device error naming it, not a hang or a crash in OpenCV.
    with pytest.raises(DeviceError, match="video99"):
        cam.start()
    with pytest.raises(ValueError, match="camera.kind"):
        Rig.model_validate({"camera": {"kind": "webcam"}})
