"""Bench section ``scale``: speed and peak memory of ``skinstretch analyze`` as the session grows.

A 180-frame flatL session is rendered once and played back and forth (0..179, 178..1, 0.., a continuous motion) into
sessions of 180, 1,800 and 18,000 frames (``--quick``: 60 and 600). The sessions are kept in the work directory
(``<workdir>/scale``) and reused by later runs (the 18,000-frame one is 5.6 GB and takes a while to write): a
session is reused when its metadata names the same base scene, seed and length. Each is analysed by the command
line, as a user would, by both methods, while the whole process tree (the command and every process it starts:
worker, forkserver, resource tracker) is sampled every 0.1 s with psutil: peak RSS summed over the tree (pages
shared between processes, e.g. the libraries, counted once per process: an upper bound), peak PSS summed over the
tree (each shared page divided among the processes sharing it: what the tree really holds), the largest process,
and the CPU seconds of the tree (a figure that, unlike frames/s, hardly depends on what else the machine runs).
Error against truth: displacement RMSE of the first 179 pairs (the rendered frames) against the simulator's truth
field, which must not change with the length.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable

SECTION = "scale"
DESCRIPTION = "analysis speed and peak memory of the process tree at 180, 1,800 and 18,000 frames (both methods)"

SAMPLE_S = 0.1
BASE_SCENE, BASE_SEED, BASE_FRAMES = "flatL", 0, 180


def _looped_metadata(base, n: int) -> dict:
    return {**dict(base.metadata), "looped": {"scene": BASE_SCENE, "seed": BASE_SEED,
                                              "base_frames": int(base.frames.shape[0]), "n_frames": int(n)}}


def _write_looped(path: Path, base, n: int) -> None:
    """A session of ``n`` frames playing ``base``'s frames back and forth."""
    from skinstretch.drivers.session_file import SessionWriter  # noqa: PLC0415

    b = base.frames.shape[0]
    period = 2 * b - 2
    idx = np.arange(n) % period
    idx = np.where(idx < b, idx, period - idx)
    dt = 1.0 / base.camera_mode.fps
    with SessionWriter(path, camera_mode=base.camera_mode, calibration=base.calibration,
                       metadata=_looped_metadata(base, n)) as w:
        for k0 in range(0, n, 256):
            k = np.arange(k0, min(n, k0 + 256))
            w.append_frames(base.frames[idx[k]], timestamps=k * dt, frame_ids=k, device_timestamps=k * dt)


def _cached_session(path: Path, base, n: int) -> float | None:
    """Seconds spent writing the looped session at ``path``, or None when the one already there was reused."""
    from skinstretch.drivers.errors import SessionFileError  # noqa: PLC0415
    from skinstretch.drivers.session_file import open_session  # noqa: PLC0415

    if path.exists():
        try:
            with open_session(path) as s:
                if s.shape[0] == n and s.metadata.get("looped") == _looped_metadata(base, n)["looped"]:
                    return None
        except SessionFileError:
            pass
        path.unlink()
    t0 = time.perf_counter()
    tmp = path.with_name(path.name + ".partial")
    _write_looped(tmp, base, n)
    tmp.rename(path)
    return time.perf_counter() - t0


@dataclass
class TreeSample:
    """The peaks of one command's process tree (bytes, CPU seconds)."""

    rss: int = 0
    pss: int = 0
    largest_rss: int = 0
    processes: int = 0
    cpu: dict[int, float] = field(default_factory=dict)  # per process, its latest figure


def _sample_tree(proc, peaks: TreeSample) -> None:
    import psutil  # noqa: PLC0415

    rss = pss = 0
    procs = [proc, *proc.children(recursive=True)]
    for p in procs:
        try:
            m = p.memory_full_info()  # /proc/PID/smaps_rollup: RSS, PSS
            t = p.cpu_times()
        except psutil.Error:
            continue
        rss += m.rss
        pss += getattr(m, "pss", m.rss)
        peaks.largest_rss = max(peaks.largest_rss, m.rss)
        peaks.cpu[p.pid] = t.user + t.system
    peaks.rss, peaks.pss = max(peaks.rss, rss), max(peaks.pss, pss)
    peaks.processes = max(peaks.processes, len(procs))


def _run_sampled(cmd: list[str]) -> tuple[float, TreeSample, str]:
    """Run ``cmd``; return (seconds, the tree's peaks, what it wrote to standard error)."""
    import psutil  # noqa: PLC0415

    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    proc = psutil.Process(p.pid)
    peaks = TreeSample()
    while p.poll() is None:
        try:
            _sample_tree(proc, peaks)
        except psutil.Error:
            break
        time.sleep(SAMPLE_S)
    _, err = p.communicate()
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {err.strip()[-500:]}")
    return time.perf_counter() - t0, peaks, err


