"""Timed, buffered playback: the protocol's new messages, the firmware's FIFO and timer, the host's buffered loop.

Everything runs on the firmware simulator's manual clock (simulated time: deterministic, and a "host stall" is a
clock jump), except the conformance test in test_display_conformance.py that plays timed frames over each
transport in real time.
"""

import dataclasses
import doctest
import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import skinstretch.drivers.display.movie_stream as playback_module
from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.display.base import TactileDisplay, TimedFrameAck
from skinstretch.drivers.display.movie_stream import (DEFAULT_LEAD_S, FATE_NOT_SENT, BufferedPlaybackReport, stream_movie,
                                      stream_movie_buffered)
from skinstretch.drivers.display.stress import StressDisplay
from skinstretch.drivers.display.transports import SerialTransport
from skinstretch.drivers.errors import DeviceError, ProtocolError, SafetyStop
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators import stress_links
from skinstretch.simulators.stress_firmware import REFUSED, StressFirmware
from skinstretch.simulators.stress_wire import ManualClock

PERIOD = 1 / 700
_names = itertools.count()


class TickingClock(ManualClock):
    """A manual clock that also moves 1 us at every reading, so a busy-wait on it ends (the immediate loop spins
    before each deadline); sleeps jump ahead as on :class:`ManualClock`."""

    def now(self) -> float:
        self.advance(1e-6)
        return self._t


@pytest.fixture
def twin():
    """make(clock=None, faults="", **driver options) -> (display, link) on the in-process stresssim link."""
    stress_links.register_url_handler()
    made = []

    def make(clock=None, faults="", **options):
        clock = clock or TickingClock()
        link = stress_links.make_link(clock=clock, seed=5, faults=faults)
        name = f"buffered{next(_names)}"
        display = StressDisplay(SerialTransport(stress_links.attach(name, link)), clock=clock.now, **options)
        made.append((display, name))
        return display, link

    yield make
    for display, name in made:
        display.close()
        stress_links.detach(name)


def _wave(n, amplitude=20.0):
    t = np.arange(n)[:, None, None] / 700
    x = np.arange(10)[None, None, :] + 0.3 * np.arange(10)[None, :, None]
    return amplitude * np.sin(2 * np.pi * 8 * (t - x / 40.0))


# ---- protocol ---------------------------------------------------------------------------------------------------

def test_timed_messages_round_trip_and_have_the_documented_sizes(rng):
    start = sp.MovieStart(rate_mhz=700_000, n_frames=42_000, start_delay_us=80_000)
    assert len(start.encode()) == 12 and sp.MovieStart.decode(start.encode()) == start
    positions = np.round(rng.uniform(-50, 50, (10, 10)) * 2) / 2
    payload = sp.encode_timed_frame(123_456, sp.encode_positions(positions))
    packet = sp.encode_packet(seq=3, command=sp.Command.TIMED_FRAME, payload=payload)
    assert len(packet) == 111 and packet[4] == 0x0A
    tick, back = sp.decode_timed_frame(sp.StreamDecoder().feed(packet)[0].payload)
    assert tick == 123_456 and np.array_equal(back, positions)

    sample = np.round(rng.uniform(-60, 60, (10, 10)) * 2) / 2
    report = sp.TickReport(41_999, 59_998_571, sp.TickFlags.APPLIED | sp.TickFlags.CLAMPED, sample)
    reply = sp.TimedFrameReply(sp.Status.ARMED | sp.Status.MOVIE, 42_055, sp.Disposition.LATE, 17, -2_500,
                               70_001, 3, report)
    again = sp.TimedFrameReply.decode(reply.encode())
    assert len(reply.encode()) == sp.TimedFrameReply.SIZE == 125
    assert (again.tick, again.disposition, again.fifo_fill, again.rx_time_us) == (42_055, sp.Disposition.LATE, 17,
                                                                                   -2_500)
    assert (again.late_frames, again.underruns) == (70_001 % 65_536, 3)  # running counts wrap at 16 bits
    assert (again.report.tick, again.report.time_us, again.report.applied) == (41_999, 59_998_571, True)
    assert again.report.flags & sp.TickFlags.CLAMPED and np.array_equal(again.report.sample_um, sample)

    status = sp.MovieStatus(sp.Status.ARMED, sp.FIFO_DEPTH, 56, 700_000, 42_000, -80_000, 7, 8, 9, 10, 11, 12, 13)
    assert len(status.encode()) == sp.MovieStatus.SIZE == 153
    again = sp.MovieStatus.decode(status.encode())
    assert dataclasses.replace(again, report=status.report) == status  # the (array-holding) report aside
    assert not again.report.present and not again.running


