"""The analysis' parameters: one frozen pydantic model per stage, gathered in :class:`AnalysisParams`.

Each stage keeps its own model: extraction, tracking, sub-pixel refinement, flow and display mapping are the
processing layer's parameter classes (:mod:`skinstretch.processing.parameters`); strain/profile, glass shading and
execution are defined here. These models are the one validation: unknown fields and out-of-range values are
refused where the parameters enter (the command line and a protocol's ``analysis.options`` delegate to them, the
latter with file, line and field), and a stage's own defaults are the analysis' defaults. Everything is in mm,
degrees, frames and grey levels; the analysis converts to pixels once.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from skinstretch.processing.display_mapping import DisplayMappingParams
from skinstretch.processing.displacement_refinement import SubpixelParams
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.extraction import ExtractionParams
from skinstretch.processing.flow import FlowParams
from skinstretch.processing.parameters import describe_validation_error
from skinstretch.processing.tracking import TrackingParams

__all__ = ["AnalysisParams", "StrainParams", "GlassShadingParams", "ExecutionParams", "METHODS", "analysis_params"]

METHODS = ("features", "flow")


class _Stage(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class StrainParams(_Stage):
    """Strain and profile (seed 5.3).

    ``spans`` are the frame spans of the triangulation strain (seed 6.3.2: 1 and 11). ``max_edge_mm`` drops long
    hull slivers; ``min_spacing_mm`` leaves out of the triangulation a tracked point this close to an older track's
    (an edge's strain error is its ends' displacement error over its length: tracks a few pixels apart, two
    landmarks of one ridge, would give edges whose strain is mostly noise; the trajectories keep every point);
    ``profile_strip_mm`` is the strip width w of Figure 62 and ``profile_step_mm`` the spacing of profile
    positions. ``flow_stride`` subsamples the flow grid for triangulation (edges ~0.8 mm, like the feature
    triangulation's ~48 px, seed 6.3.3).
    """

    spans: tuple[int, ...] = (1, 11)
    max_edge_mm: float = Field(2.0, gt=0)
    min_spacing_mm: float = Field(0.35, ge=0)
    profile_strip_mm: float = Field(1.0, gt=0)
    profile_step_mm: float = Field(0.25, gt=0)
    flow_stride: int = Field(4, ge=1)

    @field_validator("spans")
    @classmethod
    def _positive_spans(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if not v or any(s < 1 for s in v):
            raise ValueError(f"spans must be positive frame counts, got {list(v)}")
        return tuple(dict.fromkeys(int(s) for s in v))


class GlassShadingParams(_Stage):
    """Removal of brightness patterns that stay on the prism while the skin slides
    (:mod:`skinstretch.processing.glass_shading`: partial contact and slope lighting over a ridge or a valley bias
    every motion estimate towards zero there).

    ``enabled``: True / False, or None for "when the session's surface is not flat" (resolved by the analysis plan).
    ``smooth_mm`` smooths the per-pixel maps across the shape and ``along_shape_mm`` along it (the shape's band must
    then lie along an image axis within a degree or so); a sequence whose skin moved less than ``min_motion``
    (temporal over spatial contrast) is left as it is, and over a valley less than ``min_motion_valley`` (its shading
    is much the stronger: left in, it reverses the profile). The clips behind these values: docs/tuning-log.md.
    """

    enabled: bool | None = None
    smooth_mm: float = Field(0.025, gt=0)
    along_shape_mm: float = Field(1.0, gt=0)
    min_motion: float = Field(1.0, ge=0)
    min_motion_valley: float = Field(0.4, ge=0)


class ExecutionParams(_Stage):
    """How the measurement runs in parallel, chosen once per run (:func:`skinstretch.experiments.analysis.executor.
    make_executor`): ``processes`` (worker processes, each measuring a chunk of frames; the default), ``threads``
    (of this process) or ``serial``; ``workers`` of them. Inside a worker process (a Dask task, the recorder's
    analysis process) the analysis keeps to threads of that process."""

    kind: Literal["processes", "threads", "serial"] = "processes"
    workers: int = Field(2, ge=1, le=64)


class AnalysisParams(_Stage):
    """Every parameter of the analysis, one model per stage. ``robust_matching`` predicts feature displacements
    from the measured global motion (:class:`skinstretch.processing.global_motion.GlobalMotionEstimator`); kept
    though the ablation's slow clips never need it: a slide of several px a frame that starts or reverses loses the
    seed's prediction (tests/test_track_matching.py). ``subpixel`` None leaves displacements at the extraction's
    accuracy."""

    extraction: ExtractionParams = ExtractionParams()
    tracking: TrackingParams = TrackingParams()
    subpixel: SubpixelParams | None = SubpixelParams()
    robust_matching: bool = True
    flow: FlowParams = FlowParams()
    display: DisplayMappingParams = DisplayMappingParams()
    strain: StrainParams = StrainParams()
    glass_shading: GlassShadingParams = GlassShadingParams()
    execution: ExecutionParams = ExecutionParams()

    def to_dict(self) -> dict[str, Any]:
        """JSON-able nested dict (what the results' ``params_json`` records)."""
        return self.model_dump(mode="json")


def analysis_params(options: dict[str, Any] | AnalysisParams | None = None, **stages: Any) -> AnalysisParams:
    """AnalysisParams from nested options (a protocol's ``analysis.options``, a dict of stages and fields), with
    ``stages`` overriding whole stages; InvalidInputError names every bad field."""
    if isinstance(options, AnalysisParams):
        return options.model_copy(update=stages) if stages else options
    try:
        return AnalysisParams.model_validate({**dict(options or {}), **stages})
    except ValidationError as exc:
        raise InvalidInputError(describe_validation_error(exc, "analysis")) from None
