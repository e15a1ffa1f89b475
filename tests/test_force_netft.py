"""Net F/T driver against the simulator: injected loss, reordering, duplicates and garbage are counted,
a load that follows a function of time (the scene's normal force) is measured, no box -> named errors."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from skinstretch.drivers.forcesensor.netft import NetFTSensor
from skinstretch.drivers.errors import DeviceError, DeviceTimeoutError
from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.netft_box import NetFTFaults, NetFTSimulator, normal_force_wrench


def _sensor_for(sim, **kwargs) -> NetFTSensor:
    host, port = sim.address
    return NetFTSensor(host, port=port, **kwargs)


def _collect(sensor, sim, n_sent: int, timeout_s: float = 10.0):
    """Stream until the simulator has sent ``n_sent`` datagrams and they have been taken in (bounded wait)."""
    deadline = time.monotonic() + timeout_s
    while sim.stats.sent < n_sent and time.monotonic() < deadline:
        time.sleep(0.01)
    sensor._do_stop()
    time.sleep(0.2)  # let the last datagrams arrive before the receive thread stops
    sensor.stop()
    return sensor.drain()


def test_injected_faults_are_counted_exactly():
    faults = NetFTFaults(loss_probability=0.05, reorder_probability=0.05, duplicate_probability=0.03,
                         garble_probability=0.03)
    with NetFTSimulator(rate_hz=2000.0, faults=faults, seed=4) as sim, _sensor_for(sim) as sensor:
        sensor.start()
        block = _collect(sensor, sim, 600)
        s, injected = sensor.stats, sim.stats
    assert injected.lost > 0 and injected.reordered > 0 and injected.garbled > 0 and injected.duplicated > 0
    assert s.protocol_errors == injected.garbled
    assert s.duplicates == injected.duplicated
    # A datagram held back for reordering when the stream stopped is never sent: it shows as lost.
    assert injected.reordered - 1 <= s.reordered <= injected.reordered
    # Every sequence number between the first and the last one received is either received or counted lost ...
    assert len(block) + s.lost == int(block["sequence"].max() - block["sequence"].min()) + 1
    # ... and each of those lost was injected; a datagram lost or garbled after the last one received (the stop
    # raced it on a busy host) cannot be seen by the receiver at all.
    injected_gaps = injected.lost + injected.garbled + (injected.reordered - s.reordered)
    assert injected_gaps - 2 <= s.lost <= injected_gaps
    assert len(block) == s.received
    assert len(np.unique(block["sequence"])) == len(block)  # duplicates discarded


def test_load_follows_a_function_of_time():
    force = lambda t: 2.0 + 0.5 * np.sin(2 * np.pi * 3.0 * t)  # noqa: E731 - a scene-like normal force
    with NetFTSimulator(rate_hz=1000.0, wrench=normal_force_wrench(force), seed=0) as sim:
        with _sensor_for(sim) as sensor:
            sensor.start()
            block = _collect(sensor, sim, 300)
    # rdt_sequence k is the record due at (k - 1) / rate after the start request.
    t = (block["sequence"].astype(float) - 1) / 1000.0
    np.testing.assert_allclose(block["ft"][:, 2], force(t), atol=2e-6)
    assert np.ptp(block["ft"][:, 2]) > 0.9  # the sine is really there


def test_counts_per_unit_are_applied():
    with NetFTSimulator(rate_hz=500.0, wrench=lambda t: (1, 2, 3, 0.1, 0.2, 0.3),
                        counts_per_force=1_000_000, counts_per_torque=1000) as sim:
        with _sensor_for(sim, counts_per_force=1_000_000, counts_per_torque=1000) as sensor:
            sensor.start()
            sample = sensor.read(2.0)
            sensor.stop()
        with _sensor_for(sim, counts_per_force=2_000_000, counts_per_torque=1000) as wrong:
            wrong.start()
            half = wrong.read(2.0)
            wrong.stop()
    np.testing.assert_allclose(sample.ft, [1, 2, 3, 0.1, 0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(half.force_n, [0.5, 1.0, 1.5], atol=1e-6)


def test_buffered_datagrams_with_several_records_are_decoded():
    with NetFTSimulator(rate_hz=1000.0, records_per_packet=4) as sim:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.settimeout(2.0)
        try:
            sock.sendto(bytes.fromhex("1234 0003 00000002"), sim.address)  # buffered, two datagrams
            sizes = [len(sock.recv(4096)) for _ in range(2)]
        finally:
            sock.close()
    assert sizes == [4 * 36, 4 * 36]


def test_garbage_requests_do_not_crash_the_simulator():
    with NetFTSimulator(rate_hz=500.0) as sim:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            for junk in (b"", b"\x00", b"\x12\x34\x00\x07\x00\x00\x00\x00", b"x" * 100):
                sock.sendto(junk, sim.address)
        finally:
            sock.close()
        with _sensor_for(sim) as sensor:
            sensor.start()
            assert sensor.read(2.0).sequence == 1
            sensor.stop()
        assert sim.stats.bad_requests == 4 and sim.error is None


def test_no_box_is_a_named_error():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # nothing listens there now
    with NetFTSensor("127.0.0.1", port=port) as sensor:
        sensor.start()
        with pytest.raises((DeviceError, DeviceTimeoutError)):
            sensor.read(0.3)


def test_arguments_are_checked():
    with pytest.raises(InvalidInputError, match="host"):
        NetFTSensor("")
    with pytest.raises(InvalidInputError, match="port"):
        NetFTSensor("127.0.0.1", port=70000)
    with pytest.raises(InvalidInputError, match="counts_per_force"):
        NetFTSensor("127.0.0.1", counts_per_force=0)
    with pytest.raises(InvalidInputError, match="rate_hz"):
        NetFTSimulator(rate_hz=8000)
    with pytest.raises(InvalidInputError, match="loss_probability"):
        NetFTFaults(loss_probability=1.0)


def test_from_box_reads_the_calibration_over_http():
    import http.server
    import threading

    xml = b"<netft><cfgcpf>2000000</cfgcpf><cfgcpt>4000</cfgcpt></netft>"

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - http.server's naming
            body = xml if self.path == "/netftapi2.xml" else b""
            self.send_response(200 if body else 404)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    server = http.server.HTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        with NetFTSimulator(rate_hz=500.0, wrench=lambda t: (1, 0, 0, 0.5, 0, 0),
                            counts_per_force=2_000_000, counts_per_torque=4000) as sim:
            host, port = sim.address
            with NetFTSensor.from_box(host, port=port, http_port=server.server_address[1]) as sensor:
                sensor.start()
                sample = sensor.read(2.0)
                sensor.stop()
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=5)
    np.testing.assert_allclose(sample.ft, [1, 0, 0, 0.5, 0, 0], atol=1e-6)
    with pytest.raises(DeviceError, match="calibration cannot be read"):
        NetFTSensor.from_box("127.0.0.1", http_port=port, timeout_s=0.5)  # a UDP port: nothing speaks HTTP