def test_tick_times_are_exact_integers_on_a_1_us_timer():
    ticks = np.arange(42_001)
    times = np.array([sp.tick_time_us(int(k), rate_mhz=700_000) for k in ticks])
    assert set(np.diff(times)) == {1428, 1429}
    assert times[700] == 1_000_000 and times[42_000] == 60_000_000  # no drift over a minute


@pytest.mark.parametrize("make, name", [
    (lambda: sp.MovieStart(rate_mhz=0, n_frames=1, start_delay_us=0), "rate_mhz"),
    (lambda: sp.MovieStart(rate_mhz=700_001, n_frames=1, start_delay_us=0), "rate_mhz"),
    (lambda: sp.MovieStart(rate_mhz=700_000, n_frames=1, start_delay_us=2_000_000), "start_delay_us"),
    (lambda: sp.encode_timed_frame(-1, bytes(100)), "tick"),
    (lambda: sp.encode_timed_frame(0, bytes(99)), "positions"),
    (lambda: sp.rate_to_mhz(900.0), "rate_hz"),
    (lambda: sp.rate_to_mhz(float("nan")), "rate_hz"),
])
def test_bad_timed_values_are_refused_by_name(make, name):
    with pytest.raises(InvalidInputError, match=name):
        make()


def test_malformed_timed_payloads_raise_protocol_error():
    with pytest.raises(ProtocolError, match="out of range"):
        sp.MovieStart.decode(bytes(12))  # rate 0
    bad = bytearray(sp.TimedFrameReply(sp.Status(0), 0, sp.Disposition.QUEUED, 0, 0, 0, 0,
                                       sp.TickReport()).encode())
    bad[6] = 9  # disposition
    with pytest.raises(ProtocolError, match="disposition"):
        sp.TimedFrameReply.decode(bytes(bad))
    with pytest.raises(ProtocolError, match="negative tick"):
        sp.TickReport.decode(b"\xff\xff\xff\xfe" + bytes(sp.TickReport.SIZE - 4))


_sizes = [12, 4 + sp.N_CONTACTORS, sp.TickReport.SIZE, sp.TimedFrameReply.SIZE, sp.MovieStatus.SIZE]


@given(st.one_of(st.binary(max_size=300), *[st.binary(min_size=n, max_size=n) for n in _sizes]))
@settings(max_examples=300, deadline=None)
def test_timed_payload_decoders_fuzz_raise_only_protocol_error(data):
    for decode in (sp.MovieStart.decode, sp.decode_timed_frame, sp.TickReport.decode, sp.TimedFrameReply.decode,
                   sp.MovieStatus.decode):
        try:
            decode(data)
        except ProtocolError:
            pass


@given(st.integers(0, 2**32 - 1), st.sampled_from(list(sp.Disposition)), st.integers(0, 255),
       st.integers(-2**31, 2**31 - 1), st.integers(0, 2**40), st.integers(-1, 2**31 - 1),
       hnp.arrays(np.int8, (10, 10)))
@settings(max_examples=100, deadline=None)
def test_timed_reply_round_trips_any_field_values(tick, disposition, fill, rx_us, counter, report_tick, counts):
    report = sp.TickReport(report_tick, rx_us, sp.TickFlags.APPLIED, counts.astype(float) * 0.5)
    reply = sp.TimedFrameReply(sp.Status.MOVIE, tick, disposition, fill, rx_us, counter, counter, report)
    back = sp.TimedFrameReply.decode(reply.encode())
    assert (back.tick, back.disposition, back.fifo_fill, back.rx_time_us) == (tick, disposition, fill, rx_us)
    assert back.late_frames == counter % 65_536 and back.report.tick == report_tick
    assert np.array_equal(back.report.sample_um, report.sample_um)


