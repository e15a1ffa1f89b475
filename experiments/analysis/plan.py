"""The analysis plan: every choice that depends on the surface or the clip, resolved once before the measurement.

:func:`plan_analysis` turns the parameters asked for, the method, the clip's length, the session's surface and the
glass-shading step's outcome into a frozen :class:`AnalysisPlan`; :func:`~skinstretch.experiments.analysis.pipeline.
analyze` only executes it. A parameter is never replaced silently: one the clip cannot satisfy is refused
(:func:`refuse_unfit_clip`), and one the plan does not apply as asked is listed in ``overrides`` with the value
asked for, the value used and why. The plan is written to the summary (``plan``) and the results' ``plan_json``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

from skinstretch.experiments.analysis.parameters import AnalysisParams, GlassShadingParams
from skinstretch.experiments.codec_error import CodecError
from skinstretch.processing.errors import InsufficientDataError
from skinstretch.processing.measurement_uncertainty import LOSSY_MODEL_SIGMA_PX, MODEL_SIGMA_PX
from skinstretch.processing.tracking import DEFAULT_MIN_LENGTH_FRAMES, min_length_for_clip
from skinstretch.processing.trajectory_anchoring import GLASS_SMOOTHING_KEY_FRAMES, SHAPE_SMOOTHING_KEY_FRAMES

__all__ = ["AnalysisPlan", "Override", "plan_analysis", "plan_rows", "refuse_unfit_clip", "clip_notes",
           "on_plain_glass", "wants_glass_shading", "shading_min_motion"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Override:
    """A parameter the plan does not apply as asked: its dotted name, the value asked for, the value used, why."""

    parameter: str
    asked: Any
    used: Any
    reason: str

    def describe(self) -> str:
        return f"{self.parameter}: asked {self.asked!r}, used {self.used!r} ({self.reason})"


@dataclass(frozen=True)
class AnalysisPlan:
    """What the analysis of one clip does, decided once.

    ``params`` are the parameters as applied (``overrides`` says where they differ from those asked for);
    ``plain_glass``: flat (or unknown) surface and no glass shading removed; ``keyframe_smoothing_key_frames``:
    the key-frame anchoring's smoothing window (None: no anchoring); ``span_registration``: the feature method's
    longer spans registered directly between their frames; ``span_refiner``: the flow's longer spans (and cumulative
    fields) refined by registering their own frames; ``notes``: what the clip's length changed, one sentence each;
    ``shared_sigma_px``: the part of every point's predicted error (px per axis) that neighbours share and strain
    does not see (a lossy codec's, as the import measured it).
    """

    method: str
    n_frames: int
    surface: str | None
    glass_shading: str
    plain_glass: bool
    params: AnalysisParams
    keyframe_smoothing_key_frames: int | None
    span_registration: bool
    span_refiner: bool
    overrides: tuple[Override, ...] = ()
    notes: tuple[str, ...] = ()
    shared_sigma_px: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        """The JSON-able record (summary ``plan``); the parameters themselves are the results' ``params_json``."""
        return {
            "method": self.method,
            "n_frames": self.n_frames,
            "surface": self.surface,
            "glass_shading": self.glass_shading,
            "plain_glass": self.plain_glass,
            "keyframe_anchoring": self.keyframe_smoothing_key_frames is not None,
            "keyframe_smoothing_key_frames": self.keyframe_smoothing_key_frames,
            "span_registration": self.span_registration,
            "span_refiner": self.span_refiner,
            "local_prior": bool(self.params.flow.local_prior) if self.method == "flow" else None,
            "min_track_frames": self.params.tracking.min_length_frames if self.method == "features" else None,
            "shared_sigma_px": self.shared_sigma_px,
            "overrides": [dataclasses.asdict(o) for o in self.overrides],
        }


def wants_glass_shading(gs: GlassShadingParams, surface: str | None) -> bool:
    """Whether the glass-shading step runs: as ``enabled`` says, or (None) when the surface is not flat."""
    return gs.enabled if gs.enabled is not None else surface not in (None, "", "flat")


def shading_min_motion(gs: GlassShadingParams, surface: str | None) -> float:
    """The skin motion (temporal over spatial contrast) below which the shading is left in: a valley has its own
    gate (its shading is much the stronger)."""
    return gs.min_motion_valley if surface == "valley" else gs.min_motion


def on_plain_glass(shading_removed: bool, surface: str | None) -> bool:
    """Whether the skin slides on plain glass as far as the motion measurement knows: a flat (or unknown) surface
    and no glass-fixed shading removed. Only then is a feature method's longer span registered directly between its
    frames and does the flow's pair registration use its local prior: over a ridge or valley both would follow what
    is left of the glass-fixed patterns (docs/tuning-log.md, "analysis plan")."""
    return not shading_removed and surface in (None, "", "flat")


def refuse_unfit_clip(params: AnalysisParams, n_frames: int, method: str) -> None:
    """Refuse (InsufficientDataError, one line) what a clip of ``n_frames`` cannot satisfy."""
    if n_frames < 2:
        raise InsufficientDataError(f"a session needs at least 2 frames to measure motion, got {n_frames}")
    given = params.tracking.min_length_frames
    if method == "features" and given is not None and given > n_frames:
        raise InsufficientDataError(
            f"the minimum trajectory length ({given} frames, --min-track) is longer than the {n_frames}-frame "
            f"session: no trajectory could be kept; give at most {n_frames}"
        )


def clip_notes(params: AnalysisParams, n_frames: int, method: str) -> list[str]:
    """What a clip of ``n_frames`` changes in the analysis asked for by ``params`` (the minimum trajectory length
    left to its default adapts to a short clip; a strain span as long as the clip has no pair), one sentence each:
    the summary keeps them (``notes``) so that a short clip never gives a silent empty result."""
    notes = []
    if method == "features" and params.tracking.min_length_frames is None:
        effective = min_length_for_clip(n_frames)
        if effective < DEFAULT_MIN_LENGTH_FRAMES:
            notes.append(f"a {n_frames}-frame clip is shorter than the default minimum trajectory length "
                         f"({DEFAULT_MIN_LENGTH_FRAMES} frames): trajectories of at least {effective} frames are kept "
                         "(set --min-track to choose)")
    too_long = [int(s) for s in params.strain.spans if int(s) >= n_frames]
    if too_long:
        names = ", ".join(str(s) for s in too_long)
        notes.append(f"no strain over {names} frame{'s' if too_long != [1] else ''}: the {n_frames}-frame session "
                     f"has no frame pair that far apart (--span up to {n_frames - 1})")
    return notes


def plan_analysis(params: AnalysisParams, *, method: str, n_frames: int, surface: str | None = None,
                  shading_removed: bool = False, shading_status: str = "off",
                  lossy_source: bool = False, codec_error: CodecError | None = None) -> AnalysisPlan:
    """The plan of one analysis (see :class:`AnalysisPlan`); ``shading_removed``/``shading_status``: the outcome of
    the glass-shading step (:func:`~skinstretch.experiments.analysis.frames.estimate_shading`); ``lossy_source``:
    frames through lossy video compression, whose error the predicted errors then include: ``codec_error`` as the
    import measured it (:mod:`~skinstretch.experiments.codec_error`), else a fixed term. Refuses a clip the
    parameters cannot fit (:func:`refuse_unfit_clip`); notes are logged as warnings, overrides as information."""
    refuse_unfit_clip(params, n_frames, method)
    notes = clip_notes(params, n_frames, method)
    overrides: list[Override] = []
    shared = 0.0
    if lossy_source:
        sigma = None if codec_error is None else codec_error.sigma_px
        params, lossy, term = _for_lossy_source(params, sigma)
        overrides += lossy
        if lossy:
            if codec_error is not None:
                shared = round(codec_error.shared_px, 4)
            why = (f"the codec's error measured at import, {sigma:.3f} px ({shared:.3f} px of it shared by "
                   "neighbouring points, which strain does not see)" if sigma is not None
                   else "a fixed codec term (the import did not measure the codec's error)")
            notes.append(f"the predicted errors include {term} px per axis for the lossy compression, from {why} ("
                         + ", ".join(o.parameter for o in lossy) + f" {term} instead of {MODEL_SIGMA_PX}; set them "
                         "to choose)")
    if not shading_removed and shading_status.startswith("not applied") and surface not in (None, "", "flat"):
        # Said out loud: over a shape the shading left in biases the motion there (known gaps, short clips).
        reason = shading_status.removeprefix("not applied: ").removeprefix("glass shading: ").split(";")[0]
        notes.append(f"the glass-fixed shading over the {surface} was left in: {reason}. The motion across the shape "
                     "may read too small and its strain be biased; a longer slide over the shape lets the analysis "
                     "remove it")
    glass = on_plain_glass(shading_removed, surface)
    tracking, flow = params.tracking, params.flow
    where = f"over a {surface}" if surface not in (None, "", "flat") else "with glass shading removed"
    smoothing = None
    subpixel = params.subpixel
    span_registration = span_refiner = False
    if method == "features":
        if tracking.min_length_frames is None:
            tracking = dataclasses.replace(tracking, min_length_frames=min_length_for_clip(n_frames))
        registered = params.subpixel is not None and (glass or shading_removed)
        if tracking.keyframe_interval_frames is not None:
            if registered:
                smoothing = GLASS_SMOOTHING_KEY_FRAMES if glass else SHAPE_SMOOTHING_KEY_FRAMES
            else:
                why = ("no sub-pixel refinement" if params.subpixel is None
                       else f"{where} with its glass shading left in")
                overrides.append(Override("tracking.keyframe_interval_frames", tracking.keyframe_interval_frames,
                                          None, f"key-frame anchoring needs registration on glass: {why}"))
                tracking = dataclasses.replace(tracking, keyframe_interval_frames=None)
        asked = params.subpixel is not None and params.subpixel.register_spans
        span_registration = asked and registered and glass
        if asked and not span_registration:
            overrides.append(Override("subpixel.register_spans", True, False,
                                      f"{where} a span's direct registration would follow the glass-fixed "
                                      "patterns that the shading step leaves or did not remove"))
            subpixel = dataclasses.replace(params.subpixel, register_spans=False)
    else:
        if flow.local_prior and not glass:
            overrides.append(Override("flow.local_prior", True, False,
                                      f"{where} the local prior lets what the shading step leaves into each field"))
            flow = dataclasses.replace(flow, local_prior=False)
        if flow.refine_spans:
            span_refiner = glass or shading_removed
            if not span_refiner:
                overrides.append(Override("flow.refine_spans", True, False,
                                          f"{where} with its glass shading left in the refinement would follow the "
                                          "shading itself"))
                flow = dataclasses.replace(flow, refine_spans=False)
    used = params.model_copy(update={"tracking": tracking, "flow": flow, "subpixel": subpixel})
    for note in notes:
        log.warning("%s", note)
    for override in overrides:
        log.info("plan: %s", override.describe())
    return AnalysisPlan(method=method, n_frames=int(n_frames), surface=surface or None, glass_shading=shading_status,
                        plain_glass=glass, params=used, keyframe_smoothing_key_frames=smoothing,
                        span_registration=span_registration, span_refiner=span_refiner,
                        overrides=tuple(overrides), notes=tuple(notes), shared_sigma_px=shared)


def _for_lossy_source(params: AnalysisParams, codec_sigma_px: float | None
                      ) -> tuple[AnalysisParams, list[Override], float]:
    """``params`` whose predicted errors include a lossy codec's: ``model_sigma_px`` of the flow and the sub-pixel
    stages raised to the model term and ``codec_sigma_px`` in quadrature (None: :data:`LOSSY_MODEL_SIGMA_PX`)
    where left at the default (a value the user set is kept); with the overrides and the term used."""
    term = (LOSSY_MODEL_SIGMA_PX if codec_sigma_px is None
            else round(math.hypot(MODEL_SIGMA_PX, float(codec_sigma_px)), 4))
    changed, overrides = {}, []
    for stage in ("flow", "subpixel"):
        p = getattr(params, stage)
        if p is not None and p.model_sigma_px == MODEL_SIGMA_PX:
            changed[stage] = dataclasses.replace(p, model_sigma_px=term)
            overrides.append(Override(f"{stage}.model_sigma_px", MODEL_SIGMA_PX, term,
                                      "frames imported from lossy compression"))
    return (params.model_copy(update=changed) if changed else params), overrides, term


def plan_rows(plan: dict[str, Any]) -> list[tuple[str, str]]:
    """The plan recorded in a summary (:meth:`AnalysisPlan.to_dict`) as (what, value) rows for a person: the report's
    table and the viewer's panel. Empty for results written before the plan was recorded."""
    if not plan:
        return []

    def on(value: Any) -> str:
        return "on" if value else "off"

    rows = [("method", str(plan.get("method"))), ("frames", str(plan.get("n_frames"))),
            ("surface", str(plan.get("surface") or "unknown")), ("glass shading", str(plan.get("glass_shading"))),
            ("plain glass", "yes" if plan.get("plain_glass") else "no")]
    if plan.get("method") == "features":
        smoothing = plan.get("keyframe_smoothing_key_frames")
        rows += [("key-frame anchoring", f"on, smoothed over {smoothing} key frames" if smoothing else "off"),
                 ("span registration", on(plan.get("span_registration"))),
                 ("minimum trajectory length", f"{plan.get('min_track_frames')} frames")]
    else:
        rows += [("span refiner", on(plan.get("span_refiner"))), ("local prior", on(plan.get("local_prior")))]
    if plan.get("shared_sigma_px"):
        rows.append(("codec error shared by neighbours", f"{plan['shared_sigma_px']} px (strain does not see it)"))
    for o in plan.get("overrides") or []:
        rows.append((f"override: {o['parameter']}", f"asked {o['asked']!r}, used {o['used']!r}: {o['reason']}"))
    return rows
