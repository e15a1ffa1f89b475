"""Bench section ``camera``: sustained acquisition at the seed's camera modes (seed 3.3) and a 500 Hz burst.

Cameras: Aravis's in-process fake camera (the real Aravis code path), Aravis over loopback GigE Vision
(``arv-fake-gv-camera-0.8``, when installed) and the simulated camera. A consumer thread reads every frame as a
recorder would. Speed: achieved frame rate and CPU use (process CPU time / wall time, 2 cores = 200 %).
Error: frames lost (dropped + failed; the target is zero) and the spread of the frame intervals on the host clock.
"""

from __future__ import annotations

import time

import numpy as np

from skinstretch.drivers.camera.base import Camera
from skinstretch.drivers.camera_modes import CAMERA_MODES, CameraMode
from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.drivers.errors import DeviceError
from skinstretch.simulators.simulated_camera import SimulatedCamera
from skinstretch.simulators.gige_fake_camera import FakeGigECamera

SECTION = "camera"
DESCRIPTION = "camera acquisition: seed modes and a 500 Hz burst, lost frames and CPU (Aravis fake, GigE loopback, sim)"

BURST = CameraMode("burst", 640, 484, 500.0)
MODES = [CAMERA_MODES["full"], CAMERA_MODES["half"], CAMERA_MODES["strip"], BURST]
COLUMNS = ["camera", "mode", "seconds", "frames", "expected", "fps", "lost", "failed", "underruns", "interval sd ms",
           "CPU %"]


def _stream(camera: Camera, mode: CameraMode, seconds: float) -> list:
    """Stream for ``seconds`` reading every frame; one table row."""
    camera.set_mode(mode)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    camera.start()
    host_t = []
    try:
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            host_t.append(camera.read(2.0).host_timestamp_s)
    finally:
        camera.stop()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    while True:  # frames still queued at stop belong to the run
        try:
            host_t.append(camera.read(0.01).host_timestamp_s)
        except DeviceError:
            break
    stats = camera.stats
    # Aravis's own count of frames that found no free buffer: 0 means any shortfall is the camera's, not ours.
    device = getattr(camera, "device_statistics", None)
    underruns = device["underruns"] if device is not None else float("nan")
    t = np.asarray(host_t)
    fps = (len(t) - 1) / (t[-1] - t[0]) if len(t) > 1 and t[-1] > t[0] else float("nan")
    sd_ms = float(np.std(np.diff(t)) * 1e3) if len(t) > 2 else float("nan")
    return [
        repr(camera).split("(")[0],
        f"{mode.width}x{mode.height}@{mode.fps:g}",
        round(seconds, 1),
        len(t),
        int(round(seconds * mode.fps)),
        float(fps),
        stats.dropped + stats.failed,
        stats.failed,
        underruns,
        sd_ms,
        100.0 * cpu / wall,
    ]


def _aravis_rows(seconds: float, notes: list[str]) -> list[list]:
    from skinstretch.drivers.camera.aravis import AravisCamera, aravis_available

    if not aravis_available():
        notes.append("Aravis bindings not importable: Aravis rows skipped")
        return []
    rows = []
    for mode in MODES:
        with AravisCamera.fake() as cam:
            row = _stream(cam, mode, seconds)
        row[0] = "Aravis fake (in-process)"
        rows.append(row)
    server = FakeGigECamera("127.0.0.1")
    try:
        address = server.start()
    except DeviceError as exc:
        notes.append(f"{exc}: GigE loopback rows skipped")
        return rows
    try:
        for mode in (CAMERA_MODES["full"], CAMERA_MODES["strip"]):
            with AravisCamera(address) as cam:
                row = _stream(cam, mode, seconds)
            row[0] = "Aravis GigE loopback"
            rows.append(row)
        notes.append("GigE loopback: the fake camera process's own CPU is not in the CPU column")
    finally:
        server.stop()
    return rows


def _simulated_rows(seconds: float) -> list[list]:
    rows = []
    rng = np.random.default_rng(0)
    for mode in MODES:
        frames = rng.integers(0, 256, size=(8, mode.height, mode.width), dtype=np.uint8)
        with SimulatedCamera(frames.__getitem__, mode, n_frames=len(frames)) as cam:
            row = _stream(cam, mode, seconds)
        row[0] = "simulated (pre-rendered, looped)"
        rows.append(row)
    return rows


def run(options: BenchOptions) -> list[BenchTable]:
    seconds = options.seconds if options.seconds else (3.0 if options.quick else 60.0)
    notes = [
        "lost = dropped (frame-id gaps, buffer underruns, full queue) + failed (incomplete frames); target 0",
        "CPU % = process CPU time / wall time of the whole process (acquisition + consumer threads; for the "
        "in-process Aravis fake this includes the fake camera's own image generator)",
        "frames < expected with 0 lost and 0 underruns: the camera produced fewer frames (the Aravis fake cameras "
        "generate images in software and slow down on a loaded machine); nothing was lost on the way",
    ]
    rows = _aravis_rows(seconds, notes)
    rows += _simulated_rows(min(seconds, 2.0) if options.quick else seconds)
    return [BenchTable(title=f"Camera acquisition ({seconds:g} s per run)", columns=COLUMNS, rows=rows, notes=notes)]