@given(st.lists(st.binary(max_size=40), min_size=4, max_size=4), st.lists(st.integers(1, 64), max_size=30))
@settings(max_examples=100, deadline=None)
def test_timed_packets_are_found_between_garbage_in_any_chunking(garbage, cuts):
    packets = [sp.encode_packet(seq=1, command=sp.Command.START_MOVIE,
                                payload=sp.MovieStart(700_000, 0, 50_000).encode()),
               sp.encode_packet(seq=2, command=sp.Command.TIMED_FRAME, payload=sp.encode_timed_frame(7, bytes(100))),
               sp.encode_packet(seq=2, command=sp.reply_command(sp.Command.TIMED_FRAME),
                                payload=sp.TimedFrameReply(sp.Status.MOVIE, 7, sp.Disposition.QUEUED, 1, -3, 0, 0,
                                                           sp.TickReport()).encode()),
               sp.encode_packet(seq=3, command=sp.reply_command(sp.Command.READ_MOVIE),
                                payload=sp.MovieStatus(sp.Status(0), 128, 0, 700_000, 0, 0, 0, 0, 0, 0, 0, 0,
                                                       0).encode())]
    stream = b"".join(g + p for g, p in zip(garbage, packets))
    decoder, out, pos = sp.StreamDecoder(), [], 0
    for c in cuts:
        out += decoder.feed(stream[pos:pos + c])
        pos += c
    out += decoder.feed(stream[pos:])
    wanted = [(p[3], p[4], p[5:-2]) for p in packets]
    got = [(p.seq, p.command, p.payload) for p in out]
    assert [w for w in wanted if w in got] == wanted  # a garbage byte may add a packet, never hide one


# ---- the firmware's FIFO and timer ------------------------------------------------------------------------------

class Bench:
    """Packets straight into a firmware at chosen times."""

    def __init__(self, *, watchdog_s=0.05):
        self.fw = StressFirmware(seed=2)
        self.seq = 0
        self.send(sp.Command.CONFIGURE, sp.WatchdogConfig(watchdog_s=watchdog_s).encode(), 0.0)
        self.send(sp.Command.ARM, b"", 0.0)

    def send(self, command, payload, t):
        self.seq = (self.seq + 1) & 0xFF
        return sp.StreamDecoder().feed(self.fw.handle(sp.Packet(self.seq, int(command), payload), t))[0]

    def start(self, t, *, n_frames=0, delay_s=0.01):
        return sp.MovieStatus.decode(self.send(sp.Command.START_MOVIE,
                                               sp.MovieStart(700_000, n_frames, round(delay_s * 1e6)).encode(),
                                               t).payload)

    def frame(self, tick, um, t):
        reply = self.send(sp.Command.TIMED_FRAME,
                          sp.encode_timed_frame(tick, sp.encode_positions(np.full((10, 10), float(um)))), t)
        return sp.TimedFrameReply.decode(reply.payload) if reply.command != sp.Command.NAK else reply

    def play_time(self, tick):
        return self.fw.tick_time(tick)


def test_frames_take_effect_at_their_ticks_whatever_their_arrival():
    b = Bench()
    b.start(0.0, delay_s=0.01)
    for k in range(5):  # all five arrive at once, 10 ms early
        reply = b.frame(k, 2.0 * (k + 1), 0.0001 * (k + 1))
        assert reply.disposition == sp.Disposition.QUEUED and reply.fifo_fill == k + 1
        assert reply.rx_time_us == pytest.approx(-10_000 + 100 * (k + 1), abs=1)
    fw = b.fw
    for k in range(5):
        fw.advance(b.play_time(k) - 1e-7)
        assert np.all(fw.last_command_um == 2.0 * k)  # still the previous frame (0 before tick 0)
        fw.advance(b.play_time(k))
        assert np.all(fw.last_command_um == 2.0 * (k + 1))
    assert fw.timed.tick_times == [b.play_time(k) for k in range(5)]
    assert fw.movie_counters["frames_played"] == 5 and fw.movie_counters["underruns"] == 0
    assert b.play_time(1) - b.play_time(0) == pytest.approx(1428e-6, abs=1e-9)  # the 1 us timer


