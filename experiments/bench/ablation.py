"""Bench section ``ablation``: what each stage beyond the seed's method costs in CPU and gains in error.

Every stage the analysis adds to the seed's method (seed 5.1 features, or the plain dense flow) is switched off
alone through the analysis parameters (:data:`STAGES`, one row each) and the clips are analysed again, in this
process (``execution: serial``, so that ``time.process_time()`` holds all the CPU). Two sources of clips, scored by
the existing code: the scene simulator's scenes with their exact truth (``evaluate_tracking``, as ``accuracy`` and
``slipfront`` do) and the ``conditions`` section's real print moved by a known field (imported and scored from its
results files as that section does). A row reports, over its clips, the CPU ms a frame the stage costs (on minus
off) and the displacement RMSE and 11-frame edge-strain RMSE with the stage on and off, mean and worst, with a
verdict against a fixed noise threshold (:data:`NOISE_FRACTION`). Nothing here changes a default.
"""

from __future__ import annotations

import logging
import math
import shutil
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable

SECTION = "ablation"
DESCRIPTION = ("every stage beyond the seed's method switched off alone: its CPU ms a frame and what it changes in "
               "displacement and 11-frame edge-strain error (scenes and conditions clips)")

log = logging.getLogger(__name__)

#: A change in error counts when it exceeds this fraction of the error with every stage on...
NOISE_FRACTION = 0.10
#: ...and at least these absolute amounts (displacement px, edge strain percentage points).
NOISE_FLOOR_PX = 0.001
NOISE_FLOOR_PCT = 0.005

_SERIAL = {"execution": {"kind": "serial"}}


@dataclass(frozen=True)
class Stage:
    """A stage beyond the seed's method: its ``method``, the analysis options that switch it off alone, and
    whether it acts only over a ridge or valley, or only on plain glass (its row then uses only those clips)."""

    name: str
    method: str
    switch: dict[str, Any]
    shaped_only: bool = False
    flat_only: bool = False

    def switch_text(self) -> str:
        parts = []
        for stage, value in self.switch.items():
            if isinstance(value, dict):
                parts += [f"{stage}.{k}={v}" for k, v in value.items()]
            else:
                parts.append(f"{stage}={value}")
        return ", ".join(parts)


#: One row each; a stage without a switch is named in the table's notes instead.
STAGES: tuple[Stage, ...] = (
    Stage("key-frame anchoring", "features", {"tracking": {"keyframe_interval_frames": None}}),
    Stage("bridging", "features", {"tracking": {"max_bridge_frames": 0}}),
    Stage("bridge deviation bound", "features", {"tracking": {"max_bridge_deviation_spreads": None}}),
    Stage("neighbour fusion", "features", {"tracking": {"fusion_radius_mm": None}}),
    Stage("direct span registration", "features", {"subpixel": {"register_spans": False}}, flat_only=True),
    Stage("second-order span windows", "features", {"subpixel": {"span_curvature_threshold": 1e9}}),
    Stage("wide second window", "features", {"subpixel": {"wide_window_mm": None}}),
    Stage("robust matching", "features", {"robust_matching": False}),
    Stage("glass-shading removal", "features", {"glass_shading": {"enabled": False}}, shaped_only=True),
    Stage("span refiner", "flow", {"flow": {"refine_spans": False}}),
    Stage("local prior", "flow", {"flow": {"local_prior": False}}, flat_only=True),
    Stage("adaptive regularisation", "flow", {"flow": {"adaptive": False}}),
    Stage("glass-shading removal", "flow", {"glass_shading": {"enabled": False}}, shaped_only=True),
)

METHODS = ("features", "flow")


def stage_params(stage: Stage | None):
    """The analysis parameters with ``stage`` switched off (None: every stage on), run serially."""
    from skinstretch.experiments.analysis import analysis_params  # noqa: PLC0415

    options: dict[str, Any] = {k: dict(v) if isinstance(v, dict) else v for k, v in _SERIAL.items()}
    for name, value in (stage.switch if stage is not None else {}).items():
        options[name] = {**options.get(name, {}), **value} if isinstance(value, dict) else value
    return analysis_params(options)


