"""Real-time movie streaming on the simulated display (functional checks only; speed is in the bench)."""

import itertools
import time

import numpy as np
import pytest

from skinstretch.drivers.errors import InvalidTargetError
from skinstretch.drivers.display.movie_stream import PHASES, find_stalls, stream_movie
from skinstretch.drivers.display.stress import StressDisplay
from skinstretch.drivers.display.transports import SerialTransport
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators import stress_links

_names = itertools.count()


@pytest.fixture
def sim():
    stress_links.register_url_handler()
    link = stress_links.make_link(seed=7)
    name = f"playback{next(_names)}"
    display = StressDisplay(SerialTransport(stress_links.attach(name, link)), watchdog_s=0.3, ack_timeout_s=0.5)
    yield display, link
    display.close()
    stress_links.detach(name)


def test_movie_is_played_acked_and_position_error_reported(sim):
    display, link = sim
    display.zero()
    n = 140
    movie = 25 * np.sin(2 * np.pi * 5 * np.arange(n) / 700)[:, None, None] * np.linspace(0.2, 1, 100).reshape(10, 10)
    report = stream_movie(display, movie, rate_hz=700, max_outstanding=100)
    assert report.outcome == "completed" and report.rested
    sent = ~report.skipped  # frames are skipped only when the host is starved for a whole period
    assert report.frames_played == n and report.acked.sum() >= sent.sum() - 2
    # after a skip the movie may jump further than the slew limit allows: compare frames following a sent one
    recent_skip = np.convolve(report.skipped.astype(int), np.ones(10, int))[:n] > 0
    steady = sent & ~recent_skip
    assert np.allclose(report.commands_um[steady], np.rint(movie * 2)[steady] / 2)
    assert np.array_equal(np.array(link.firmware.commands_um)[-sent.sum():], report.commands_um[sent])
    rms = report.position_rms_error_um()
    assert rms.shape == (10, 10) and np.all(np.isfinite(rms))
    # lag, hysteresis, gain spread and 0.5 um quantisation: about a micrometre, never tens
    assert 0.05 < rms.mean() < 3.0
    assert report.period_jitter_p99_s >= 0 and report.missed_deadlines <= n
    assert np.all(np.diff(report.deadlines_s) > 0)


def test_callback_sees_acks_and_corrects_commands(sim):
    display, _ = sim
    seen = []

    def offset_by_two(index, command, ack):
        seen.append(ack is not None)
        return command + 2.0

    report = stream_movie(display, np.zeros((60, 10, 10)), callback=offset_by_two)
    assert report.completed
    assert np.all(report.commands_um[~report.skipped] == 2.0) and any(seen[10:])


def test_unsafe_movie_is_limited_not_refused(sim):
    display, link = sim
    movie = np.full((30, 10, 10), 500.0)
    report = stream_movie(display, movie)
    assert report.completed
    assert np.abs(report.commands_um).max() <= 50
    assert np.abs(np.diff(report.commands_um, axis=0)).max() <= display.max_step_um
    assert link.firmware.clamped_frames == 0


@pytest.mark.parametrize("kwargs, name", [(dict(rate_hz=900), "rate_hz"), (dict(rate_hz=700, spin_s=0.01), "spin_s"),
                                          (dict(max_outstanding=0), "max_outstanding"),
                                          (dict(settle_frames=-1), "settle_frames")])
def test_bad_options_are_refused_by_name(sim, kwargs, name):
    with pytest.raises(InvalidInputError, match=name):
        stream_movie(sim[0], np.zeros((5, 10, 10)), **kwargs)


def test_bad_movie_shape_is_refused(sim):
    with pytest.raises(InvalidInputError, match="movie_um"):
        stream_movie(sim[0], np.zeros((5, 10)))


@pytest.mark.parametrize("bad", [np.nan, np.inf, 1j])
def test_a_movie_with_a_non_position_is_refused_before_the_display_moves(sim, bad):
    display, link = sim
    movie = np.zeros((30, 10, 10), complex if bad == 1j else float)
    movie[5, 2, 7] = bad
    with pytest.raises(InvalidTargetError, match=r"frame 5, contactor \(2, 7\)"):
        stream_movie(display, movie)
    assert not display.armed and link.firmware.frames_received == 0


