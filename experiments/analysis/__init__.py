"""The analysis of a session (seed chapters 4-5): motion by features or dense flow, strain, profile, tactile movie.

Read it in this order:

* :mod:`.parameters` — one frozen pydantic model per stage, gathered in :class:`AnalysisParams`;
* :mod:`.plan` — what the surface and the clip change, resolved once into a frozen :class:`AnalysisPlan`;
* :mod:`.executor` — the one way it runs in parallel (processes, threads or serial), chosen once per run;
* :mod:`.frames` — frames streamed from a session file (or held by the caller), glass-fixed shading removed;
* :mod:`.measure` — motion between consecutive frames, chunk by chunk on the executor;
* :mod:`.derive` — strain tables, fingertip motion, visibility window, profile and movie, in pixels;
* :mod:`.cumulative` — every frame's motion from the reference frame, along trajectories or the flow's skin points;
* :mod:`.pipeline` — :func:`analyze_session` / :func:`analyze_frames`: the stages in order, results written as they
  come (:mod:`skinstretch.experiments.results_file`).
"""

from skinstretch.experiments.analysis.executor import make_executor
from skinstretch.experiments.analysis.parameters import (
    METHODS, AnalysisParams, ExecutionParams, GlassShadingParams, StrainParams, analysis_params,
)
from skinstretch.experiments.analysis.pipeline import analyze, analyze_frames, analyze_session, surface_kind
from skinstretch.experiments.analysis.plan import AnalysisPlan, plan_analysis

__all__ = [
    "AnalysisParams", "StrainParams", "GlassShadingParams", "ExecutionParams", "METHODS", "analysis_params",
    "make_executor", "analyze", "analyze_frames", "analyze_session", "surface_kind", "AnalysisPlan", "plan_analysis",
]