@dataclass(frozen=True)
class Run:
    """One clip analysed by one method with one stage off (``stage`` None: all on)."""

    clip: str
    shaped: bool
    method: str
    stage: str | None
    cpu_ms_per_frame: float
    displacement_rmse_px: float
    edge_rmse_11_pct: float
    points_per_pair: float


@dataclass(frozen=True)
class ClipScore:
    """One analysis of a clip: its CPU seconds, the clip's frames, its errors against the truth and how many
    points it measured (a stage may pay by keeping points the others would lose)."""

    cpu_s: float
    n_frames: int
    displacement_rmse_px: float
    edge_rmse_11_pct: float
    points_per_pair: float


@dataclass
class _Clip:
    """A clip to analyse: its name, whether it is over a ridge or valley, and how to analyse and score it."""

    name: str
    shaped: bool
    analyse: Callable[[str, Any], ClipScore]  # (method, AnalysisParams)
    cleanup: Callable[[], None] = field(default=lambda: None)


def _scene_clip(scene_name: str, n_frames: int, seed: int, texture: str | None = None) -> _Clip:
    from skinstretch.experiments.analysis import analyze_frames  # noqa: PLC0415
    from skinstretch.experiments.evaluation.tracking import evaluate_tracking  # noqa: PLC0415
    from skinstretch.simulators.scene import load_scene, render_session  # noqa: PLC0415

    scene = load_scene(scene_name)
    if texture is not None:
        scene = scene.with_texture(texture)
    s = render_session(scene, n_frames=n_frames, seed=seed)
    surface = scene.surface.kind

    def analyse(method: str, params):
        c0 = time.process_time()
        r = analyze_frames(s.frames, calibration=s.calibration, method=method, params=params, surface=surface)
        cpu = time.process_time() - c0
        ev = evaluate_tracking(r, s.truth)
        return ClipScore(cpu, n_frames, ev["tracking"]["displacement_rmse_px"], 100.0 * ev["strain"]["edge_rmse_11"],
                         ev["tracking"]["n_displacements"] / max(n_frames - 1, 1))

    name = f"{scene_name}{'' if texture is None else ' (' + texture + ')'} seed {seed}"
    return _Clip(name, surface not in (None, "", "flat"), analyse)


def _condition_clip(name: str, workdir) -> _Clip:
    from skinstretch.experiments.bench import conditions  # noqa: PLC0415

    c = conditions.condition(name)
    directory = workdir / "ablation" / conditions._folder(c.name)
    imported, clip = conditions.imported_session(c, directory)

    def analyse(method: str, params):
        row = conditions.analyse_and_score(c, imported, clip, method, directory, params=params)
        s = row.scores
        return ClipScore(row.cpu_ms_per_frame * imported.n_frames / 1000.0, imported.n_frames,
                         s.displacement_rmse_px, s.edge_rmse_pct.get(11, math.nan),
                         s.points / max(imported.n_frames - 1, 1))

    return _Clip(f"conditions: {name}", False, analyse, lambda: shutil.rmtree(directory, ignore_errors=True))


def _plan(quick: bool) -> tuple[list[tuple[str, int, int, str | None]], list[str]]:
    """(scene, frames, seed, texture) of the scene clips, and the conditions rows, of a quick or full run; the
    full run adds a curved field (stretch: what the flow's local prior was built for), a motion reversal, valleyS and
    real prints as the texture (sparse prints: what bridging and the wide window were built for)."""
    if quick:
        return [(s, 48, 0, None) for s in ("slipfront", "ridgeL")], ["base 30 px/mm"]
    scenes = [(s, 72, 0, None) for s in ("flatL", "slipfront", "stretch", "ridgeL", "valleyL", "reversal")]
    scenes += [("valleyS", 60, 1, None)]  # where a bridged point once drifted by pixels
    scenes += [("slipfront", 72, 0, "afis_p1_2"), ("valleyL", 72, 0, "afis_p1_2"), ("ridgeL", 72, 0, "afis_p2_1")]
    return scenes, ["base 30 px/mm", "issue: 19.7 px/mm, white, noise 2"]