def test_no_ack_means_no_error_figure_not_nan(sim):
    display, link = sim
    link.stall()
    report = stream_movie(display, np.zeros((3, 10, 10)), final_ack_timeout_s=0.01)
    assert not report.acked.any()
    with pytest.raises(InvalidInputError, match="no acknowledged frame"):
        report.position_rms_error_um()


def test_a_failing_callback_still_rests_the_display_then_raises(sim):
    display, link = sim

    def broken(index, command, ack):
        if index >= 20:  # not == 20: a loaded machine may skip that frame as late
            return np.zeros((3, 3))  # a bug in the caller's controller
        return command + 5.0

    with pytest.raises(InvalidInputError, match="requested_um"):
        stream_movie(display, np.zeros((40, 10, 10)), rate_hz=200, callback=broken)
    assert np.all(display.last_command_um == 0)
    link.advance()
    assert link.firmware.benders.resting


def test_every_frame_is_stamped_at_each_phase_in_order(sim):
    display, _ = sim
    report = stream_movie(display, np.zeros((80, 10, 10)), rate_hz=500)
    assert report.completed
    ph = report.phase_times_s
    assert ph.shape == (80, len(PHASES))
    sent = ~report.skipped
    assert np.all(np.isfinite(ph[sent]))
    stamps = ph[sent].reshape(-1)
    assert np.all(np.diff(stamps) >= 0)  # one clock, stamped in loop order
    assert np.array_equal(ph[sent, PHASES.index("send")], report.send_times_s[sent])
    assert np.all(ph[sent, PHASES.index("send")] >= report.deadlines_s[sent])  # never sent early
    assert report.thread_cpu_s[0] == 0 and np.all(np.diff(report.thread_cpu_s) >= 0)
    assert report.clock_origin_s > 0


@pytest.mark.parametrize("how", ["sleep", "spin"])
def test_a_stall_is_located_by_frame_phase_and_cpu_charge(sim, how):
    display, _ = sim

    stalled_at = []

    def stall_once(index, command, ack):
        if index >= 40 and not stalled_at:  # frame 40 itself may be skipped on a starved machine
            stalled_at.append(index)
            if how == "sleep":
                time.sleep(0.02)  # off the CPU: a late wake-up, the GIL held elsewhere, a stolen vCPU look so
            else:
                end = time.thread_time() + 0.02  # 20 ms on the CPU, charged to the sending thread
                while time.thread_time() < end:
                    pass
        return None

    report = stream_movie(display, np.zeros((120, 10, 10)), rate_hz=500, callback=stall_once,
                          max_outstanding=100)
    assert report.completed and len(stalled_at) == 1
    k = stalled_at[0]
    ours = [s for s in report.stalls(0.015) if s.frame == k and s.after == "prepared"]
    assert len(ours) == 1, report.stalls(0.015)
    stall = ours[0]
    assert stall.before == "waited"  # the callback runs between these two stamps
    assert stall.duration_s >= 0.02
    assert stall.start_s == pytest.approx(report.phase_times_s[k, PHASES.index("waited")])
    if how == "sleep":
        assert stall.thread_cpu_s < 0.5 * stall.duration_s
    else:
        assert stall.thread_cpu_s >= 0.02


def test_find_stalls_skips_unstamped_phases_and_checks_its_threshold():
    ph = np.arange(20, dtype=float).reshape(4, 5) * 1e-3  # 1 ms between stamps
    ph[2, 1:] = np.nan  # a skipped frame is stamped at its start only
    ph[3:] += 0.010  # 10 ms lost between frame 2's start and frame 3's start
    cpu = np.array([0.0, 0.001, 0.002, 0.003])
    stalls = find_stalls(ph, cpu, min_gap_s=0.005)
    assert len(stalls) == 1
    s = stalls[0]
    assert (s.frame, s.before, s.after) == (3, "start", "start")
    assert s.duration_s == pytest.approx(0.015) and s.start_s == pytest.approx(0.010)
    assert np.isnan(s.thread_cpu_s)  # no stamp after the last frame
    assert find_stalls(ph, None, min_gap_s=0.02) == []
    assert find_stalls(np.empty((0, 5)), None) == []
    with pytest.raises(InvalidInputError, match="min_gap_s"):
        find_stalls(ph, cpu, min_gap_s=0.0)
