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
from skinstretch.drivers.display.safety import limit_command, rest_ramp
from skinstretch.drivers.display.stress import StressDisplay
from skinstretch.drivers.display.transports import Transport
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.stress_firmware import StressFirmware

anything = st.floats(allow_nan=True, allow_infinity=True, width=64)
frames = hnp.arrays(np.float64, (10, 10), elements=anything)
safe_previous = hnp.arrays(np.float64, (10, 10), elements=st.integers(-100, 100).map(lambda c: c * 0.5))


def test_doctests_of_the_codec_and_limits_pass():
    for module in (safety_module, protocol_module):
        result = doctest.testmod(module)
        assert result.failed == 0 and result.attempted > 0


@given(frames, safe_previous, st.floats(0.5, 50), st.floats(0.5, 100))
@settings(max_examples=150, deadline=None)
def test_limited_command_is_in_range_within_slew_and_on_the_grid(request, previous, range_um, max_step_um):
    previous = np.clip(previous, -np.floor(range_um * 2) / 2, np.floor(range_um * 2) / 2)
    out = limit_command(request, previous, range_um=range_um, max_step_um=max_step_um)
    c = out.command_um
    assert c.shape == (10, 10) and np.all(np.isfinite(c))
    assert np.all(np.abs(c) <= range_um + 1e-12)
    assert np.all(np.abs(c - previous) <= max_step_um + 1e-12)
    assert np.array_equal(c * 2, np.rint(c * 2))
    held = ~np.isfinite(request)
    assert np.array_equal(c[held], previous[held]) and out.non_finite == held.sum()


def test_safe_request_passes_unchanged_and_flags_stay_clear():
    previous = np.zeros((10, 10))
    request = np.full((10, 10), 4.5)
    out = limit_command(request, previous, max_step_um=10)
    assert np.array_equal(out.command_um, request) and not out.modified


@pytest.mark.parametrize("request_um", ["abc", np.zeros((10, 9)), [[1, 2]], None])
def test_garbage_requests_are_refused_by_name(request_um):
    with pytest.raises(InvalidInputError, match="requested_um"):
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