def test_a_frame_arriving_at_or_after_its_play_time_is_late_dropped_and_counted():
    b = Bench()
    b.start(0.0)
    b.frame(0, 3.0, 0.001)
    late = b.frame(1, 6.0, b.play_time(1))  # exactly at its play time: too late
    assert late.disposition == sp.Disposition.LATE and late.late_frames == 1
    assert late.status & sp.Status.LATE_FRAME
    b.fw.advance(b.play_time(2))
    assert np.all(b.fw.last_command_um == 3.0)  # dropped: tick 1 held frame 0
    assert b.fw.movie_counters["late_frames"] == 1 and b.fw.movie_counters["underruns"] == 2  # ticks 1, 2
    assert b.fw.timed.dispositions == [sp.Disposition.QUEUED, sp.Disposition.LATE]


def test_a_full_fifo_refuses_at_once_and_never_blocks():
    b = Bench()
    b.start(0.0, n_frames=1000, delay_s=0.5)
    for k in range(sp.FIFO_DEPTH):
        assert b.frame(k, 0.5, 0.001).disposition == sp.Disposition.QUEUED
    full = b.frame(sp.FIFO_DEPTH, 0.5, 0.001)
    assert full.disposition == sp.Disposition.FIFO_FULL and full.fifo_fill == sp.FIFO_DEPTH
    assert full.status & sp.Status.FIFO_REJECT
    assert b.frame(5, 0.5, 0.001).disposition == sp.Disposition.DUPLICATE
    b.fw.advance(b.play_time(0))  # one played: room for one more
    assert b.frame(sp.FIFO_DEPTH, 0.5, b.play_time(0)).disposition == sp.Disposition.QUEUED
    assert b.fw.movie_counters["fifo_rejects"] == 2
    b2 = Bench()
    b2.start(0.0, n_frames=3)
    assert b2.frame(3, 0.0, 0.001).disposition == sp.Disposition.PAST_END


def test_underrun_holds_the_position_then_the_watchdog_rests_the_contactors():
    b = Bench(watchdog_s=0.05)
    b.start(0.0)
    for k in range(8):
        b.frame(k, 1.5 * (k + 1), 0.001)
    fw = b.fw
    last = b.play_time(7)
    fw.advance(last + 0.049)  # 34 ticks with nothing to play: held, still armed
    assert fw.armed and np.all(fw.last_command_um == 12.0) and fw.movie_running
    assert fw.movie_counters["underruns"] == 34 and fw.status & sp.Status.UNDERRUN
    assert np.allclose(fw.benders.deflection_um(), 12.0 * fw.benders.gain, atol=0.7)  # hysteresis band
    fw.advance(last + 0.051)
    assert not fw.armed and fw.watchdog_trips == 1 and not fw.movie_running
    assert fw.status & sp.Status.WATCHDOG_TRIPPED
    fw.advance(last + 0.051 + 0.04)  # 8 rest time constants
    assert np.all(np.abs(fw.benders.deflection_um()) < 1.0)
    assert b.frame(40, 0.0, last + 0.1).command == sp.Command.NAK


@pytest.mark.parametrize("stop", [sp.Command.REST, sp.Command.DISARM, sp.Command.STOP_MOVIE])
def test_stop_commands_are_not_queued_they_flush_and_act_at_once(stop):
    b = Bench()
    b.start(0.0, delay_s=0.001)
    for k in range(100):  # 143 ms of movie buffered
        b.frame(k, min(10.0 * (k + 1), 40.0), 0.0005)
    fw = b.fw
    t_stop = b.play_time(10) + 0.0003
    fw.advance(t_stop)
    assert len(fw.fifo) == 89
    b.send(stop, b"", t_stop)
    assert not fw.fifo and not fw.movie_running and not fw.status & sp.Status.MOVIE
    fw.advance(t_stop + 0.04)
    if stop == sp.Command.STOP_MOVIE:
        assert np.all(fw.last_command_um == 40.0) and fw.armed  # held; frames or REST must follow
    else:
        assert fw.benders.resting and np.all(np.abs(fw.benders.deflection_um()) < 1.0)
    fw.advance(t_stop + 0.2)
    assert len(fw.timed.tick_times) == 11  # no tick ran after the stop
    assert fw.benders.resting  # after a STOP_MOVIE the watchdog rests a display left alone
    nak = b.frame(150, 0.0, t_stop + 0.2)
    assert nak.command == sp.Command.NAK and sp.decode_nak(nak.payload)[0] in (sp.NakCode.NO_MOVIE,
                                                                               sp.NakCode.NOT_ARMED)
    counters = sp.MovieStatus.decode(b.send(sp.Command.READ_MOVIE, b"", t_stop + 0.2).payload)
    assert (counters.frames_queued, counters.frames_played) == (100, 11)  # still readable after the stop
    # the oldest tick report not carried yet (STOP_MOVIE's own reply carried tick 0's)
    assert counters.report.present and counters.report.tick == (1 if stop == sp.Command.STOP_MOVIE else 0)


