"""Bench section ``recording``: sustained crash-safe recording from the simulated and the Aravis fake camera.

For each camera mode (640x484 @60 Hz, 640x100 @220 Hz) and each camera (the simulated camera streaming
pre-rendered fingerprint-like frames in real time; Aravis's in-process fake camera when the bindings import),
frames go through :class:`skinstretch.experiments.recorder.Recorder` into an SWMR session file for ``seconds`` (10 minutes
by default, 5 s with ``--quick``). Reported: frames written, frames dropped (frame-id gaps, camera drops and
recorder drops), CPU use of this process, bytes written and rate, the deepest writer queue, and an integrity
check (every frame id present once, sampled frames read back identical).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import open_session
from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.experiments.recorder import record_from_camera
from skinstretch.processing.pixel_scale import Calibration

SECTION = "recording"
DESCRIPTION = "crash-safe recording at 640x484@60 and 640x100@220: dropped frames, CPU, bytes (sim + Aravis fake)"


def _pattern_frames(mode, n: int = 32) -> np.ndarray:
    """Fingerprint-like stripes (0.43 mm period at 62 px/mm ~ 27 px) drifting between frames, with noise."""
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0 : mode.height, 0 : mode.width]
    out = np.empty((n, mode.height, mode.width), np.uint8)
    for k in range(n):
        phase = 2 * np.pi * (x * 0.8 + y * 0.6 + 3 * k) / 27.0
        img = 130 + 75 * np.cos(phase) + rng.normal(0, 2, (mode.height, mode.width))
        out[k] = np.clip(img, 0, 255).astype(np.uint8)
    return out


def _cameras(mode):
    from skinstretch.simulators.simulated_camera import SimulatedCamera  # noqa: PLC0415 - experiments pick the simulated device

    frames = _pattern_frames(mode)
    yield "simulated", lambda: SimulatedCamera(frames.__getitem__, mode, n_frames=len(frames), loop=True)
    try:
        from skinstretch.drivers.camera.aravis import AravisCamera, aravis_available  # noqa: PLC0415
    except ImportError:
        return
    if aravis_available():
        yield "aravis-fake", lambda: AravisCamera.fake()


def _record(make_camera, mode, seconds: float, path: Path) -> list:
    sampled: dict[int, int] = {}  # frame number -> checksum, every 97th frame

    def sample(k: int, frame) -> None:
        if k % 97 == 0:
            sampled[k] = int(np.asarray(frame.image, np.int64).sum())

    count = record_from_camera(make_camera(), path, mode=mode, calibration=Calibration(px_per_mm=mode.width / 10.3),
                               seconds=seconds, metadata={"bench": "recording"}, queue_size=512, on_frame=sample)
    with open_session(path) as s:
        bad = sum(1 for k, v in sampled.items() if k >= s.n_frames or int(s.frame(k).astype(np.int64).sum()) != v)
    stats, wall = count.stats, count.seconds
    return [f"{mode.width}x{mode.height}@{mode.fps:g}", count.frames, count.frames / wall, count.dropped, bad,
            count.cpu_s / wall * 100, stats.bytes_written / 1e6, stats.bytes_written / 1e6 / wall,
            stats.max_queue_depth, stats.status]


def run(options: BenchOptions) -> list[BenchTable]:
    seconds = options.seconds or (5.0 if options.quick else 600.0)
    work = Path(options.workdir) / "recording"
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    notes = []
    for mode_name in ("full", "strip"):
        mode = CAMERA_MODES[mode_name]
        for cam_name, make in _cameras(mode):
            path = work / f"{cam_name}-{mode_name}-{time.strftime('%H%M%S')}.h5"
            try:
                rows.append([cam_name, *_record(make, mode, seconds, path)])
            except Exception as exc:  # one camera failing is reported, the others still run
                notes.append(f"{cam_name} {mode_name}: {type(exc).__name__}: {exc}")
            finally:
                path.unlink(missing_ok=True)
    notes.append(f"{seconds:g} s per run; CPU is this process (camera thread + writer thread), % of one core.")
    notes.append("dropped = frame-id gaps + camera drops + recorder queue drops; 'bad' = sampled frames that did not "
                 "read back identical.")
    return [BenchTable(
        title=f"Recording to an SWMR session file ({seconds:g} s per run)",
        columns=["camera", "mode", "frames", "fps", "dropped", "bad", "CPU %", "MB", "MB/s", "max queue", "status"],
        rows=rows, notes=notes)]
