"""The stretch profile along the sliding direction (seed 5.3.2, Figure 62/94) and the seed's finding (6.3.2):
between consecutive frames the skin compresses before a ridge and expands after it, the reverse for a valley,
and a flat surface shows no such pattern (a much smaller profile)."""


import numpy as np
import pytest

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.stretch import StretchProfile, horizontal_stretch_profile, mean_profile, profile_pattern
from skinstretch.processing.tracking import MotionSample


def _sample(x, d):
    pts = np.column_stack([x, np.zeros_like(x)])
    return MotionSample(0, 1, pts, np.column_stack([d, np.zeros_like(d)]), np.arange(len(x)))


def test_profile_is_exact_for_a_linear_field_however_the_points_are_spread():
    # Points crowd towards small x (like features thinning out into a dark band): the two strips' mean positions
    # are not their centres, so dividing by the strip width would under-read the stretch.
    x = 400.0 * np.random.default_rng(3).power(0.5, 4000)
    prof = horizontal_stretch_profile(
        _sample(x, 0.01 * x + 2.0), fingertip_displacement=np.array([2.0, 0.0]),
        x_positions=np.arange(60.0, 341.0, 20.0), strip_width_px=40.0,
    )
    assert prof.valid.all()
    np.testing.assert_allclose(prof.change, 0.01, rtol=1e-9)


def test_positions_whose_strips_are_not_covered_are_invalid():
    x = np.concatenate([np.linspace(0, 150, 300), np.linspace(250, 400, 300)])  # no skin seen in (150, 250)
    prof = horizontal_stretch_profile(
        _sample(x, 0.02 * x), fingertip_displacement=np.zeros(2), x_positions=np.arange(40.0, 361.0, 10.0),
        strip_width_px=40.0,
    )
    inside_gap = (prof.x > 150 + 10) & (prof.x < 250 - 10)
    assert not prof.valid[inside_gap].any()
    far = (prof.x <= 130) | (prof.x >= 270)
    assert prof.valid[far].all()
    np.testing.assert_allclose(prof.change[prof.valid], 0.02, rtol=1e-9)
    assert np.isnan(prof.change[~prof.valid]).all()
    with pytest.raises(InvalidInputError, match="min_points"):
        horizontal_stretch_profile(_sample(x, x), fingertip_displacement=np.zeros(2), x_positions=x[:3],
                                   strip_width_px=4.0, min_points=0)


def test_mean_profile_needs_min_pairs():
    x = np.arange(3.0)
    a = StretchProfile(x, np.array([1.0, np.nan, 3.0]), np.array([True, False, True]))
    b = StretchProfile(x, np.array([3.0, 2.0, np.nan]), np.array([True, True, False]))
    m = mean_profile([a, b], min_pairs=2)
    assert m.valid.tolist() == [True, False, False]
    assert m.change[0] == 2.0 and np.isnan(m.change[1:]).all()
    assert mean_profile([a, b]).valid.all()
    with pytest.raises(InvalidInputError, match="min_pairs"):
        mean_profile([a], min_pairs=0)


def test_profile_pattern_orders_the_lobes_along_the_sliding_direction():
    x = np.linspace(0.0, 10.0, 41)
    z = x - 5.0
    ridge = StretchProfile(x, z * np.exp(-0.5 * z**2), np.ones_like(x, bool))  # compression at x < 5
    p = profile_pattern(ridge, direction=1.0)
    assert p.compression_first and p.compression_at == pytest.approx(4.0) and p.expansion_at == pytest.approx(6.0)
    assert not profile_pattern(ridge, direction=-1.0).compression_first
    assert p.amplitude == pytest.approx(np.sqrt(np.mean((z * np.exp(-0.5 * z**2)) ** 2)))
    with pytest.raises(InvalidInputError, match="direction"):
        profile_pattern(ridge, direction=0.0)
    with pytest.raises(InsufficientDataError):
        profile_pattern(StretchProfile(x, ridge.change, x < 0.3), direction=1.0)
    # An edge value (skin at the contact boundary) is left out with a margin.
    edged = StretchProfile(x, np.where(x > 9.9, -1.0, ridge.change), ridge.valid)
    assert not profile_pattern(edged, direction=1.0).compression_first
    inner = profile_pattern(edged, direction=1.0, margin=1.0)
    assert inner.compression_first and (inner.compression_at, inner.expansion_at) == (p.compression_at, p.expansion_at)


# ----------------------------------------------------------------------------- the seed's finding, simulated


def _true_pattern(name, n_frames):
    """Seed Figure 94 from the simulator's true motion of a short session (no rendering needed)."""
    from skinstretch.experiments.analysis.derive import stretch_profile
    from skinstretch.experiments.evaluation.tracking import TruthField
    from skinstretch.simulators.scene import SceneRenderer, load_scene

    r = SceneRenderer(load_scene(name), seed=0)
    tf = TruthField(r.truth(n_frames))
    px = r.calibration.px_per_mm
    samples = [tf.grid_motion(k, k + 1, stride=2) for k in range(n_frames - 1)]
    ft = np.array([s.displacement.mean(axis=0) for s in samples])
    positions = np.arange(0.25 * px, r.camera_mode.height - 0.125 * px, 0.25 * px)
    prof = stretch_profile(samples, ft, axis=1, positions=positions, strip_px=px)  # the finger slides along y
    shape_y = float(r.optics.surface_to_image(np.array([0.0, r.surface.center_mm]))[1])
    return profile_pattern(prof, direction=np.sign(ft[:, 1].sum()), margin=px), shape_y


def test_true_profile_compresses_before_a_ridge_and_expands_after_it_reversed_for_a_valley():
    ridge, ridge_y = _true_pattern("ridgeL", 40)
    valley, valley_y = _true_pattern("valleyL", 40)
    flat, _ = _true_pattern("flatL", 40)
    # The sliding is along +y in both: "before" the shape is at smaller y.
    assert ridge.compression_first and ridge.compression_at < ridge_y < ridge.expansion_at
    assert not valley.compression_first and valley.expansion_at < valley_y < valley.compression_at
    assert flat.amplitude < 0.4 * min(ridge.amplitude, valley.amplitude)


@pytest.fixture(scope="module")
def measured():
    """The feature method on short rendered sessions, evaluated against their truth."""
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.experiments.evaluation.tracking import TruthField, evaluate_profile
    from skinstretch.simulators.scene import render_session

    params = analysis_params({"tracking": {"min_length_frames": 10}})
    out = {}
    for name in ("ridgeL", "flatL"):
        s = render_session(name, n_frames=40, seed=0)
        r = analyze_frames(s.frames, calibration=s.calibration, method="features", params=params)
        out[name] = evaluate_profile(r, TruthField(s.truth), strip_px=s.calibration.px(params.strain.profile_strip_mm))
    return out


def test_measured_profile_shows_the_ridge_pattern_and_flat_has_none(measured):
    ridge, flat = measured["ridgeL"], measured["flatL"]
    assert ridge["compression_first"] is True and ridge["true_compression_first"] is True
    assert ridge["correlation"] > 0.8
    assert flat["compression_first"] is None and np.isnan(flat["correlation"]) and "flat surface" in flat["note"]
    assert flat["amplitude"] < 0.4 * ridge["amplitude"]
