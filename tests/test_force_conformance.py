"""One conformance suite for every ForceSensor available here: the Net F/T driver against its simulator, in
the same process and as a separate program (``python -m skinstretch.simulators.netft_box``)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from skinstretch.drivers.forcesensor.base import FORCE_SAMPLE_DTYPE, ForceSample, ForceSensor
from skinstretch.drivers.forcesensor.netft import NetFTSensor
from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.netft_box import NetFTBoxProcess, NetFTSimulator, normal_force_wrench
from tests.helpers import wait_until

FORCE_N = 1.5


@pytest.fixture(params=["netft-simulator", "netft-simulator-process"])
def sensor(request) -> ForceSensor:
    if request.param == "netft-simulator":
        sim = NetFTSimulator(rate_hz=500.0, wrench=normal_force_wrench(lambda t: FORCE_N)).start()
        host, port = sim.address
        yield NetFTSensor(host, port=port)
        sim.close()
    else:
        with NetFTBoxProcess(rate_hz=500.0, force_n=FORCE_N) as (host, port):  # bounded by the test timeout
            yield NetFTSensor(host, port=port)


def test_streams_samples_in_newtons(sensor):
    with sensor:
        sensor.start()
        samples = [sensor.read(2.0) for _ in range(50)]
        sensor.stop()
        stats = sensor.stats
    assert all(isinstance(s, ForceSample) and s.ft.shape == (6,) for s in samples)
    np.testing.assert_allclose([s.force_n[2] for s in samples], FORCE_N, atol=1e-6)
    np.testing.assert_allclose([s.torque_nm for s in samples], 0.0, atol=1e-6)
    seq = np.array([s.sequence for s in samples])
    assert np.all(np.diff(seq) == 1)
    assert all(s.status == 0 for s in samples)
    assert stats.received >= 50 and stats.lost == 0 and stats.protocol_errors == 0


def test_drain_returns_a_structured_array(sensor):
    with sensor:
        sensor.start()
        sensor.read(2.0)
        wait_until(lambda: sensor.stats.received >= 20)
        sensor.stop()
        block = sensor.drain()
    assert block.dtype == FORCE_SAMPLE_DTYPE and len(block) >= 19
    assert np.all(np.diff(block["sequence"]) == 1) and np.all(np.diff(block["t"]) >= 0)
    np.testing.assert_allclose(block["ft"][:, 2], FORCE_N, atol=1e-6)


def test_bias_zeroes_the_present_load(sensor):
    with sensor:
        sensor.start()
        sensor.read(2.0)
        sensor.bias()
        deadline = time.monotonic() + 5.0
        while True:  # bounded: the bias takes effect within a few samples
            sample = sensor.read(2.0)
            if abs(sample.force_n[2]) < 1e-6 or time.monotonic() > deadline:
                break
        sensor.stop()
    assert abs(sample.force_n[2]) < 1e-6


def test_silence_after_stop_and_bad_use(sensor):
    with pytest.raises(DeviceError, match="not open"):
        sensor.bias()
    with sensor:
        with pytest.raises(DeviceError, match="not streaming"):
            sensor.read(0.05)
        sensor.start()
        sensor.read(2.0)
        with pytest.raises(InvalidInputError, match="timeout_s"):
            sensor.read(-1)
        sensor.stop()
        sensor.drain()
        with pytest.raises(DeviceError):
            sensor.read(0.05)
        sensor.start()  # restarts cleanly, counters reset
        assert sensor.read(2.0).sequence >= 1
        assert sensor.stats.lost == 0


def test_timeout_when_the_box_goes_quiet(sensor):
    with sensor:
        sensor.start()
        sensor.read(2.0)
        sensor._do_stop()  # the box stops streaming while the driver still expects data
        time.sleep(0.1)
        sensor.drain()
        with pytest.raises(DeviceTimeoutError, match="no sample within"):
            sensor.read(0.1)
