"""One conformance suite for the STReSS driver, run over every transport to the firmware simulator:
the pyserial ``stresssim://`` URL, a real pty pair served by a thread, and the pyusb bulk backend."""

import itertools
import time
from dataclasses import dataclass

import numpy as np
import pytest

from skinstretch.drivers.errors import InvalidTargetError
from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.display.stress import StressDisplay
from skinstretch.drivers.display.transports import SerialTransport, UsbTransport
from skinstretch.drivers.errors import DeviceError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators import stress_links
from skinstretch.simulators.stress_firmware import StressFirmware
from skinstretch.simulators.stress_wire import ManualClock, PacedLink

_names = itertools.count()
# long enough that a test process starved by a busy CI machine does not trip it by accident
WATCHDOG_S = 0.3


@dataclass
class Rig:
    display: StressDisplay
    link: PacedLink
    wait: object  # wait(seconds): lets simulated (or real) time pass

    @property
    def firmware(self) -> StressFirmware:
        return self.link.firmware


@pytest.fixture(params=["url", "pty", "usb"])
def rig(request):
    kind = request.param
    stress_links.register_url_handler()
    if kind == "url":
        clock = ManualClock()
        link = stress_links.make_link(clock=clock, seed=3)
        name = f"conformance{next(_names)}"
        display = StressDisplay(SerialTransport(stress_links.attach(name, link)), clock=clock.now, watchdog_s=WATCHDOG_S)
        yield Rig(display, link, clock.advance)
        display.close()
        stress_links.detach(name)
    elif kind == "pty":
        link = stress_links.make_link(seed=3)
        server = stress_links.start_pty_firmware(link)
        display = StressDisplay(SerialTransport(server.port), reply_timeout_s=0.5, watchdog_s=WATCHDOG_S)
        yield Rig(display, link, time.sleep)
        display.close()
        server.stop()
        assert server.error is None
    else:
        # real time: the transport's reader thread keeps a bulk read pending, as libusb would
        link = PacedLink.usb_high_speed(StressFirmware(seed=3, t0=time.perf_counter()), clock=stress_links.RealClock())
        display = StressDisplay(UsbTransport(backend=stress_links.StressUsbBackend(link)), reply_timeout_s=0.5,
                                watchdog_s=WATCHDOG_S)
        yield Rig(display, link, time.sleep)
        display.close()


def test_identify(rig):
    info = rig.display.identify()
    assert (info.rows, info.cols, info.range_um, info.max_rate_hz) == (10, 10, 50.0, 700)
    assert info.firmware.startswith("stresssim") and info.protocol_version == sp.PROTOCOL_VERSION


def test_frames_are_acked_with_measured_positions_that_follow_the_command(rig):
    d = rig.display
    d.zero()
    d.arm()
    target = np.full((10, 10), 8.0)
    for _ in range(4):
        ack = d.send_frame(target)
        rig.wait(0.003)
    ack = d.send_frame(target)
    assert ack.status & sp.Status.ARMED
    assert np.array_equal(ack.command_um, target)
    # gain spread 3 %, hysteresis 0.6 um, quantisation 0.25 um
    assert np.all(np.abs(ack.measured_um - target) < 2.0)
    assert len(d.acks) == 5 and [a.seq for a in d.acks] == sorted({a.seq for a in d.acks})


def test_driver_limits_slew_and_firmware_never_has_to(rig):
    d = rig.display
    d.arm()
    ack = d.send_frame(np.full((10, 10), 1e6))
    assert np.all(ack.command_um == d.max_step_um)
    with pytest.raises(InvalidTargetError, match=r"contactor \(0, 0\)"):  # refused, never guessed
        d.send_frame(np.full((10, 10), np.nan))
    assert np.all(d.last_command_um == d.max_step_um)
    rig.link.advance()
    assert rig.firmware.clamped_frames == 0
    assert np.all(rig.firmware.last_command_um == d.max_step_um)


def test_read_status_counts_frames_and_clears_sticky_bits(rig):
    d = rig.display
    d.arm()
    for k in range(3):
        d.send_frame(np.full((10, 10), float(k)))
    report = d.read_status()
    assert report.frames_received == 3 and report.watchdog_trips == 0 and report.crc_errors == 0
    assert report.status & sp.Status.ARMED
    assert d.measured_positions_um().shape == (10, 10)


