"""Bench section ``tracking``: speed against error of skin-motion measurement on the seed's scenes (seed 6.3.2).

For each scene: our feature method (extraction, matching, sub-pixel refinement, strain) and our dense flow method
on the whole sequence, then, on the same subset of frame pairs, our flow and OpenCV's DIS (medium preset),
DeepFlow and Farneback, all judged against the simulator's truth field the same way
(:mod:`skinstretch.experiments.evaluation.tracking`).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import cv2
import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable

SECTION = "tracking"
DESCRIPTION = "skin motion and strain: our feature and flow methods vs DIS, DeepFlow, Farneback (speed and error)"

SCENES = ("flatL", "ridgeL", "valleyL", "flatS", "ridgeS", "valleyS")


def _peers():
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    deep = cv2.optflow.createOptFlow_DeepFlow()
    return {
        "OpenCV DIS medium": lambda a, b: dis.calc(a, b, None),
        "OpenCV DeepFlow": lambda a, b: deep.calc(a, b, None),
        # FACTS: window 41 was Farneback's best on fingerprint texture.
        "OpenCV Farneback": lambda a, b: cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 41, 5, 7, 1.5, 0),
    }


def _rms(x) -> float:
    x = np.asarray(x, dtype=np.float64)
    return float(np.sqrt(np.mean(x**2))) if x.size else math.nan


def _pattern_ok(profile: dict) -> str:
    """"yes"/"no": the measured profile's lobes come in the true order; "n/a" without a true pattern (flat)."""
    if profile.get("true_compression_first") is None:
        return "n/a"
    return "yes" if profile.get("compression_first") == profile["true_compression_first"] else "no"


def run(options: BenchOptions) -> list[BenchTable]:
    from skinstretch.experiments.analysis import analysis_params, make_executor

    scenes = list(options.scenes or (["ridgeL"] if options.quick else SCENES))
    n_frames = 24 if options.quick else 180
    n_peer_pairs = 4 if options.quick else 16
    full_rows, pair_rows, notes = [], [], []
    warmed: set[str] = set()
    executor = make_executor(analysis_params().execution)  # one executor for the whole run, as a batch would
    try:
        return _run(options, scenes, n_frames, n_peer_pairs, full_rows, pair_rows, notes, warmed, executor)
    finally:
        executor.shutdown()