def test_the_firmware_refuses_what_does_not_fit_the_movie_state():
    fw = StressFirmware()
    dec = sp.StreamDecoder()

    def nak_code(command, payload=b""):
        packet = dec.feed(fw.handle(sp.Packet(1, int(command), payload), 0.0))[0]
        return sp.decode_nak(packet.payload)[0] if packet.command == sp.Command.NAK else None

    start = sp.MovieStart(700_000, 0, 10_000).encode()
    assert nak_code(sp.Command.START_MOVIE, start) == sp.NakCode.NOT_ARMED
    fw.handle(sp.Packet(1, sp.Command.ARM, b""), 0.0)
    assert nak_code(sp.Command.TIMED_FRAME, bytes(104)) == sp.NakCode.NO_MOVIE
    assert nak_code(sp.Command.START_MOVIE, bytes(12)) == sp.NakCode.BAD_VALUE  # rate 0
    assert nak_code(sp.Command.START_MOVIE, bytes(5)) == sp.NakCode.BAD_LENGTH
    assert nak_code(sp.Command.START_MOVIE, start) is None
    assert nak_code(sp.Command.FRAME, bytes(100)) == sp.NakCode.MOVIE_RUNNING
    assert nak_code(sp.Command.TIMED_FRAME, bytes(100)) == sp.NakCode.BAD_LENGTH
    assert fw.timed.dispositions == [REFUSED]


# ---- the host's buffered loop -----------------------------------------------------------------------------------

def test_doctests_of_the_playback_module_pass():
    result = doctest.testmod(playback_module)
    assert result.failed == 0 and result.attempted > 0


def test_a_host_stall_shorter_than_the_lead_misses_nothing_where_immediate_misses(twin):
    movie = _wave(1400)  # 2 s
    results = {}
    for mode in ("immediate", "buffered"):
        clock = TickingClock()
        display, link = twin(clock)

        def stall(k, command, ack):
            if k in (300, 900):
                clock.advance(0.030)  # the callback sleeps 30 ms: a stalled host
            return None

        if mode == "immediate":
            report = stream_movie(display, movie, callback=stall, clock=clock.now, max_outstanding=100)
        else:
            report = stream_movie_buffered(display, movie, callback=stall, clock=clock.now)
        assert report.completed and report.rested
        results[mode] = report, link.firmware
    immediate, _ = results["immediate"]
    buffered, fw = results["buffered"]
    assert immediate.missed_deadlines >= 2 * 15  # each stall covers 21 frame periods
    assert isinstance(buffered, BufferedPlaybackReport)
    assert buffered.missed_deadlines == 0 and buffered.underruns == 0 and buffered.late_frames == 0
    rec = fw.timed.as_arrays()  # the firmware's own record agrees
    assert np.all(rec["timed_arrivals"] < rec["timed_play_times"]) and rec["tick_applied"].all()
    assert rec["tick_applied"].size == 1400 and fw.clamped_frames == 0
    assert 0.030 < buffered.min_arrival_margin_s < DEFAULT_LEAD_S  # the stall ate into the lead, no more
    periods = buffered.playout_periods_s
    assert periods.size == 1399 and np.all(np.abs(periods - PERIOD) < 1e-6)  # the display's timer, not the host
    assert buffered.acked.all() and buffered.reports_lost == 0  # every tick's measurement came back once
    assert buffered.position_rms_error_um().mean() == pytest.approx(
        immediate.position_rms_error_um().mean(), rel=0.1)


