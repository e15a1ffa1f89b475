"""No out-of-range or over-slew command ever leaves the driver, whatever the caller asks."""

import doctest

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

import skinstretch.drivers.display.safety as safety_module
import skinstretch.drivers.display.stress_protocol as protocol_module
from skinstretch.drivers.display import stress_protocol as sp
from skinstretch.drivers.display.safety import check_movie, limit_command, rest_ramp
from skinstretch.drivers.errors import InvalidTargetError
from skinstretch.drivers.display.base import PreparedFrame
from skinstretch.drivers.display.stress import StressDisplay
from skinstretch.drivers.display.transports import Transport
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.stress_firmware import StressFirmware

anything = st.floats(allow_nan=False, allow_infinity=False, width=64)  # any finite double, huge ones included
frames = hnp.arrays(np.float64, (10, 10), elements=anything)
safe_previous = hnp.arrays(np.float64, (10, 10), elements=st.integers(-100, 100).map(lambda c: c * 0.5))


def test_doctests_of_the_codec_and_limits_pass():
    for module in (safety_module, protocol_module):
        result = doctest.testmod(module)
        assert result.failed == 0 and result.attempted > 0


@given(frames, safe_previous, st.floats(0.5, 50), st.floats(0.5, 100))
@settings(max_examples=200, deadline=None)
def test_limited_command_is_safe_and_never_silently_altered(request, previous, range_um, max_step_um):
    previous = np.clip(previous, -np.floor(range_um * 2) / 2, np.floor(range_um * 2) / 2)
    out = limit_command(request, previous, range_um=range_um, max_step_um=max_step_um)
    c = out.command_um
    assert c.shape == (10, 10) and np.all(np.isfinite(c))
    assert np.all(np.abs(c) <= range_um + 1e-12)
    assert np.all(np.abs(c - previous) <= max_step_um + 1e-12)
    assert np.array_equal(c * 2, np.rint(c * 2))
    # never silently altered: a contactor not marked clamped got its request, up to the 0.5 um grid's rounding
    free = ~out.clamped
    assert np.all(np.abs(c[free] - request[free]) <= 0.25)
    assert out.modified == bool(out.clamped.any())
    # and a clamped one went as far towards its request as the limits allow
    r_um, s_um = np.floor(range_um * 2) / 2, np.floor(max_step_um * 2) / 2
    reach = np.clip(np.clip(np.rint(np.clip(request, -r_um, r_um) * 2) / 2, previous - s_um, previous + s_um),
                    -r_um, r_um)
    assert np.array_equal(c, reach)


@pytest.mark.parametrize("bad, where", [(np.nan, (3, 4)), (np.inf, (0, 9)), (-np.inf, (9, 0))])
def test_non_finite_targets_are_refused_naming_the_contactor(bad, where):
    request = np.zeros((10, 10))
    request[where] = bad
    with pytest.raises(InvalidTargetError, match=rf"contactor \({where[0]}, {where[1]}\)") as info:
        limit_command(request, np.zeros((10, 10)))
    assert info.value.contactor == where and isinstance(info.value, InvalidInputError)


def test_complex_bool_and_object_targets_are_refused():
    request = np.zeros((10, 10), complex)
    request[2, 5] = 1 + 2j
    with pytest.raises(InvalidTargetError, match=r"complex.*contactor \(2, 5\)") as info:
        limit_command(request, np.zeros((10, 10)))
    assert info.value.contactor == (2, 5)
    with pytest.raises(InvalidTargetError, match="complex"):  # even with no imaginary part: a bug upstream
        limit_command(np.zeros((10, 10), complex), np.zeros((10, 10)))
    for garbage in (np.zeros((10, 10), bool), np.full((10, 10), "1.0"), np.full((10, 10), None)):
        with pytest.raises(InvalidTargetError, match="real numbers"):
            limit_command(garbage, np.zeros((10, 10)))


def test_movies_are_checked_whole_naming_frame_and_contactor():
    movie = np.zeros((7, 10, 10))
    movie[4, 1, 2] = np.nan
    with pytest.raises(InvalidTargetError, match=r"frame 4, contactor \(1, 2\)"):
        check_movie(movie)
    with pytest.raises(InvalidTargetError, match="shape"):
        check_movie(np.zeros((0, 10, 10)))
    assert check_movie(np.ones((2, 10, 10), np.int16)).dtype == np.float64


def test_safe_request_passes_unchanged_and_flags_stay_clear():
    previous = np.zeros((10, 10))
    request = np.full((10, 10), 4.5)
    out = limit_command(request, previous, max_step_um=10)
    assert np.array_equal(out.command_um, request) and not out.modified and not out.clamped.any()


@pytest.mark.parametrize("request_um", ["abc", np.zeros((10, 9)), [[1, 2]], None, [[1, 2], [3]]])
def test_garbage_requests_are_refused_by_name(request_um):
    with pytest.raises(InvalidTargetError, match="requested_um"):
        limit_command(request_um, np.zeros((10, 10)))


