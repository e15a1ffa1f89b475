"""Closed-loop playback: the corrector beats open loop on a display with hysteresis and finger load, and the
force ceiling and a link failure stop the movie with every contactor at rest."""

import numpy as np
import pytest

from skinstretch.drivers.display.base import DisplayInfo, FrameAck, TactileDisplay
from skinstretch.drivers.display.stress_protocol import Status
from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.playback import ContactorCorrector, _check_movie, load_movie, play_movie
from skinstretch.drivers.errors import DeviceError, SessionFileError
from skinstretch.processing.errors import InvalidInputError


class PlantDisplay(TactileDisplay):
    """A display whose contactors have a gain error, a load offset and backlash (hysteresis); the ack of a frame
    reports the positions reached under the previous frame, quantised to 0.5 um like the wire encoding."""

    def __init__(self, *, seed=0, backlash_um=4.0, load_um=-3.0, fail_after=None, **kw):
        super().__init__(**kw)
        rng = np.random.default_rng(seed)
        self.gain = rng.uniform(0.8, 1.1, (10, 10))
        self.offset = load_um + rng.normal(0, 1.0, (10, 10))
        self.half_band = backlash_um / 2
        self.pos = np.zeros((10, 10))
        self.inner = np.zeros((10, 10))
        self.fail_after = fail_after
        self.frames = 0
        self.rested = True
        self._seq = 0
        self._pending = []

    @property
    def outstanding(self):
        return len(self._pending)

    def _do_identify(self):
        return DisplayInfo("plant", "0", 1, 10, 10, 50.0, 1000)

    def _do_configure(self, *, watchdog_s, max_step_um):
        pass

    def _do_arm(self):
        self.rested = False

    def _do_disarm(self):
        self._do_rest()

    def _do_zero(self):
        pass

    def _do_rest(self):
        if self.fail_after is not None and self.frames >= self.fail_after:
            raise DeviceError("link lost (plant)")
        self.inner[:] = 0
        self.pos[:] = 0
        self.rested = True

    def _do_read_status(self):
        raise NotImplementedError

    def _do_submit_frame(self, command_um):
        if self.fail_after is not None and self.frames >= self.fail_after:
            raise DeviceError("link lost (plant)")
        self.frames += 1
        measured = np.round(self.pos * 2) / 2  # what the sensors read when the frame arrives
        drive = self.gain * command_um
        # backlash: the inner position follows the drive only beyond the dead band
        self.inner = np.clip(self.inner, drive - self.half_band, drive + self.half_band)
        self.pos = self.inner + self.offset
        self._seq = (self._seq + 1) & 0xFF
        self._pending.append(FrameAck(self._seq, Status.ARMED, measured, command_um, 0.0, 0.0))
        return self._seq

    def _do_collect_acks(self, *, wait_for, timeout_s):
        got, self._pending = self._pending, []
        return got

    def _do_close(self):
        pass


