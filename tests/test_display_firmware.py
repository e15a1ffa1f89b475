"""The firmware simulator's physics and pacing: lag, hysteresis, finger load, rest ramp, line-rate timing."""

import numpy as np
import pytest

from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators import stress_links
from skinstretch.simulators.stress_benders import BenderArray, BenderParameters
from skinstretch.simulators.stress_firmware import StressFirmware
from skinstretch.simulators.stress_wire import LinkFaults, ManualClock, PacedLink

QUIET = BenderParameters(gain_spread=0.0, offset_spread_um=0.0, noise_um=0.0)


def test_first_order_lag_reaches_63_percent_after_one_time_constant():
    b = BenderArray(params=BenderParameters(hysteresis_um=0.0, gain_spread=0, offset_spread_um=0, noise_um=0))
    b.resting = False
    b.command(np.full((10, 10), 10.0))
    b.advance(b.params.tau_s)
    assert np.allclose(b.deflection_um(), 10 * (1 - np.exp(-1)), atol=1e-9)
    b.advance(1.0)
    assert np.allclose(b.deflection_um(), 10.0)


def test_play_hysteresis_leaves_a_band_of_twice_its_half_width():
    b = BenderArray(params=QUIET)
    h = QUIET.hysteresis_um
    b.command(np.full((10, 10), 20.0))
    b.advance(0.1)
    assert np.allclose(b.deflection_um(), 20.0 - h)
    b.command(np.full((10, 10), 10.0))
    b.advance(0.2)
    coming_down = b.deflection_um().copy()
    b.command(np.zeros((10, 10)))
    b.advance(0.3)
    b.command(np.full((10, 10), 10.0))
    b.advance(0.4)
    assert np.allclose(coming_down - b.deflection_um(), 2 * h)


def test_finger_load_reduces_deflection_like_springs_in_series():
    b = BenderArray(params=QUIET)
    load = np.zeros((10, 10))
    load[2, 3] = QUIET.bender_stiffness_n_per_mm  # as stiff as the bender: half the deflection
    b.set_load(load)
    b.command(np.full((10, 10), 20.6))
    b.advance(0.1)
    d = b.deflection_um()
    assert d[2, 3] == pytest.approx(d[0, 0] / 2)
    with pytest.raises(InvalidInputError):
        b.set_load(-1.0)


def test_rest_ramp_is_soft_then_complete():
    b = BenderArray(params=QUIET)
    b.command(np.full((10, 10), 40.0))
    b.advance(0.1)
    b.rest()
    b.advance(0.1 + 0.001)
    assert np.all(b.deflection_um() > 20)  # 1 ms into a 5 ms ramp: no snap back
    b.advance(0.2)
    assert np.all(np.abs(b.deflection_um()) <= QUIET.hysteresis_um + 1e-6)


def test_frames_arrive_at_the_line_rate_and_replies_leave_at_it():
    clock = ManualClock(10.0)
    link = PacedLink.uart(StressFirmware(t0=10.0), clock=clock, baud=1_000_000, processing_s=0.0)
    frame = sp.encode_packet(seq=1, command=sp.Command.IDENTIFY)
    link.host_write(frame)
    link.advance()
    assert link.host_read(100) == b""  # nothing can have come back yet
    byte = 10 / 1_000_000
    clock.advance(len(frame) * byte)
    link.advance()
    assert link.host_read(100) == b""  # the request is in; the reply is on its way
    nxt = link.next_event()
    reply_len = sp.OVERHEAD + 6 + len(b"stresssim 1.0")
    assert nxt == pytest.approx(10.0 + (len(frame) + reply_len) * byte)
    clock.advance(nxt - clock.now())
    packets = sp.StreamDecoder().feed(link.host_read(1000))
    assert packets and sp.Identity.decode(packets[0].payload).rows == 10


def test_firmware_records_frame_receive_times_on_the_wire_clock():
    clock = ManualClock()
    link = PacedLink.uart(StressFirmware(), clock=clock, baud=2_000_000)
    fw = link.firmware
    link.host_write(sp.encode_packet(seq=1, command=sp.Command.ARM))
    for k in range(5):
        clock.advance(1 / 700)
        link.host_write(sp.encode_packet(seq=2 + k, command=sp.Command.FRAME, payload=bytes(100)))
    clock.advance(0.01)
    link.advance()
    times = np.array(fw.frame_times)
    assert np.allclose(np.diff(times), 1 / 700) and times[0] == pytest.approx(1 / 700 + 107 * 10 / 2e6)
    assert fw.frames_received == 5 and fw.sequence_gaps == 0


def test_firmware_guards_range_and_slew_itself():
    fw = StressFirmware()
    fw.handle(sp.Packet(1, sp.Command.ARM, b""), 0.0)
    payload = np.full(100, 127, dtype=np.int8).tobytes()  # 63.5 um from rest: far too far
    reply = fw.handle(sp.Packet(2, sp.Command.FRAME, payload), 0.001)
    status, _ = sp.decode_frame_ack(sp.StreamDecoder().feed(reply)[0].payload)
    assert status & sp.Status.CLAMPED and np.all(fw.last_command_um == sp.DEFAULT_MAX_STEP_UM)
    nak = sp.StreamDecoder().feed(fw.handle(sp.Packet(3, 0x33, b""), 0.002))[0]
    assert nak.command == sp.Command.NAK and sp.decode_nak(nak.payload)[0] == sp.NakCode.UNKNOWN_COMMAND


def test_fault_spec_parsing():
    f = LinkFaults.parse("drop:0.01, corrupt:0.5,stall_after:3,vanish_after:9")
    assert (f.drop_rate, f.corrupt_rate, f.stall_after_frames, f.vanish_after_frames) == (0.01, 0.5, 3, 9)
    with pytest.raises(InvalidInputError):
        LinkFaults(drop_rate=2.0)
    with pytest.raises(InvalidInputError):
        stress_links.make_link(baud=12)
