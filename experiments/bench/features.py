"""Bench section ``features``: feature extraction + editing speed against accuracy on simulated scenes.

Per scene: frames/s for a sequence (single thread and a 2-thread pool), and recall / precision / localisation
RMSE / repeatability of minutiae and pores against the simulator's truth (matching rules in
:mod:`skinstretch.experiments.evaluation.features`).
"""

from __future__ import annotations

import time

from skinstretch.experiments.bench import BenchOptions, BenchTable

SECTION = "features"
DESCRIPTION = "feature extraction and editing (seed ch. 4): frames/s, recall, precision, localisation, repeatability"

_DEFAULT_SCENES = ("flatL", "ridgeL", "valleyL", "flatS")

#: Targets of the brief, printed under the table.
TARGETS = {
    "minutiae recall": 0.90,
    "minutiae precision": 0.90,
    "pore recall": 0.85,
    "pore precision": 0.90,
    "pore RMSE px": 0.15,
    "minutiae repeatability px": 0.1,
    "frames/s (2 threads)": 200,
}


#: Timed passes per scene (each: the sequence on 1 thread, then on 2); the best is reported.
_PASSES = 3


def _scene_row(name: str, n_frames: int) -> list:
    import numpy as np
    from skinstretch.experiments.evaluation.features import evaluate_features
    from skinstretch.processing.extraction import FeatureExtractor
    from skinstretch.processing.feature_filters import border_mask
    from skinstretch.simulators.scene import load_scene, render_session

    scene = load_scene(name).model_copy(update={"n_frames": n_frames})
    rs = render_session(scene, n_frames=n_frames, seed=0)
    frames = list(rs.frames)
    ex = FeatureExtractor(calibration=rs.calibration)
    # Seed 3.5: the illumination map of the sequence (max over frames, low-passed) normalises the valleys; the
    # seed uses it for every sequence, and the curved surfaces need it (their slopes darken the light).
    t0 = time.perf_counter()
    ex.fit_illumination(frames)
    illum_ms = (time.perf_counter() - t0) * 1000
    ex.extract(frames[0])  # compile / warm caches outside the timing
    # Best of _PASSES passes: the machine is shared, and a slower pass measures the other loads, not the code.
    fps1 = fps2 = 0.0
    cpu_ms = float("inf")
    for _ in range(_PASSES):
        t0, c0 = time.perf_counter(), time.process_time()
        ex.extract_many(frames, workers=1)
        fps1 = max(fps1, len(frames) / (time.perf_counter() - t0))
        cpu_ms = min(cpu_ms, (time.process_time() - c0) / len(frames) * 1000)
        t0 = time.perf_counter()
        results = ex.extract_many(frames, workers=2)
        fps2 = max(fps2, len(frames) / (time.perf_counter() - t0))
    feats = np.concatenate([r.features for r in results])
    dilation = rs.calibration.px_int(ex.params.border_dilation_mm)
    masks = {k: border_mask(r.background, dilation_px=dilation) for k, r in enumerate(results)}
    ev = evaluate_features(feats, rs.truth, px_per_mm=rs.calibration.px_per_mm, exclusion_masks=masks)
    m, p = ev["minutiae"], ev["pore"]
    nan = float("nan")
    val = lambda d, k: nan if d[k] is None else float(d[k])  # noqa: E731
    h, w = rs.frames.shape[1:]
    return [
        name,
        f"{w}x{h}",
        n_frames,
        cpu_ms,
        fps1,
        fps2,
        val(m, "recall"),
        val(m, "precision"),
        val(m, "loc_rmse_px"),
        val(m, "loc_bias_px"),
        val(m, "loc_rmse_debiased_px"),
        val(m, "repeatability_px"),
        val(ev["valley_ending"], "repeatability_px"),
        val(ev["valley_bifurcation"], "repeatability_px"),
        val(p, "recall"),
        val(p, "precision"),
        val(p, "loc_rmse_px"),
        val(p, "repeatability_px"),
        m["n_truth"] / max(len(frames), 1),
        p["n_truth"] / max(len(frames), 1),
        illum_ms,
    ]


def run(options: BenchOptions) -> list[BenchTable]:
    scenes = list(options.scenes) if options.scenes else (["flatL"] if options.quick else list(_DEFAULT_SCENES))
    n_frames = 20 if options.quick else 60
    rows = [_scene_row(name, n_frames) for name in scenes]
    table = BenchTable(
        title="Feature extraction + editing, default parameters, default noise, seed 0 (seed 3.5 and chapter 4)",
        columns=[
            "scene",
            "size",
            "frames",
            "cpu ms/frame",
            "fps 1 thr",
            "fps 2 thr",
            "min recall",
            "min prec",
            "min rmse px",
            "min bias px",
            "min debiased rmse px",
            "min rep px",
            "end rep px",
            "bif rep px",
            "pore recall",
            "pore prec",
            "pore rmse px",
            "pore rep px",
            "min/frame",
            "pores/frame",
            "illum map ms",
        ],
        rows=rows,
        notes=[
            "min = minutiae (valley endings + bifurcations pooled); matching one-to-one within 0.1 mm, visible truth "
            "outside the border deletion mask only (experiments/evaluation/features.py).",
            "illumination compensation (seed 3.5) fitted on each sequence first (its time: last column, once per "
            "sequence); fps: extraction + editing + sub-pixel per frame, after a warm-up frame; cpu ms/frame: process "
            f"CPU time of the single-thread run (less sensitive than fps to other loads on the machine); all three the "
            f"best of {_PASSES} passes.",
            "rep = RMS frame-to-frame change of a matched feature's localisation error (jitter vs true motion); "
            "end / bif = valley endings / bifurcations alone.",
            "bias = RMS of each truth feature's mean offset (valley endings are located where the valley's grey "
            "centre line reaches the local mean, a constant ~3 px beyond the simulator's phase singularity); "
            "debiased rmse = RMS of the error around that mean; rmse^2 = bias^2 + debiased^2 (rmse is the raw figure).",
            "targets: " + ", ".join(f"{k} {'>=' if 'recall' in k or 'prec' in k or 'frames' in k else '<='} {v}"
                                    for k, v in TARGETS.items()),
        ],
    )
    return [table]