def test_zero_needs_a_disarmed_display_and_removes_sensor_offsets(rig):
    d = rig.display
    rig.wait(0.05)
    before = d.read_status().positions_um
    d.zero()
    after = d.read_status().positions_um
    assert np.abs(before).max() > 0.5  # the seeded sensor offsets are visible before zeroing
    assert np.abs(after).max() <= 0.5
    assert d.read_status().status & sp.Status.ZEROED
    d.arm()
    with pytest.raises(DeviceError, match="disarmed"):
        d.zero()


def test_frames_before_arm_are_refused(rig):
    with pytest.raises(DeviceError, match="not armed"):
        rig.display.send_frame(np.zeros((10, 10)))


def test_rest_brings_every_contactor_back(rig):
    d = rig.display
    d.zero()
    d.arm()
    for k in range(1, 5):
        d.send_frame(np.full((10, 10), 10.0 * k))
        rig.wait(0.002)
    d.rest()
    rig.wait(0.06)  # 12 rest time constants
    report = d.read_status()
    assert report.status & sp.Status.RESTING
    assert np.all(np.abs(report.positions_um) <= 1.0)  # hysteresis band + quantisation
    assert np.all(d.last_command_um == 0)


def test_watchdog_sends_contactors_to_rest_and_disarms(rig):
    d = rig.display
    d.zero()
    d.arm()
    for _ in range(4):
        d.send_frame(np.full((10, 10), 20.0))
    rig.wait(WATCHDOG_S + 0.1)  # watchdog + rest ramp
    report = d.read_status()
    assert report.watchdog_trips == 1
    assert report.status & sp.Status.WATCHDOG_TRIPPED and not report.status & sp.Status.ARMED
    assert np.all(np.abs(report.positions_um) <= 1.0)
    with pytest.raises(DeviceError, match="NOT_ARMED"):
        d.send_frame(np.zeros((10, 10)))


def test_bad_arguments_are_refused_by_name(rig):
    d = rig.display
    d.arm()
    with pytest.raises(InvalidInputError, match="requested_um"):
        d.send_frame(np.zeros((3, 3)))
    with pytest.raises(InvalidInputError, match="timeout_s"):
        d.collect_acks(timeout_s=-1)


def test_ack_history_is_bounded_and_counts_every_ack():
    from skinstretch.drivers.display.base import FrameAck, TactileDisplay
    from skinstretch.drivers.display.stress_protocol import Status

    class _AckSource(TactileDisplay):
        """Only the base class's ack bookkeeping is exercised: each collect returns 1000 new acks."""

        _n = 0

        def _do_collect_acks(self, *, wait_for, timeout_s):
            got = [FrameAck(self._n + i, Status.ARMED, np.zeros((10, 10)), np.zeros((10, 10)), 0.0, 0.0)
                   for i in range(1000)]
            self._n += 1000
            return got

    _AckSource.__abstractmethods__ = frozenset()  # the device methods are never called here
    d = _AckSource()
    for _ in range(10):
        d.collect_acks()
    assert d.acks_received == 10_000
    assert len(d.acks) == TactileDisplay.ACK_HISTORY
    assert d.acks[-1].seq == 9_999 and d.acks[0].seq == 10_000 - TactileDisplay.ACK_HISTORY


def test_timed_frames_play_from_the_fifo_at_their_ticks(rig):
    d = rig.display
    assert d.supports_timed_playback
    d.zero()
    d.arm()
    # 250 ms between the start and tick 0: a test process starved by a busy machine still gets 20 frames across
    status = d.start_movie(rate_hz=700, n_frames=20, start_delay_s=0.25)
    assert status.running and status.fifo_depth == sp.FIFO_DEPTH and status.time_us == -250_000
    for k in range(20):
        d.submit_timed_frame(k, np.full((10, 10), 0.5 * k))
    rig.wait(0.3)
    d.collect_acks(timeout_s=0.05)
    receipts = d.take_receipts()
    assert [r.tick for r in receipts] == list(range(20))
    assert all(r.disposition == sp.Disposition.QUEUED and r.rx_time_s < -0.1 for r in receipts)
    final = d.read_movie_status()
    assert (final.frames_played, final.late_frames, final.underruns, final.next_tick) == (20, 0, 0, 20)
    assert not final.running
    while final.report.present:  # the tick reports no frame reply was left to carry
        final = d.read_movie_status()
    ticks = [a.tick for a in d.collect_acks()]
    assert ticks == sorted(ticks) and ticks[-1] == 19 and len(ticks) >= 20 - 1
    d.rest()
    rig.link.advance()
    assert rig.firmware.clamped_frames == 0 and rig.firmware.benders.resting
    assert np.all(rig.firmware.last_command_um == 0)
