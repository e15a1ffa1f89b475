"""The analysis plan (one place for surface- and clip-dependent choices) and one default per parameter."""

import json

import pytest

from skinstretch.experiments.analysis import AnalysisParams
from skinstretch.experiments.analysis.parameters import analysis_params
from skinstretch.experiments.analysis.plan import plan_analysis, plan_rows
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.tracking import TrackingParams
from skinstretch.processing.trajectory_anchoring import GLASS_SMOOTHING_KEY_FRAMES, SHAPE_SMOOTHING_KEY_FRAMES


def test_one_default_per_parameter():
    """A stage's own defaults are the analysis' defaults, however the parameters are built."""
    built = AnalysisParams(tracking=TrackingParams())
    assert analysis_params({"tracking": {}}) == built == analysis_params({}) == AnalysisParams()
    t = analysis_params({}).tracking
    assert (t.smoothing_radius_frames, t.max_bridge_frames) == (0, None)
    # a field given changes that field only
    assert analysis_params({"tracking": {"max_bridge_frames": 1}}).tracking == TrackingParams(max_bridge_frames=1)


def test_a_refused_parameter_is_one_line():
    with pytest.raises(InvalidInputError) as exc:
        analysis_params({"tracking": {"max_bridge_frames": -1, "search_radius_mm": 0}})
    text = str(exc.value)
    assert "\n" not in text
    assert "analysis.tracking.max_bridge_frames" in text and "analysis.tracking.search_radius_mm" in text
    with pytest.raises(InvalidInputError) as exc:
        analysis_params({"flow": {"no_such_option": 1}})
    assert "\n" not in str(exc.value) and "no_such_option" in str(exc.value)


def test_flow_over_a_ridge_records_the_local_prior_override():
    params = analysis_params({"flow": {"local_prior": True}})
    plan = plan_analysis(params, method="flow", n_frames=60, surface="ridge", shading_removed=True,
                         shading_status="applied (motion ratio 1.50)")
    assert not plan.plain_glass and plan.span_refiner
    assert plan.params.flow.local_prior is False and params.flow.local_prior is True
    (override,) = plan.overrides
    assert (override.parameter, override.asked, override.used) == ("flow.local_prior", True, False)
    record = json.loads(json.dumps(plan.to_dict()))
    assert record["overrides"][0]["parameter"] == "flow.local_prior" and record["local_prior"] is False


def test_flow_on_glass_applies_the_parameters_as_asked():
    params = analysis_params({})
    plan = plan_analysis(params, method="flow", n_frames=60, surface="flat")
    assert plan.plain_glass and plan.span_refiner and plan.overrides == ()
    assert plan.params == params


def test_shape_with_shading_left_in_turns_refinement_off_and_says_so():
    params = analysis_params({})
    flow = plan_analysis(params, method="flow", n_frames=24, surface="ridge", shading_removed=False,
                         shading_status="not applied: glass shading: the skin moved too little")
    assert not flow.span_refiner
    assert {o.parameter for o in flow.overrides} == {"flow.local_prior", "flow.refine_spans"}
    assert any("shading over the ridge was left in: the skin moved too little" in n for n in flow.notes)
    features = plan_analysis(params, method="features", n_frames=24, surface="ridge", shading_removed=False,
                             shading_status="not applied: glass shading: the skin moved too little")
    assert features.keyframe_smoothing_key_frames is None and not features.span_registration
    assert {(o.parameter, o.asked, o.used) for o in features.overrides} == {
        ("tracking.keyframe_interval_frames", 5, None), ("subpixel.register_spans", True, False)}


def test_features_anchoring_follows_the_surface():
    params = analysis_params({})
    glass = plan_analysis(params, method="features", n_frames=60, surface=None)
    shape = plan_analysis(params, method="features", n_frames=60, surface="valley", shading_removed=True)
    assert glass.keyframe_smoothing_key_frames == GLASS_SMOOTHING_KEY_FRAMES and glass.span_registration
    assert shape.keyframe_smoothing_key_frames == SHAPE_SMOOTHING_KEY_FRAMES and not shape.span_registration
    assert glass.overrides == ()
    (override,) = shape.overrides  # the span registration asked for (the default) is not applied, and says why
    assert (override.parameter, override.used) == ("subpixel.register_spans", False)
    assert "over a valley" in override.reason and shape.params.subpixel.register_spans is False