def _run(options, scenes, n_frames, n_peer_pairs, full_rows, pair_rows, notes, warmed, executor):
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.experiments.analysis.derive import stretch_profile
    from skinstretch.experiments.analysis.executor import WorkerProcesses
    from skinstretch.experiments.analysis.frames import ArrayFrames, FrameReader, estimate_shading
    from skinstretch.experiments.analysis.plan import plan_analysis
    from skinstretch.experiments.evaluation.tracking import TruthField, evaluate_dense_pair, evaluate_tracking
    from skinstretch.processing.flow import DenseFlow
    from skinstretch.processing.flow_fields import sample_dense_flow
    from skinstretch.processing.tracking import MotionSample
    from skinstretch.simulators.scene import load_scene, render_session

    for name in scenes:
        sc = load_scene(name)
        n = min(n_frames, sc.n_frames)
        s = render_session(sc, n_frames=n, seed=0)
        frames, cal, truth = s.frames, s.calibration, s.truth
        tf = TruthField(truth)
        base = analysis_params()
        params = base.model_copy(update={"tracking": replace(base.tracking,
                                                             min_length_frames=min(30, max(2, n // 3)))})
        if not warmed and isinstance(executor, WorkerProcesses):
            t0 = time.perf_counter()
            executor.submit(int, 0).result()  # the worker processes start once per run (then kept)
            notes.append(f"the run's {executor.workers} worker processes were started before timing "
                         f"({time.perf_counter() - t0:.1f} s, once per run; kept for later analyses)")
            notes.append("each method analysed the first scene once untimed before its timed run (compiled kernels "
                         "loaded): the figures are a batch analysis' later sessions")
        for method in ("features", "flow"):
            if method not in warmed:
                # An untimed first analysis of the same frames: compiled kernels (numba) load or compile at their
                # first call, and the first analysis of a process writes into fresh memory (the feature method's
                # shared frame blocks, kept afterwards; large arrays), which costs this VM a page fault per 4 KiB.
                # The timed run is then what every later session of a batch analysis costs.
                analyze_frames(frames, calibration=cal, method=method, params=params, surface=sc.surface.kind,
                               executor=executor)
                warmed.add(method)
            r = analyze_frames(frames, calibration=cal, method=method, params=params, surface=sc.surface.kind,
                               executor=executor)
            ev = evaluate_tracking(r, truth)
            t = r.timing
            full_rows.append(
                [
                    name,
                    f"ours {method}",
                    n,
                    t["frames_per_s"],
                    (n / t["extraction_s"]) if "extraction_s" in t else math.nan,
                    n
                    / (
                        t.get("tracking_s", t.get("flow_s", 0.0))
                        + t.get("image_prep_s", 0.0)
                        + t.get("chaining_s", 0.0)
                        + t["derive_s"]
                    ),
                    ev["tracking"]["displacement_rmse_px"],
                    ev["tracking"]["displacement_median_px"],
                    ev["tracking"]["wrong_match_rate"],
                    ev["strain"]["edge_rmse_1"] * 100,
                    ev["strain"]["edge_rmse_11"] * 100 if 11 in r.spans else math.nan,
                    ev["strain"]["area_rmse_1"] * 100,
                    ev["profile"]["correlation"],
                    ev["profile"]["amplitude"] * 100,
                    ev["profile"]["true_amplitude"] * 100,
                    _pattern_ok(ev["profile"]),
                ]
            )
        # The same pairs, and the same frames (glass-fixed shading removed as our pipeline does), for every method.
        source = ArrayFrames(frames)
        shading, _ = estimate_shading(source, calibration=cal, params=params, surface=sc.surface.kind)
        shaded = FrameReader(source, shading)
        frames = np.stack([shaded(k) for k in range(len(source))])
        pairs = np.linspace(0, n - 2, n_peer_pairs).round().astype(int)
        plan = plan_analysis(params, method="flow", n_frames=n, surface=sc.surface.kind,
                             shading_removed=shading is not None)
        ours = DenseFlow(calibration=cal, params=plan.params.flow)  # as the analysis does
        methods = {"ours flow": None}
        methods.update(_peers())
        strip = cal.px(params.strain.profile_strip_mm)
        axis = int(np.argmax(np.ptp(truth.rigid[:n, :2], axis=0)))
        length = frames.shape[2] if axis == 0 else frames.shape[1]
        step = cal.px(params.strain.profile_step_mm)
        positions = np.arange(step, length - step / 2, step)
        true_samples, true_ft = [], []
        for k in pairs:
            g = tf.grid_motion(int(k), int(k) + 1, stride=2)
            true_samples.append(g)
            true_ft.append(g.displacement.mean(axis=0) if len(g) else np.zeros(2))
        true_prof = stretch_profile(true_samples, np.asarray(true_ft), axis=axis, positions=positions, strip_px=strip)
        for label, fn in methods.items():
            derr, eerr, secs, samples, fts = [], [], 0.0, [], []
            for k in pairs:
                a, b = frames[k], frames[k + 1]
                t0 = time.perf_counter()
                if fn is None:
                    field = ours.compute(a, b, frame_a=int(k), frame_b=int(k) + 1)

                    def sampler(p, field=field):
                        return field.sample(p)[0]
                else:
                    flow = fn(a, b)

                    def sampler(p, flow=flow):
                        return sample_dense_flow(flow, p)
                secs += time.perf_counter() - t0
                vis = truth.feature_visible[k]
                fp = np.column_stack([truth.feature_x[k, vis], truth.feature_y[k, vis]])
                de = evaluate_dense_pair(sampler, tf, int(k), int(k) + 1, edge_points=fp)
                derr.append(de.displacement_errors)
                eerr.append(de.edge_errors)
                g = true_samples[len(samples)]
                d = sampler(g.points)
                ok = np.all(np.isfinite(d), axis=1)
                samples.append(MotionSample(int(k), int(k) + 1, g.points[ok], d[ok], g.ids[ok]))
                fts.append(d[ok].mean(axis=0) if ok.any() else np.zeros(2))
            prof = stretch_profile(samples, np.asarray(fts), axis=axis, positions=positions, strip_px=strip)
            okp = prof.valid & true_prof.valid
            corr = (
                float(np.corrcoef(prof.change[okp], true_prof.change[okp])[0, 1])
                if sc.surface.kind != "flat"  # a flat surface's true profile has no pattern to correlate with
                and okp.sum() > 2 and np.std(prof.change[okp]) > 0 and np.std(true_prof.change[okp]) > 0
                else math.nan
            )
            d_all = np.concatenate(derr)
            pair_rows.append(
                [
                    name,
                    label,
                    len(pairs),
                    len(pairs) / secs,
                    _rms(d_all),
                    float(np.median(d_all)) if d_all.size else math.nan,
                    float(np.mean(d_all > 0.5)) if d_all.size else math.nan,
                    _rms(np.concatenate(eerr)) * 100,
                    corr,
                ]
            )
    notes.append("displacement errors are frame-to-frame, px, against the simulator's truth field at each point")
    notes.append("edge strain RMSE in % (strain as fraction x 100) on Delaunay edges; profile = seed Figure 94")
    notes.append(
        "profile corr: measured vs true profile (n/a on a flat surface: its truth has no pattern); amp = RMS of the "
        "profile in %; pattern = compression before a ridge and expansion after it (reversed for a valley), as the "
        "truth; on ridge/valley scenes glass-fixed shading is removed first (skinstretch.processing.glass_shading)"
    )
    notes.append(
        "feature method: 'extract fps' = extraction alone on one core (each of the 2 worker processes extracts and "
        "tracks its own chunk of frames); 'rest fps' = matching + sub-pixel refinement (with its per-frame image "
        "preparation) + strain + profile + tactile movie, on one core"
    )
    return [
        BenchTable(
            title="Whole sequences: our methods (analyze pipeline)",
            columns=[
                "scene", "method", "frames", "frames/s", "extract fps", "rest fps", "disp RMSE px", "disp median px",
                "wrong match", "edge RMSE 1 %", "edge RMSE 11 %", "area RMSE 1 %", "profile corr", "profile amp %",
                "true amp %", "pattern",
            ],
            rows=full_rows,
            notes=notes,
        ),
        BenchTable(
            title="Same frame pairs, dense methods (flow at truth grid points; edges between true features)",
            columns=["scene", "method", "pairs", "pairs/s", "disp RMSE px", "disp median px", "frac > 0.5 px",
                     "edge RMSE 1 %", "profile corr"],
            rows=pair_rows,
            notes=["profile correlation here is over the sampled pairs only; every method sees the same frames"],
        ),
    ]