def _displacement_rmse(results, truth) -> float:
    from skinstretch.experiments.evaluation.tracking import TruthField  # noqa: PLC0415
    from skinstretch.experiments.results_file import pair_row_offsets  # noqa: PLC0415

    tf = TruthField(truth)
    pairs = results.motion_pairs
    n = min(pairs.size, tf.n_frames - 1)
    with results.open() as f:  # only the pairs with a truth (the motion table of 18,000 frames is large)
        offsets = pair_row_offsets(pairs["n_points"][:n])
        m = f["motion"][: int(offsets[-1])]
    errs = []
    for i in range(n):
        rows = m[offsets[i] : offsets[i + 1]]
        if rows.size:
            d, ok = tf.between(np.column_stack([rows["x"], rows["y"]]), int(pairs["frame_a"][i]),
                               int(pairs["frame_b"][i]))
            errs.append(np.hypot(*(np.column_stack([rows["dx"], rows["dy"]])[ok] - d[ok]).T))
    e = np.concatenate(errs) if errs else np.zeros(0)
    return float(np.sqrt(np.mean(e**2))) if e.size else math.nan


def run(options: BenchOptions) -> list[BenchTable]:
    from skinstretch.experiments.results_file import read_results  # noqa: PLC0415
    from skinstretch.simulators.scene import render_session  # noqa: PLC0415

    lengths = (60, 600) if options.quick else (180, 1800, 18000)
    lengths = tuple(int(v) for v in options.extra.get("scale_lengths", lengths))
    work = options.workdir / "scale"
    work.mkdir(parents=True, exist_ok=True)
    base = render_session(BASE_SCENE, n_frames=min(BASE_FRAMES, max(lengths)), seed=BASE_SEED, workers=2)
    rows, first_second = [], []
    for n in lengths:
        session = work / f"{BASE_SCENE}_looped_{n}.h5"
        t_write = _cached_session(session, base, n)
        for method in ("features", "flow"):
            out = work / f"{BASE_SCENE}_{n}_{method}"
            shutil.rmtree(out, ignore_errors=True)
            cmd = [sys.executable, "-m", "skinstretch.cli", "analyze", str(session), "-o", str(out),
                   "--method", method, "--quiet"]
            seconds, peaks, err = _run_sampled(cmd)
            if n == lengths[0]:  # the first analysis of this bench run against a second one, both new processes
                shutil.rmtree(out, ignore_errors=True)
                again, again_peaks, _ = _run_sampled(cmd)
                first_second.append([n, method, seconds, sum(peaks.cpu.values()), again,
                                     sum(again_peaks.cpu.values()), seconds / again,
                                     "yes" if "compiling the analysis' kernels" in err else "no"])
            summary = json.loads((out / "summary.json").read_text())
            r = read_results(out)
            mb = 2**20
            rows.append([n, method, summary["timing"]["frames_per_s"], n / seconds, sum(peaks.cpu.values()),
                         peaks.rss / mb, peaks.pss / mb, peaks.largest_rss / mb, peaks.processes,
                         (out / "results.h5").stat().st_size / mb, _displacement_rmse(r, base.truth),
                         "reused" if t_write is None else t_write])
            shutil.rmtree(out, ignore_errors=True)
    return [
        BenchTable(
            title="skinstretch analyze on longer sessions (flatL played back and forth): speed and peak memory",
            columns=["frames", "method", "frames/s", "frames/s w/ start", "CPU s (tree)", "peak RSS MB (tree)",
                     "peak PSS MB (tree)", "peak RSS MB (largest process)", "processes", "results MB",
                     "disp RMSE px (first 179 pairs)", "session write s"],
            rows=rows,
            notes=[
                "frames/s: the analysis' own figure; 'w/ start' includes starting Python, the imports and the "
                "worker process of the command; both depend on what else the machine runs, CPU s (user + system "
                "of every process of the tree at its last sample) much less",
                "memory: every process of the command's tree (the command, its worker process, the forkserver "
                "and the resource tracker) read with psutil's memory_full_info (/proc/PID/smaps_rollup) every "
                f"{SAMPLE_S} s; RSS summed over the tree counts the pages the processes share (the libraries) "
                "once per process (an upper bound), PSS divides them among their processes (what the tree "
                "holds); each column is its own peak over the run",
                "the frames are streamed from the session file; features, trajectories, motion, strain and flow "
                "fields, movie are written to the results file as they are final, and what stays in memory per "
                "frame is a few numbers (flags, fingertip, window)",
                f"sessions are kept in {work} and reused when their metadata matches ('reused')",
            ],
        ),
        BenchTable(
            title="The first analysis after set-up against the second (compiled kernels: `./run` compiles them)",
            columns=["frames", "method", "first s", "first CPU s", "second s", "second CPU s", "first / second",
                     "compiled at run time"],
            rows=first_second,
            notes=["two `skinstretch analyze` processes in a row on the same session, each timed as above; "
                   "'compiled at run time': the first one logged that it compiled a kernel (its cache missed)",
                   "on a fresh clone the bench's own `./run` set-up compiles them first (`python -m "
                   "skinstretch.experiments.compile_kernels`); the target is first / second <= 2"],
        ),
    ]