def test_the_direct_span_registration_can_be_switched_off():
    """Its ablation row's switch: the chained motion alone, on glass too."""
    plan = plan_analysis(analysis_params({"subpixel": {"register_spans": False}}), method="features", n_frames=60)
    assert plan.plain_glass and not plan.span_registration and plan.overrides == ()
    assert plan.keyframe_smoothing_key_frames == GLASS_SMOOTHING_KEY_FRAMES  # the key frames stay


def test_the_clip_length_is_planned_or_refused():
    params = analysis_params({})
    short = plan_analysis(params, method="features", n_frames=10)
    assert short.params.tracking.min_length_frames == 5 and short.to_dict()["min_track_frames"] == 5
    assert any("10-frame clip" in n for n in short.notes) and any("no strain over 11" in n for n in short.notes)
    with pytest.raises(InsufficientDataError, match="give at most 12"):
        plan_analysis(analysis_params({"tracking": {"min_length_frames": 20}}), method="features", n_frames=12)
    with pytest.raises(InsufficientDataError):
        plan_analysis(params, method="flow", n_frames=1)


def test_the_summary_holds_the_plan(analysed_study):
    from skinstretch.experiments.results_file import read_results

    for name, method, glass in (("000-flat-r1", "features", True), ("001-ridge-r1", "flow", False)):
        trial = analysed_study / "s01" / "study" / name / "analysis"
        summary = json.loads((trial / "summary.json").read_text())
        assert summary["plan"]["method"] == method and summary["plan"]["plain_glass"] is glass
        r = read_results(trial / "results.h5")
        assert r.plan == summary["plan"]
        assert r.params["flow"]["local_prior"] is glass  # the parameters recorded are the ones used


@pytest.mark.parametrize(("flags", "message"), [
    (["--min-track", "0"], "--min-track: Input should be greater than or equal to 1"),
    (["--span", "0,11"], "--span: Value error, spans must be positive frame counts, got [0, 11]"),
])
def test_the_command_line_delegates_to_the_parameters(tmp_path, capsys, flags, message):
    """The flags' ranges are the parameters' (one validation path): refused in one line, exit status 2."""
    from skinstretch.cli import main

    assert main(["analyze", str(tmp_path / "none.h5"), "-o", str(tmp_path / "out"), *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith(message) and "\n" not in err


def test_a_lossy_source_raises_the_model_error_left_at_its_default():
    from skinstretch.processing.measurement_uncertainty import LOSSY_MODEL_SIGMA_PX, MODEL_SIGMA_PX

    plan = plan_analysis(analysis_params({}), method="features", n_frames=60, lossy_source=True)
    assert {o.parameter: (o.asked, o.used) for o in plan.overrides} == {
        "flow.model_sigma_px": (MODEL_SIGMA_PX, LOSSY_MODEL_SIGMA_PX),
        "subpixel.model_sigma_px": (MODEL_SIGMA_PX, LOSSY_MODEL_SIGMA_PX)}
    assert plan.params.subpixel.model_sigma_px == LOSSY_MODEL_SIGMA_PX
    assert any("lossy compression" in n for n in plan.notes)
    kept = plan_analysis(analysis_params({"flow": {"model_sigma_px": 0.02}, "subpixel": {"model_sigma_px": 0.02}}),
                         method="flow", n_frames=60, lossy_source=True)  # the user's values are kept
    assert kept.overrides == () and kept.params.flow.model_sigma_px == 0.02 and kept.notes == ()
    assert plan.shared_sigma_px == 0.0  # the codec's error not measured: the fixed term, all of it independent


def test_a_measured_codec_error_enters_the_points_errors_and_its_shared_part_leaves_strain_alone():
    import math

    from skinstretch.experiments.codec_error import CodecError
    from skinstretch.processing.measurement_uncertainty import MODEL_SIGMA_PX

    plan = plan_analysis(analysis_params({}), method="flow", n_frames=60, lossy_source=True,
                         codec_error=CodecError(sigma_px=0.05, independent_px=0.03, how="given", n_points=100))
    assert plan.params.flow.model_sigma_px == pytest.approx(math.hypot(MODEL_SIGMA_PX, 0.05), abs=1e-4)
    assert plan.shared_sigma_px == pytest.approx(0.04) and plan.to_dict()["shared_sigma_px"] == plan.shared_sigma_px
    assert any("measured at import, 0.050 px (0.040 px of it shared" in n for n in plan.notes), plan.notes
    assert ("codec error shared by neighbours", "0.04 px (strain does not see it)") in plan_rows(plan.to_dict())