def test_a_stall_longer_than_the_lead_is_reported_as_missed_deadlines(twin):
    clock = TickingClock()
    display, link = twin(clock, watchdog_s=0.5)

    def stall(k, command, ack):
        if k == 200:
            clock.advance(0.120)  # 40 ms past the 80 ms lead
        return None

    report = stream_movie_buffered(display, _wave(700), callback=stall, clock=clock.now)
    assert report.completed
    fw = link.firmware
    assert report.underruns == fw.movie_counters["underruns"] > 0
    not_sent = int(np.sum(report.fates == FATE_NOT_SENT))
    assert report.missed_deadlines == report.late_frames + not_sent > 0
    rec = fw.timed.as_arrays()
    on_time = np.unique(rec["timed_ticks"][(rec["timed_arrivals"] < rec["timed_play_times"])
                                           & (rec["timed_dispositions"] == sp.Disposition.QUEUED)])
    assert 700 - on_time.size == report.missed_deadlines  # host report == the simulator's record
    assert np.nanmax(np.abs(report.playout_periods_s - PERIOD)) > PERIOD / 2  # the gap shows as jitter
    # a dropped frame can make the next one two slew steps away from what is held: the firmware clamps it;
    # whatever happens, the contactors never move more than the slew limit from one applied frame to the next
    assert fw.clamped_frames == 0 or report.late_frames > 0
    applied = np.array(fw.commands_um)
    assert np.all(np.abs(np.diff(applied, axis=0)) <= display.max_step_um)


def test_safety_stop_flushes_the_buffer_and_rests_at_once(twin, monkeypatch):
    clock = TickingClock()
    display, link = twin(clock)
    fw = link.firmware
    rest_at = []
    real_rest = fw._rest
    monkeypatch.setattr(fw, "_rest", lambda packet, t: (rest_at.append(t), real_rest(packet, t))[1])
    raised_at = []

    def ceiling(k, command, ack):
        if k == 400:
            raised_at.append(clock.now())
            raise SafetyStop("normal force 6.1 N above the 5 N ceiling")
        return command

    report = stream_movie_buffered(display, _wave(1400), callback=ceiling, clock=clock.now)
    assert report.outcome == "safety_stop" and "ceiling" in report.error and report.rested
    assert rest_at and rest_at[0] - raised_at[0] < 0.002  # REST on the wire at once, not after 80 ms of frames
    assert report.frames_flushed > 40  # what was buffered never played
    applied = np.asarray(fw.timed.tick_times)[np.asarray(fw.timed.tick_applied)]
    assert applied.max() < rest_at[0] and report.frames_played == len(fw.timed.tick_times) < 400
    clock.advance(0.04)
    link.advance()
    assert np.all(np.abs(fw.benders.deflection_um()) < 1.0)


@pytest.mark.parametrize("fault", ["vanish_after:200", "stall_after:200"])
def test_link_loss_mid_movie_keeps_the_report_and_the_display_rests(twin, fault):
    clock = TickingClock()
    display, link = twin(clock, faults=fault)
    report = stream_movie_buffered(display, _wave(1400), clock=clock.now)
    assert report.outcome == "link_failure" and not report.rested
    assert 120 <= report.frames_played < 1400 and report.acked[:100].all()  # what came back is kept
    assert report.commands_um.shape[0] == report.frames_played
    fw = link.firmware
    lost_at = fw.timed.arrivals[199]  # the 200th frame: the link died behind it
    assert clock.now() - lost_at < 0.5  # the host noticed within a bounded time
    clock.advance(DEFAULT_LEAD_S + fw.config.watchdog_s + 0.05)
    link.advance()
    applied = np.asarray(fw.timed.tick_times)[np.asarray(fw.timed.tick_applied)]
    assert applied.max() <= lost_at + DEFAULT_LEAD_S + PERIOD  # it played what it held, no more
    assert not fw.armed and fw.watchdog_trips == 1
    assert np.all(np.abs(fw.benders.deflection_um()) < 1.0)


anything = st.floats(allow_nan=False, allow_infinity=False, width=64)  # non-finite: refused (test_display_safety)


