"""Bench section ``scale``: speed and peak memory of ``skinstretch analyze`` as the session grows.

A 180-frame flatL session is rendered once and played back and forth (0..179, 178..1, 0.., a continuous motion) into
sessions of 180, 1,800 and 18,000 frames (``--quick``: 60 and 600). Each is analysed by the command line, as a user
would, by both methods, while the whole process tree (the command and every worker it starts) is sampled every
0.1 s: peak RSS summed over the tree (shared pages, e.g. the libraries every worker maps, counted once per
process: an upper bound) and peak PSS (each shared page divided among the processes sharing it: what the tree
really holds). Error against truth: displacement RMSE of the first 179 pairs (the rendered frames) against the
simulator's truth field, which must not change with the length.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import time

import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable

SECTION = "scale"
DESCRIPTION = "analysis speed and peak memory of the process tree at 180, 1,800 and 18,000 frames (both methods)"

SAMPLE_S = 0.1


def _write_looped(path, base, n: int) -> None:
    """A session of ``n`` frames playing ``base``'s frames back and forth."""
    from skinstretch.drivers.session_file import SessionWriter  # noqa: PLC0415

    b = base.frames.shape[0]
    period = 2 * b - 2
    idx = np.arange(n) % period
    idx = np.where(idx < b, idx, period - idx)
    dt = 1.0 / base.camera_mode.fps
    with SessionWriter(path, camera_mode=base.camera_mode, calibration=base.calibration,
                       metadata=dict(base.metadata)) as w:
        for k0 in range(0, n, 256):
            k = np.arange(k0, min(n, k0 + 256))
            w.append_frames(base.frames[idx[k]], timestamps=k * dt, frame_ids=k, device_timestamps=k * dt)


def _tree_memory(proc) -> tuple[int, int]:
    """(RSS summed over the tree, PSS summed over the tree), bytes."""
    import psutil  # noqa: PLC0415

    rss = pss = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            m = p.memory_full_info()
        except psutil.Error:
            continue
        rss += m.rss
        pss += getattr(m, "pss", m.rss)
    return rss, pss


def _run_sampled(cmd: list[str]) -> tuple[int, float, float, float]:
    """Run ``cmd``; return (exit status, seconds, peak tree RSS MB, peak tree PSS MB)."""
    import psutil  # noqa: PLC0415

    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    proc = psutil.Process(p.pid)
    peak_rss = peak_pss = 0
    while p.poll() is None:
        try:
            rss, pss = _tree_memory(proc)
        except psutil.Error:
            break
        peak_rss, peak_pss = max(peak_rss, rss), max(peak_pss, pss)
        time.sleep(SAMPLE_S)
    _, err = p.communicate()
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {err.strip()[-500:]}")
    return p.returncode, time.perf_counter() - t0, peak_rss / 2**20, peak_pss / 2**20


def _displacement_rmse(results, truth) -> float:
    from skinstretch.experiments.evaluation.tracking import TruthField  # noqa: PLC0415

    tf = TruthField(truth)
    m = results.motion
    pairs = results.motion_pairs
    errs = []
    for i in range(min(pairs.size, tf.n_frames - 1)):
        rows = m[m["pair"] == i]
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
    base = render_session("flatL", n_frames=min(180, max(lengths)), seed=0, workers=2)
    rows = []
    for n in lengths:
        session = work / f"flatL_{n}.h5"
        t0 = time.perf_counter()
        _write_looped(session, base, n)
        t_write = time.perf_counter() - t0
        for method in ("features", "flow"):
            out = work / f"flatL_{n}_{method}"
            shutil.rmtree(out, ignore_errors=True)
            cmd = [sys.executable, "-m", "skinstretch.cli", "analyze", str(session), "-o", str(out),
                   "--method", method, "--quiet"]
            _, seconds, rss, pss = _run_sampled(cmd)
            summary = json.loads((out / "summary.json").read_text())
            r = read_results(out)
            rows.append([n, method, summary["timing"]["frames_per_s"], n / seconds, rss, pss,
                         (out / "results.h5").stat().st_size / 2**20, _displacement_rmse(r, base.truth), t_write])
            shutil.rmtree(out, ignore_errors=True)
        session.unlink()
    return [
        BenchTable(
            title="skinstretch analyze on longer sessions (flatL played back and forth): speed and peak memory",
            columns=["frames", "method", "frames/s", "frames/s w/ start", "peak RSS MB (tree)", "peak PSS MB (tree)",
                     "results MB", "disp RMSE px (first 179 pairs)", "session write s"],
            rows=rows,
            notes=[
                "frames/s: the analysis' own figure; 'w/ start' includes starting Python, the imports and the worker "
                "processes (2, forkserver) of the command",
                "peak RSS sums every process of the tree (libraries mapped by every worker counted once per "
                "process: an upper bound); PSS divides shared pages among their processes (what the tree holds); "
                f"both sampled every {SAMPLE_S} s with psutil",
                "the frames are streamed from the session file; motion, strain and flow fields are written to the "
                "results file as they are computed",
            ],
        )
    ]