def test_bad_limits_are_refused():
    with pytest.raises(InvalidInputError, match="range_um"):
        limit_command(np.zeros((10, 10)), np.zeros((10, 10)), range_um=80)
    with pytest.raises(InvalidInputError, match="max_step_um"):
        limit_command(np.zeros((10, 10)), np.zeros((10, 10)), max_step_um=float("nan"))


def test_rest_ramp_reaches_zero_within_slew():
    frames_ = rest_ramp(np.full((10, 10), 50.0), max_step_um=10)
    assert len(frames_) == 5 and np.all(frames_[-1] == 0)
    steps = np.abs(np.diff(np.concatenate([[np.full((10, 10), 50.0)], frames_]), axis=0))
    assert steps.max() <= 10


class FirmwareWire(Transport):
    """A byte-level fake port: every byte the driver writes goes through the firmware simulator's decoder."""

    def __init__(self):
        self.firmware = StressFirmware(seed=1)
        self.decoder = sp.StreamDecoder()
        self.replies = bytearray()
        self.frames = []
        self.t = 0.0

    @property
    def description(self):
        return "firmware wire"

    def write(self, data):
        for packet in self.decoder.feed(data):
            self.t += 1 / 700
            if packet.command == sp.Command.FRAME:
                self.frames.append(sp.decode_positions(packet.payload))
            self.replies += self.firmware.handle(packet, self.t)

    def read(self, max_bytes, *, timeout_s):
        out = bytes(self.replies[:max_bytes])
        del self.replies[:max_bytes]
        return out

    def close(self):
        pass


@given(st.lists(frames, min_size=1, max_size=12), st.floats(0.5, 30))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_no_unsafe_frame_ever_reaches_the_wire(requests, max_step_um):
    wire = FirmwareWire()
    display = StressDisplay(wire, max_step_um=max_step_um, clock=lambda: wire.t)
    display.arm()
    for request in requests:
        display.send_frame(request)
    display.rest()
    display.send_frame(np.full((10, 10), -1e9))
    step = np.floor(max_step_um * 2) / 2
    sent = np.array(wire.frames)
    assert np.all(np.abs(sent) <= 50)
    previous = np.concatenate([[np.zeros((10, 10))], sent[:-2]])  # the last frame follows a rest (reference 0)
    assert np.all(np.abs(sent[:-1] - previous) <= step)
    assert np.all(np.abs(sent[-1]) <= step)
    assert wire.firmware.clamped_frames == 0  # the firmware's own guard never had to act


def test_a_stale_prepared_frame_is_limited_again_before_it_leaves():
    wire = FirmwareWire()
    display = StressDisplay(wire, max_step_um=5.0, clock=lambda: wire.t)
    display.arm()
    early = display.prepare_frame(np.full((10, 10), 5.0))  # limited against 0: a 5 um step
    display.send_frame(np.full((10, 10), -5.0))
    display.send_prepared(early)  # against -5 it would be a 10 um step
    assert np.all(wire.frames[-1] == 0.0)
    assert wire.firmware.clamped_frames == 0


def test_a_prepared_frame_whose_array_disagrees_with_its_bytes_is_refused_and_not_believed():
    wire = FirmwareWire()
    display = StressDisplay(wire, clock=lambda: wire.t)
    display.arm()
    display.send_frame(np.full((10, 10), 4.0))
    good = display.prepare_frame(np.full((10, 10), 8.0))
    with pytest.raises(ValueError):
        good.command_um[0, 0] = 1.0  # read-only: nobody changes a command behind its bytes
    forged = PreparedFrame(np.full((10, 10), 6.0), good.wire, good.epoch)  # claims 6 um, its bytes say 8 um
    with pytest.raises(InvalidTargetError, match=r"disagree at contactor \(0, 0\)"):
        display.send_prepared(forged)
    assert np.all(display.last_command_um == 4.0) and len(wire.frames) == 1  # nothing sent, nothing believed
    unsafe = PreparedFrame(np.full((10, 10), 40.0), sp.encode_positions(np.full((10, 10), 40.0)), good.epoch)
    with pytest.raises(InvalidTargetError, match="slew"):  # bytes and array agree, but the step is 36 um
        display.send_prepared(unsafe)
    with pytest.raises(InvalidTargetError, match="wire"):
        display.send_prepared(PreparedFrame(good.command_um, b"\x00" * 7, good.epoch))
    assert len(wire.frames) == 1
    display.send_prepared(good)
    assert np.all(display.last_command_um == 8.0) and np.all(wire.frames[-1] == 8.0)
    display.start_movie(rate_hz=100.0, n_frames=5, start_delay_s=0.05)
    with pytest.raises(InvalidTargetError, match="disagree"):
        display.send_timed(0, PreparedFrame(np.full((10, 10), 9.0), display.prepare_frame(np.full((10, 10), 10.0)).wire,
                                            display._epoch))
    assert np.all(display.last_command_um == 8.0)
