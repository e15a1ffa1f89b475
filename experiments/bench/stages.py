"""Bench section ``stages``: what each stage of the analysis costs a frame, beside the analysis' error.

A flatL and a ridgeL clip are rendered and analysed by both methods in this process, serially (the stages one
after another on one core), the way ``skinstretch analyze`` analyses a session. Each stage's seconds (wall) come
from the analysis' own ``timing``
(``summary.json``): extraction, the tracker's image preparation and matching with refinement, key-frame anchoring,
span registration, the flow's pair fields and its span refiner, strain and derived outputs. Errors against the
simulator's truth (:mod:`skinstretch.experiments.evaluation.tracking`): frame-to-frame displacement RMSE and edge
strain RMSE of the 1- and 11-frame spans. A stage's CPU time is estimated as its wall time times the whole call's
CPU over wall (the share of a core the process had: on a shared machine the wall time stretches, the CPU time much
less). The ablation (every stage switched off alone) cites these costs.
"""

from __future__ import annotations

import math
import time

import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable

SECTION = "stages"
DESCRIPTION = "ms a frame of each stage of the analysis (both methods, one core), beside its error"

#: (scene, frames) analysed; --quick: shorter clips.
CLIPS = (("flatL", 180), ("ridgeL", 180))
QUICK_CLIPS = (("flatL", 60), ("ridgeL", 60))

#: The timing keys of each method, in pipeline order, and the stage each names. A key the analysis did not run
#: (no key frames over a shape whose shading stayed in) reads 0.
STAGES = {
    "features": (("extraction_s", "feature extraction"), ("image_prep_s", "tracker's image preparation"),
                 ("tracking_s", "matching and refinement (the tracker)"), ("keyframes_s", "key-frame anchoring"),
                 ("span_registration_s", "span registration (11-frame spans)"),
                 ("derive_s", "strain and derived outputs")),
    "flow": (("flow_pairs_s", "pair fields"), ("span_refiner_s", "span refiner (11-frame spans)"),
             ("derive_s", "strain and derived outputs")),
}


def _errors(results, truth) -> tuple[float, float, float]:
    from skinstretch.experiments.evaluation.tracking import TruthField, displacement_errors, edge_strain_errors  # noqa: PLC0415

    tf = TruthField(truth)

    def rms(a):
        return float(np.sqrt(np.mean(np.square(a)))) if a.size else math.nan

    return (rms(displacement_errors(results, tf)), 100 * rms(edge_strain_errors(results, tf, 1)[0]),
            100 * rms(edge_strain_errors(results, tf, 11)[0]))


def stage_seconds(method: str, timing: dict[str, float]) -> dict[str, float]:
    """Seconds per stage key of :data:`STAGES` from an analysis' ``timing``: the tracker's own seconds without
    the key frames and span registration (which the pipeline counts in ``tracking_s``), the flow's pair fields
    without its span refiner (counted in ``flow_s``)."""
    t = dict(timing)
    if method == "features":
        t["tracking_s"] = t.get("tracking_s", 0.0) - t.get("keyframes_s", 0.0) - t.get("span_registration_s", 0.0)
    else:
        t["flow_pairs_s"] = t.get("flow_s", 0.0) - t.get("span_refiner_s", 0.0)
    return {key: max(0.0, float(t.get(key, 0.0))) for key, _ in STAGES[method]}


def run(options: BenchOptions) -> list[BenchTable]:
    from skinstretch.experiments.analysis.pipeline import analyze_frames, surface_kind  # noqa: PLC0415
    from skinstretch.simulators.scene import render_session  # noqa: PLC0415

    rows = []
    for scene, n in QUICK_CLIPS if options.quick else CLIPS:
        session = render_session(scene, n_frames=n, seed=0, workers=2)
        for method in ("features", "flow"):
            c0, t0 = time.process_time(), time.perf_counter()
            r = analyze_frames(session.frames, calibration=session.calibration, method=method,
                               surface=surface_kind(session.metadata), params={"execution": {"kind": "serial"}})
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            disp, edge1, edge11 = _errors(r, session.truth)
            share = cpu / wall if wall > 0 else 1.0
            for key, name in STAGES[method]:
                ms = 1000 * stage_seconds(method, r.timing)[key] / n
                rows.append([scene, method, name, ms * share, ms, disp, edge1, edge11])
            rows.append([scene, method, "whole analysis", 1000 * cpu / n, 1000 * wall / n, disp, edge1, edge11])
    return [BenchTable(
        title="The analysis stage by stage: ms a frame, one core, beside the whole analysis' error",
        columns=["scene", "method", "stage", "CPU ms/frame", "wall ms/frame", "disp RMSE px", "edge RMSE 1 %",
                 "edge RMSE 11 %"],
        rows=rows,
        notes=[
            "serial analysis in one process (the stages one after another on one core); wall ms/frame = the stage's "
            "seconds in the analysis' timing / frames, CPU ms/frame = that times the whole call's CPU / wall (an "
            "estimate); 'whole analysis': the call's measured CPU and wall",
            "errors are the whole analysis' (every stage on): the ablation section switches stages off one by one",
            "ridgeL: key frames and span registration run where the glass-fixed shading was removed (the plan)",
        ],
    )]
