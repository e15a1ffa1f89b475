"""Bench section ``playback``: open- against closed-loop tactile movie playback on the simulated STReSS.

The firmware twin (``skinstretch.simulators.stress_firmware``: first-order lag, play-operator hysteresis, seeded gain
spread, finger load as a lateral stiffness in series with each bender) is driven through the real driver over its
paced serial link at 700 Hz. The same movie (10x10 sinusoids, 10-30 um, 2 Hz, random phases — a stand-in for a
measured movie with the same bandwidth) is played open loop and closed loop at several finger loads. Reported:
RMS position error against the target (after a settle time), the ratio, late frames and the p99 period jitter.
"""

from __future__ import annotations

import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable
from skinstretch.experiments.playback import fit_movie, play_movie
from skinstretch.experiments.rig import make_display, sim_display_url

SECTION = "playback"
DESCRIPTION = "tactile movie on the simulated STReSS (hysteresis, finger load): RMS error open vs closed loop"


def bench_movie(seconds: float, *, rate_hz: float = 700.0, seed: int = 1) -> np.ndarray:
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, (10, 10))
    amp = rng.uniform(10, 30, (10, 10))
    return amp * np.sin(2 * np.pi * 2.0 * t[:, None, None] + phase)


def run(options: BenchOptions) -> list[BenchTable]:
    seconds = options.seconds or (1.5 if options.quick else 10.0)
    loads = (0.0, 0.15) if options.quick else (0.0, 0.15, 0.5)
    movie = bench_movie(seconds)
    rows = []
    notes = []
    settle = min(350, movie.shape[0] // 4)
    for load in loads:
        # Reach under load: bender (0.5 N/mm) and skin in series; keep the targets within 70 % of it.
        reach_um = 50.0 * 0.5 / (0.5 + load)
        movie_fit, _ = fit_movie(movie, peak_um=min(30.0, 0.7 * reach_um))
        res = {}
        for closed in (False, True):
            display = make_display(sim_display_url(seed=3, load_n_per_mm=load))
            try:
                display.zero()
                res[closed] = play_movie(display, movie_fit, rate_hz=700.0, closed_loop=closed, settle_frames=settle)
            finally:
                display.close()
        o, c = res[False], res[True]
        ratio = o.rms_error_um / c.rms_error_um if c.rms_error_um > 0 else float("inf")
        rows.append([load, float(np.max(np.abs(movie_fit))), o.frames_played, o.rms_error_um, c.rms_error_um, ratio,
                     o.late_frames + c.late_frames, max(o.extra["period_jitter_p99_s"], c.extra["period_jitter_p99_s"]) * 1e3,
                     "yes" if o.complete and c.complete else f"no: {o.stopped or c.stopped}"])
    notes.append(f"{seconds:g} s of movie at 700 Hz per run; RMS after {settle} settle frames; measured position "
                 "of frame k (from the ack of frame k+1) against the target of frame k.")
    notes.append("Goal: closed loop at least 5x lower RMS error than open loop with hysteresis and finger load.")
    return [BenchTable(
        title="Closed-loop playback on the simulated STReSS display",
        columns=["load N/mm", "peak um", "frames", "open RMS um", "closed RMS um", "ratio", "late frames",
                 "p99 jitter ms", "complete"],
        rows=rows, notes=notes)]