class StepClock:
    """Deterministic deadline clock: every reading advances 50 us, so the stream never falls behind a starved
    host's wall clock (the fake display answers at once)."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 5e-5
        return self.t


def _play(display, movie, **kw):
    return play_movie(display, movie, clock=StepClock(), **kw)


class FixedForce:
    def __init__(self, values):
        self.values = list(values)
        self.k = 0

    def latest(self):
        v = self.values[min(self.k, len(self.values) - 1)]
        self.k += 1
        return np.array([0.0, 0.0, v, 0.0, 0.0, 0.0])


def _movie(n=1000, seed=1):
    t = np.arange(n) / 700.0
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, (10, 10))
    amp = rng.uniform(10, 30, (10, 10))
    return amp * np.sin(2 * np.pi * 2.0 * t[:, None, None] + phase)


def test_closed_loop_cuts_rms_error_at_least_five_times(tmp_path):
    movie = _movie()
    open_ = _play(PlantDisplay(), movie, closed_loop=False, settle_frames=250)
    closed = _play(PlantDisplay(), movie, closed_loop=True, settle_frames=250, path=tmp_path / "pb.h5")
    assert open_.complete and closed.complete and closed.rested
    assert open_.rms_error_um > 2.0
    assert closed.rms_error_um * 5 <= open_.rms_error_um, (open_.rms_error_um, closed.rms_error_um)
    with open_session(tmp_path / "pb.h5") as s:
        assert s.complete and s.metadata["closed_loop"] is True
        t, measured = s.read_stream("display_measured")
        assert measured.shape == (1000, 10, 10)
        _, cmd = s.read_stream("display_command")
        # the corrections stay bounded
        assert np.max(np.abs(cmd - movie.astype(np.float32))[250:]) <= ContactorCorrector().max_correction_um + 0.5


def test_force_ceiling_stops_movie_with_contactors_at_rest(tmp_path):
    display = PlantDisplay()
    force = FixedForce([1.0] * 101 + [6.0])  # the first sample is read before the movie starts
    result = _play(display, _movie(400), force=force, force_ceiling_n=5.0, path=tmp_path / "pb.h5")
    assert result.stopped.startswith("safety stop: normal force 6.00 N")
    assert result.frames_sent == 100 and not result.complete  # frames skipped on a starved host aside
    assert display.rested and not display.armed and result.rested
    assert np.all(display.pos == 0)
    with open_session(tmp_path / "pb.h5") as s:
        assert s.status == "failed" and "safety stop" in s.status_reason
        assert s.read_stream("display_target")[1].shape[0] == result.frames_played
        _, wrench = s.read_stream("force")  # the sample that tripped the ceiling is kept, after the played frames'
        assert wrench.shape[0] == result.frames_played + 1 and wrench[-1, 2] == 6.0
    assert result.extra["ceiling_sample"]["frame"] == result.frames_played


def test_link_failure_stops_movie_and_reports_it():
    display = PlantDisplay(fail_after=50)
    result = _play(display, _movie(200))
    assert result.frames_sent == 50 and "display link failed" in result.stopped
    assert not result.rested  # the link is gone: the host could not confirm; the firmware watchdog rests it
    assert not display.armed


def test_a_run_stopped_within_its_start_up_says_no_rms_error_in_words():
    lines = []
    result = _play(PlantDisplay(fail_after=5), _movie(200), settle_frames=20, progress=lines.append)
    assert result.frames_sent == 5 and np.isnan(result.rms_error_um)
    assert "nan" not in lines[-1].lower() and "RMS error n/a" in lines[-1]


def test_corrector_learns_gain_offset_and_backlash():
    display = PlantDisplay(seed=3)
    corrector = ContactorCorrector()
    _play(display, _movie(1000), corrector=corrector)
    np.testing.assert_allclose(corrector.gain, display.gain, atol=0.05)
    np.testing.assert_allclose(corrector.offset_um, display.offset, atol=1.0)
    assert np.median(np.abs(corrector.backlash_um + display.half_band)) < 0.7


def test_bad_inputs_are_named():
    with pytest.raises(InvalidInputError, match="movie_um"):
        _play(PlantDisplay(), np.zeros((5, 8, 8)))
    with pytest.raises(InvalidInputError, match=r"frame 0, contactor \(0, 0\) is nan"):
        _play(PlantDisplay(), np.full((5, 10, 10), np.nan))
    with pytest.raises(InvalidInputError, match="max_correction_um"):
        ContactorCorrector(max_correction_um=-1)


def test_load_movie_formats(tmp_path):
    m = np.zeros((4, 10, 10))
    m[1, 2, 3] = 7.5
    np.save(tmp_path / "m.npy", m)
    got, rate = load_movie(tmp_path / "m.npy")
    assert got.shape == (4, 10, 10) and got[1, 2, 3] == 7.5 and rate is None
    with pytest.raises(SessionFileError, match="no such"):
        load_movie(tmp_path / "none.npy")
    np.save(tmp_path / "bad.npy", np.zeros((4, 3)))
    with pytest.raises(InvalidInputError, match="shape"):
        load_movie(tmp_path / "bad.npy")


def test_a_users_movie_with_nan_or_complex_values_is_refused_naming_the_frame(tmp_path):
    # A user's movie: NaN is refused (issue 41: it was silently reset to rest), and so is a complex array (it
    # played, imaginary parts dropped, with only numpy's ComplexWarning).
    m = np.zeros((4, 10, 10))
    m[1, 2, 3] = np.nan
    np.save(tmp_path / "nan.npy", m)
    with pytest.raises(InvalidInputError, match=r"nan.npy: frame 1, contactor \(2, 3\) is nan"):
        load_movie(tmp_path / "nan.npy")
    np.save(tmp_path / "complex.npy", np.zeros((4, 10, 10), complex))
    with pytest.raises(InvalidInputError, match="complex.npy is complex"):
        load_movie(tmp_path / "complex.npy")
    # A movie the analysis wrote: NaN marks a contactor it could not measure, reset to rest (seed 5.4).
    got = _check_movie(m, tmp_path / "analysis", analysed=True)
    assert got[1, 2, 3] == 0 and np.isfinite(got).all()
    with pytest.raises(InvalidInputError, match="is inf"):
        _check_movie(np.where(np.isnan(m), np.inf, m), tmp_path / "analysis", analysed=True)


def test_corrector_stays_converged_over_a_long_movie():
    # 60 s at 700 Hz of a plant with gain 0.8, offset 0.3 um and backlash 0.5 um: the estimates must stay put
    # (an RLS whose covariance drifts from symmetric ran away after ~9 s on the display twin).
    rng = np.random.default_rng(4)
    corrector = ContactorCorrector()
    t = np.arange(42_000) / 700.0
    phase = rng.uniform(0, 2 * np.pi, (10, 10))
    prev_cmd, direction, direction_prev = np.zeros((10, 10)), np.ones((10, 10)), np.ones((10, 10))
    for k in range(t.size):
        target = 20 * np.sin(2 * np.pi * 2.0 * t[k] + phase)
        cmd = corrector.command(target)
        step = cmd - prev_cmd
        direction = np.where(np.abs(step) > 1e-9, np.sign(step), direction)
        measured = 0.8 * prev_cmd + 0.3 + 0.5 * direction_prev  # the ack of frame k answers frame k - 1
        corrector.observe_ack(FrameAck(k & 0xFF, Status.ARMED, measured + rng.normal(0, 0.05, (10, 10)), cmd, 0.0, 0.0))
        prev_cmd, direction_prev = cmd, direction.copy()
    np.testing.assert_allclose(corrector.gain, 0.8, atol=0.02)
    np.testing.assert_allclose(corrector.offset_um, 0.3, atol=0.1)
    np.testing.assert_allclose(corrector.backlash_um, 0.5, atol=0.1)
    assert np.all(np.isfinite(corrector.P)) and np.allclose(corrector.P, corrector.P.transpose(0, 2, 1))


class BrokenForce:
    """A force sensor whose driver fails after some frames (a bug, a lost connection raising an unexpected error)."""

    def __init__(self, after):
        self.after, self.k = after, 0

    def latest(self):
        self.k += 1
        if self.k > self.after:
            raise RuntimeError("sensor driver crashed")
        return np.array([0.0, 0.0, 1.5, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("closed_loop", [True, False])
def test_an_interrupted_movie_keeps_what_it_played_with_the_contactors_at_rest(tmp_path, closed_loop):
    display = PlantDisplay()
    movie = _movie(300)
    with pytest.raises(RuntimeError, match="sensor driver crashed"):
        _play(display, movie, force=BrokenForce(after=121), closed_loop=closed_loop, buffered=False,  # 1: before
              path=tmp_path / "pb.h5", metadata={"trial": 7})
    assert display.rested and not display.armed
    with open_session(tmp_path / "pb.h5") as s:
        assert s.status == "failed" and "interrupted: RuntimeError: sensor driver crashed" in s.status_reason
        assert s.metadata["trial"] == 7 and s.metadata["command_source"].startswith("host")
        t, target = s.read_stream("display_target")
        assert target.shape == (120, 10, 10) and np.all(np.diff(t) >= 0)
        np.testing.assert_array_equal(target, movie[:120].astype(np.float32))
        _, cmd = s.read_stream("display_command")
        assert np.all(np.isfinite(cmd))
        if not closed_loop:
            np.testing.assert_array_equal(cmd, target)
        _, measured = s.read_stream("display_measured")
        assert np.all(np.isnan(measured))
        _, force = s.read_stream("force")
        assert force.shape == (120, 6) and np.all(force[:, 2] == 1.5)