def run(options: BenchOptions) -> list[BenchTable]:
    scenes, condition_names = _plan(options.quick)
    runs: list[Run] = []
    warmed: set[tuple[str, bool]] = set()
    makers = [lambda s=s: _scene_clip(*s) for s in scenes]
    makers += [lambda n=n: _condition_clip(n, options.workdir) for n in condition_names]
    for make in makers:
        clip = make()
        for method in METHODS:
            if (method, clip.shaped) not in warmed:  # compiled kernels load once (a shape's own on its first
                clip.analyse(method, stage_params(None))  # shaped clip): not a stage's cost
                warmed.add((method, clip.shaped))
            for stage in (None, *(s for s in STAGES if s.method == method)):
                if stage is not None and (stage.shaped_only and not clip.shaped or stage.flat_only and clip.shaped):
                    continue
                score = clip.analyse(method, stage_params(stage))
                runs.append(Run(clip.name, clip.shaped, method, None if stage is None else stage.name,
                                1000.0 * score.cpu_s / score.n_frames, float(score.displacement_rmse_px),
                                float(score.edge_rmse_11_pct), float(score.points_per_pair)))
                log.info("%s %s off=%s: %.1f ms/frame, disp %.4f px, edge11 %.3f %%", clip.name, method,
                         runs[-1].stage, runs[-1].cpu_ms_per_frame, runs[-1].displacement_rmse_px,
                         runs[-1].edge_rmse_11_pct)
        clip.cleanup()
    return [_stage_table(runs, scenes, condition_names), _run_table(runs)]


def _worse(on: float, off: float, floor: float) -> float:
    """How much worse ``off`` is than ``on`` beyond the noise (positive), better (negative), or 0 within it;
    nothing measured with the stage off counts as worse."""
    if not math.isfinite(off):
        return math.inf if math.isfinite(on) else 0.0
    if not math.isfinite(on):
        return -math.inf
    noise = max(NOISE_FRACTION * abs(on), floor)
    d = off - on
    return d if abs(d) > noise else 0.0


def stage_verdict(on: dict[str, float], off: dict[str, float]) -> str:
    """"pays" when switching the stage off worsens the mean or worst of either error beyond the noise, "off
    better" when it improves one beyond the noise and worsens none, else "within noise"."""
    changes = [_worse(on[k], off[k], NOISE_FLOOR_PX if k.startswith("disp") else NOISE_FLOOR_PCT)
               for k in on if not k.startswith("points")]
    # fewer points measured (a sparser mesh) counts against switching off, more points does not count for it
    changes.append(max(_worse(off["points mean"], on["points mean"], 0.0), 0.0))
    if any(c > 0 for c in changes):
        return "pays"
    if any(c < 0 for c in changes):
        return "off better"
    return "within noise"


def _summary(runs: list[Run]) -> dict[str, float]:
    d = np.array([r.displacement_rmse_px for r in runs], dtype=np.float64)
    e = np.array([r.edge_rmse_11_pct for r in runs], dtype=np.float64)
    p = np.array([r.points_per_pair for r in runs], dtype=np.float64)

    def agg(x, f):
        return float(f(x)) if np.isfinite(x).all() and x.size else math.nan

    return {"disp mean": agg(d, np.mean), "disp worst": agg(d, np.max),
            "edge mean": agg(e, np.mean), "edge worst": agg(e, np.max), "points mean": agg(p, np.mean)}