@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 25), st.just(10), st.just(10)), elements=anything),
       st.floats(0.5, 30), st.floats(-1e12, 1e12, allow_nan=False))
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_buffered_playback_never_puts_an_unsafe_frame_on_the_wire(movie, max_step_um, correction):
    clock = ManualClock()
    stress_links.register_url_handler()
    link = stress_links.make_link(clock=clock, seed=1)
    name = f"buffered{next(_names)}"
    display = StressDisplay(SerialTransport(stress_links.attach(name, link)), clock=clock.now, max_step_um=max_step_um)
    wire = sp.StreamDecoder()
    frames = []
    real_write = link.host_write

    def tap(data):
        frames.extend(sp.decode_timed_frame(p.payload) for p in wire.feed(data)
                      if p.command == sp.Command.TIMED_FRAME)
        real_write(data)

    link.host_write = tap
    try:
        report = stream_movie_buffered(display, movie, clock=clock.now, lead_s=0.01,
                                       callback=lambda k, c, a: c + correction if k % 3 else None)
    finally:
        display.close()
        stress_links.detach(name)
    assert report.completed
    ticks = [t for t, _ in frames]
    assert ticks == list(range(len(movie)))
    sent = np.array([f for _, f in frames])
    step = np.floor(max_step_um * 2) / 2
    assert np.all(np.abs(sent) <= 50)
    assert np.all(np.abs(np.diff(np.concatenate([np.zeros((1, 10, 10)), sent]), axis=0)) <= step)
    assert link.firmware.clamped_frames == 0


def test_callback_sees_measurements_of_played_ticks_and_its_corrections_play(twin):
    clock = TickingClock()
    display, _ = twin(clock)
    seen = []

    def offset(k, command, ack):
        seen.append((k, ack))
        return command + 2.0

    report = stream_movie_buffered(display, np.zeros((300, 10, 10)), callback=offset, clock=clock.now)
    assert report.completed and np.all(report.commands_um == 2.0)
    acks = [(k, a) for k, a in seen if a is not None]
    assert acks and all(isinstance(a, TimedFrameAck) for _, a in acks)
    lead_frames = int(DEFAULT_LEAD_S * 700)
    assert all(a.tick <= k - lead_frames + 1 for k, a in acks)  # measured ticks lag by the buffer
    ticks = [a.tick for a in display.acks]
    assert ticks == list(range(300))  # one measurement per tick, in order, pairing like immediate acks
    assert all(a.seq == a.tick & 0xFF for a in display.acks)
    late = list(display.acks)[50:]
    assert all(np.all(a.command_um == 2.0) and a.applied for a in late)
    assert np.allclose([a.measured_um.mean() for a in late], 2.0, atol=0.8)  # gain spread, hysteresis


@pytest.mark.parametrize("kwargs, name", [
    (dict(lead_s=0.001), "lead_s"), (dict(lead_s=0.5), "lead_s"), (dict(low_water_s=0.1), "low_water_s"),
    (dict(low_water_s=0.0), "low_water_s"), (dict(window=0), "window"), (dict(rate_hz=701), "rate_hz"),
    (dict(end_timeout_s=-1), "end_timeout_s"), (dict(settle_frames=-1), "settle_frames")])
def test_bad_buffered_options_are_refused_by_name(twin, kwargs, name):
    display, _ = twin()
    with pytest.raises(InvalidInputError, match=name):
        stream_movie_buffered(display, np.zeros((5, 10, 10)), **kwargs)


def test_a_display_without_a_fifo_is_refused_and_immediate_frames_wait_for_the_movie_to_end(twin):
    class NoFifo(TactileDisplay):
        pass

    NoFifo.__abstractmethods__ = frozenset()  # no device method is reached
    with pytest.raises(InvalidInputError, match="no timed playback"):
        stream_movie_buffered(NoFifo(), np.zeros((5, 10, 10)))
    display, _ = twin(ManualClock())
    display.arm()
    display.start_movie(rate_hz=700, n_frames=0, start_delay_s=0.05)
    with pytest.raises(DeviceError, match="timed movie is running"):
        display.submit_frame(np.zeros((10, 10)))
    display.submit_timed_frame(3, np.zeros((10, 10)))
    with pytest.raises(InvalidInputError, match="ticks increase"):
        display.submit_timed_frame(3, np.zeros((10, 10)))
    status = display.stop_movie()
    assert not status.running and status.frames_queued == 1 and status.fifo_fill == 0
    display.send_frame(np.ones((10, 10)))  # immediate again
