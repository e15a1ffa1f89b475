"""Bench section ``force``: ATI Net F/T RDT streaming on loopback against the simulated box.

The simulator runs as a separate program (``python -m skinstretch.simulators.netft_box``), as a real box would be a separate
machine, so the CPU column is the driver's alone. Speed: achieved sample rate and driver CPU use. Error: samples
lost (sequence gaps; the target is zero at 1 kHz), reordered, garbled, and the force error against the load the
box applies (constant normal force here; the counts quantise it to 1e-6 N).
A last row runs the simulator in-process with a time-varying load and injected faults, to show they are counted.
"""

from __future__ import annotations

import time

import numpy as np

from skinstretch.drivers.forcesensor.netft import NetFTSensor
from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.simulators.netft_box import NetFTBoxProcess, NetFTFaults, NetFTSimulator, normal_force_wrench

SECTION = "force"
DESCRIPTION = "Net F/T RDT over loopback UDP: 1 kHz and 7 kHz, lost/reordered samples, force error, driver CPU"

COLUMNS = ["box", "rate Hz", "seconds", "samples", "expected", "achieved Hz", "lost", "reordered",
           "protocol errors", "max |F error| N", "CPU %"]
FORCE_N = 2.5


def _udp_receive_buffer_errors() -> int | None:
    """The kernel's count of UDP datagrams dropped because a socket's receive buffer was full (all sockets)."""
    try:
        lines = [line.split() for line in open("/proc/net/snmp").read().splitlines() if line.startswith("Udp:")]
        return int(dict(zip(lines[0], lines[1]))["RcvbufErrors"])
    except (OSError, IndexError, KeyError, ValueError):
        return None


def _stream(sensor: NetFTSensor, seconds: float, truth) -> tuple[list, float]:
    wall0, cpu0 = time.perf_counter(), time.process_time()
    blocks = []
    sensor.start()
    try:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            time.sleep(0.02)  # a recorder drains in blocks, as it would write them to the session file
            blocks.append(sensor.drain())
    finally:
        sensor.stop()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    blocks.append(sensor.drain())
    block = np.concatenate(blocks)
    s = sensor.stats
    t = block["t"]
    achieved = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else float("nan")
    err = float(np.max(np.abs(block["ft"] - truth(block["sequence"])))) if len(block) else float("nan")
    return [len(block), None, float(achieved), s.lost, s.reordered, s.protocol_errors, err, 100.0 * cpu / wall], wall


def _subprocess_row(rate_hz: float, seconds: float) -> list:
    box = NetFTBoxProcess(rate_hz=rate_hz, force_n=FORCE_N)
    constant = np.array([0, 0, FORCE_N, 0, 0, 0], dtype=float)
    with box as (host, port), NetFTSensor(host, port=port) as sensor:
        values, _ = _stream(sensor, seconds, lambda seq: constant)
    values[1] = int(round(seconds * rate_hz))
    lost = box.stats.lost if box.stats is not None else "?"
    return [f"simulator process (send failures {lost})", rate_hz, seconds, *values]


def _faulty_row(seconds: float) -> list:
    rate_hz = 1000.0
    force = lambda t: 2.0 + 0.5 * np.sin(2 * np.pi * 2.0 * t)  # noqa: E731 - a pressing-like normal force
    faults = NetFTFaults(loss_probability=0.01, reorder_probability=0.01, garble_probability=0.005)
    with NetFTSimulator(rate_hz=rate_hz, wrench=normal_force_wrench(force), faults=faults, seed=1) as sim:
        host, port = sim.address

        def truth(seq):
            t = (np.asarray(seq, dtype=float) - 1) / rate_hz
            out = np.zeros((len(t), 6))
            out[:, 2] = force(t)
            return out

        with NetFTSensor(host, port=port) as sensor:
            values, _ = _stream(sensor, seconds, truth)
        injected = sim.stats
    values[1] = int(round(seconds * rate_hz))
    row = ["in-process, faults on", rate_hz, seconds, *values]
    row[0] += f" (injected lost {injected.lost}, reordered {injected.reordered}, garbled {injected.garbled})"
    return row


def run(options: BenchOptions) -> list[BenchTable]:
    seconds = options.seconds if options.seconds else (3.0 if options.quick else 60.0)
    before = _udp_receive_buffer_errors()
    rows = [_subprocess_row(1000.0, seconds), _subprocess_row(7000.0, seconds)]
    after = _udp_receive_buffer_errors()
    rows.append(_faulty_row(min(seconds, 3.0)))
    notes = [
        "lost = rdt_sequence gaps not made good by a late arrival (garbled datagrams also leave a gap); target 0",
        "F error: every sample's 6 components against the load the simulator applied at that sequence number",
        "CPU % = this process's CPU time / wall time (driver receive thread + draining); the box is another process",
        "send failures: datagrams the simulator could not send; kernel UDP receive-buffer drops during the two "
        f"loopback runs (whole machine): {after - before if before is not None and after is not None else 'n/a'}",
    ]
    return [BenchTable(title=f"Net F/T RDT streaming over loopback ({seconds:g} s per run)", columns=COLUMNS,
                       rows=rows, notes=notes)]