def _stage_table(runs: list[Run], scenes, condition_names) -> BenchTable:
    rows = []
    for method in METHODS:
        base = {r.clip: r for r in runs if r.method == method and r.stage is None}
        s = _summary(list(base.values()))
        rows.append(["(every stage on)", method, "", len(base), float(np.mean([r.cpu_ms_per_frame
                                                                               for r in base.values()])), math.nan,
                     s["disp mean"], math.nan, s["disp worst"], math.nan, s["edge mean"], math.nan, s["edge worst"],
                     math.nan, s["points mean"], math.nan, ""])
        for stage in (st for st in STAGES if st.method == method):
            off = [r for r in runs if r.method == method and r.stage == stage.name]
            if not off:
                continue
            on = [base[r.clip] for r in off]
            a, b = _summary(on), _summary(off)
            cost = float(np.mean([x.cpu_ms_per_frame - y.cpu_ms_per_frame for x, y in zip(on, off)]))
            rows.append([stage.name, method, stage.switch_text(), len(off),
                         float(np.mean([x.cpu_ms_per_frame for x in on])), cost,
                         a["disp mean"], b["disp mean"], a["disp worst"], b["disp worst"],
                         a["edge mean"], b["edge mean"], a["edge worst"], b["edge worst"], a["points mean"],
                         b["points mean"], stage_verdict(a, b)])
    n_frames = sorted({n for _, n, _, _ in scenes})
    seeds = sorted({s for _, _, s, _ in scenes})
    return BenchTable(
        title="Every stage beyond the seed's method, switched off alone: CPU it costs, error it changes "
              "(mean and worst over the clips)",
        columns=["stage", "method", "switched off by", "clips", "CPU ms/frame all on", "CPU ms/frame cost",
                 "disp RMSE px on", "off", "worst on", "worst off", "11-frame edge RMSE % on", "off", "worst on",
                 "worst off", "points/pair on", "off", "verdict"],
        rows=rows,
        notes=[
            f"Clips: scenes {', '.join(dict.fromkeys(n + (f' ({t})' if t else '') for n, _, _, t in scenes))} ({'/'.join(map(str, n_frames))} "
            f"frames, seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}; exact truth, scored by "
            "evaluate_tracking) and the conditions clip"
            f"{'s' if len(condition_names) > 1 else ''} {'; '.join(repr(n) for n in condition_names)} (40 frames, "
            "imported and scored as the conditions section does). Glass-shading removal acts over a ridge or valley "
            "only: its rows use those clips alone; there, switching it off also leaves out what the analysis "
            "runs only when the shading was removed (the features' key-frame anchoring, the flow's span refiner), "
            "so its cost and gain include theirs.",
            "CPU ms/frame: time.process_time() of the analysis run serially in this process (every thread of it), "
            "over the clip's frames; cost = all on minus the stage off, mean over the row's clips (negative: the "
            "stage saves time, e.g. by leaving fewer points to later stages). Shared 2-core machine: a few ms is "
            "within its jitter.",
            "Errors: displacement RMSE of consecutive frames, px; 11-frame edge-strain RMSE, percentage points. "
            f"Noise is a fixed threshold, not a seed spread: a change counts when it exceeds {NOISE_FRACTION:.0%} of "
            f"the all-on value and at least {NOISE_FLOOR_PX} px / {NOISE_FLOOR_PCT} pp. Verdict: pays = switching "
            "it off worsens the mean or worst of either error beyond that, or loses more than that fraction of the "
            "points measured per consecutive pair (points/pair, mean over the clips); off better = it improves "
            "an error beyond that and worsens none; else within noise.",
            "No switch, so no row: the extractor's ridge-period statistics and band rule (ExtractionParams has no "
            "off for them). The features' direct span registration and the flow's local prior act on plain glass "
            "only (over a ridge or valley the analysis leaves them off): their rows use the flat clips alone.",
        ],
    )


def _run_table(runs: list[Run]) -> BenchTable:
    return BenchTable(
        title="Every analysis of the ablation, clip by clip",
        columns=["clip", "method", "stage off", "CPU ms/frame", "disp RMSE px", "11-frame edge RMSE %",
                 "points/pair"],
        rows=[[r.clip, r.method, r.stage or "(none)", r.cpu_ms_per_frame, r.displacement_rmse_px,
               r.edge_rmse_11_pct, r.points_per_pair] for r in runs],
    )
