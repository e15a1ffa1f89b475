"""The deformation field: exact inverse, exact gradient, zero strain for rigid translation, ridge mechanics sign."""

import numpy as np
import pytest

from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.deformation import (
    DeformationModel,
    MotionProfile,
    PlasticDistortion,
    RidgeMechanics,
    green_lagrange,
)
from skinstretch.simulators.surfaces import RuledSurface


def _model(**kw):
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (1.0, 0.4, 2.0, 6.0), (2.0, -0.3, 3.0, -4.0)])
    return DeformationModel(
        motion=motion,
        plastic=PlasticDistortion(semi_axes_mm=(2.5, 3.0), band_mm=2.0, stick=0.3, lag_mm=0.15, stick_slip_mm=0.05),
        mechanics=RidgeMechanics(peak_strain=0.05, center_s_mm=0.5, sigma_mm=0.75),
        rotation_center_mm=(0.3, -0.2),
        **kw,
    )


@pytest.fixture
def skin_points(rng):
    return rng.uniform(-6, 6, size=(4000, 2))


@pytest.mark.parametrize("t", [0.37, 1.0, 1.6])
def test_inverse_undoes_forward(skin_points, t):
    d = _model().at(t)
    x = d.forward(skin_points)
    # 1e-6 mm is 6e-5 px at the full field's 62 px/mm: far below any tracker's error.
    np.testing.assert_allclose(d.inverse(x), skin_points, atol=1e-6)
    np.testing.assert_allclose(d.inverse_reference(x), skin_points, atol=1e-6)
    assert np.median(np.abs(d.inverse(x) - skin_points)) < 1e-10


def test_gradient_matches_finite_differences(skin_points):
    d = _model().at(1.3)
    _, h = d.displacement(skin_points, with_gradient=True)
    e = 1e-6
    for j in range(2):
        step = np.zeros(2)
        step[j] = e
        fd = (d.displacement(skin_points + step) - d.displacement(skin_points - step)) / (2 * e)
        np.testing.assert_allclose(h[:, :, j], fd, atol=1e-6)


def test_frame_zero_is_undeformed(skin_points):
    d = _model().at(0.0)
    assert np.all(d.displacement(skin_points) == 0.0)


@pytest.mark.parametrize("velocity", [(0.0, 1.5), (2.0, -0.5), (-4.9, 0.3)])
def test_pure_translation_has_exactly_zero_strain(skin_points, velocity):
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (3.0, 3 * velocity[0], 3 * velocity[1], 0.0)])
    model = DeformationModel(motion=motion)  # no lag, no stick, no mechanics: rigid sliding
    for t in (0.5, 2.9):
        disp, h = model.at(t).displacement(skin_points, with_gradient=True)
        assert np.all(h == 0.0)
        assert np.all(green_lagrange(h) == 0.0)
        np.testing.assert_allclose(disp, np.broadcast_to(np.multiply(velocity, t), disp.shape), atol=1e-12)


def test_rotation_is_strain_free_to_precision(skin_points):
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (1.0, 0.5, 0.0, 12.0)])
    _, h = DeformationModel(motion=motion).at(1.0).displacement(skin_points, with_gradient=True)
    assert np.max(np.abs(green_lagrange(h))) < 1e-14


def test_rotation_is_counter_clockwise_on_the_image():
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (1.0, 0.0, 0.0, 90.0)])
    x = DeformationModel(motion=motion).at(1.0).forward(np.array([[1.0, 0.0]]))
    np.testing.assert_allclose(x, [[0.0, -1.0]], atol=1e-12)  # right of centre -> up the image (y down)


@pytest.mark.parametrize("direction", [1.0, -1.0])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_ridge_compresses_before_and_expands_after_between_frames(sign, direction):
    """Seed 6.3.2: between consecutive frames, skin approaching a ridge compresses and skin past it expands
    (reversed for a valley), in whichever direction the finger slides."""
    surface = RuledSurface(kind="ridge" if sign > 0 else "valley")
    sig = surface.sigma_mm
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (4.0, 0.0, direction * 4.0, 0.0)])  # 1 mm/s along +-s
    model = DeformationModel(motion=motion, mechanics=RidgeMechanics(peak_strain=sign * 0.04, sigma_mm=sig))
    dt, h = 1.0 / 60.0, 1e-3
    a, b = model.at(2.0), model.at(2.0 + dt)
    # Glass-fixed positions one sigma before / after the shape in the sliding direction, +-h along s.
    now = np.array([[0.0, direction * p + e] for p in (-sig, sig) for e in (-h, h)])
    step = b.forward(a.inverse(now)) - now
    rate = (step[1::2, 1] - step[0::2, 1]) / (2 * h)  # change in stretch along s over one frame
    expected = 0.04 * (1.0 * dt) * np.exp(-0.5) / sig  # a v dt max|g'|
    np.testing.assert_allclose(sign * rate, [-expected, expected], rtol=0.05)
    # The skin now on the shape has been compressed (ridge) / stretched (valley) relative to frame 0.
    X = a.inverse(np.array([[0.0, 0.0]]))
    _, grad = a.displacement(X, with_gradient=True)
    assert sign * green_lagrange(grad)[0, 1] < -0.03


def test_ridge_lag_is_zero_in_frame_zero_and_far_from_the_shape():
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (2.0, 0.0, 2.0, 0.0)])
    model = DeformationModel(motion=motion, mechanics=RidgeMechanics(peak_strain=0.04, sigma_mm=0.75))
    pts = np.array([[0.3, -0.2], [1.0, 0.0]])
    assert np.all(model.at(0.0).displacement(pts) == 0.0)
    far = np.array([[0.0, -12.0]])  # never crossed the shape: moves with the bulk
    np.testing.assert_allclose(model.at(1.5).displacement(far), [[0.0, 1.5]], atol=1e-12)


def test_stick_keeps_the_ellipse_still_while_the_bulk_rotates():
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (1.0, 0.0, 0.0, 10.0)])
    model = DeformationModel(motion=motion, plastic=PlasticDistortion(semi_axes_mm=(2.0, 2.0), band_mm=1.0, stick=1.0))
    d = model.at(1.0)
    assert np.all(d.displacement(np.array([[0.5, 0.5], [-1.0, 0.3]])) == 0.0)
    far = np.array([[5.0, 0.0]])
    np.testing.assert_allclose(d.forward(far), [[5 * np.cos(np.pi / 18), -5 * np.sin(np.pi / 18)]], atol=1e-12)


def test_invalid_parameters_are_named():
    with pytest.raises(InvalidInputError, match="keyframe times"):
        MotionProfile.from_keyframes([(0, 0, 0, 0), (0, 1, 1, 0)])
    with pytest.raises(InvalidInputError, match="stick"):
        PlasticDistortion(stick=2.0)
    with pytest.raises(InvalidInputError, match="peak_strain"):
        RidgeMechanics(peak_strain=0.9)


def test_surface_profile_and_arc_length():
    r = RuledSurface(kind="ridge", width_mm=3.0, height_mm=0.5)
    z = np.linspace(-5, 5, 101)
    s = r.arc_length(z)
    assert np.all(np.diff(s) > np.diff(z) - 1e-12)  # the arc is never shorter than its projection
    np.testing.assert_allclose(r.flat_coordinate(s), z, atol=1e-6)
    assert r.max_slope == pytest.approx(np.max(np.abs(r.slope(np.linspace(-3, 3, 20001)))), rel=1e-6)
    assert RuledSurface(kind="valley").height(0.0) == pytest.approx(-0.5)
    with pytest.raises(InvalidInputError, match="kind"):
        RuledSurface(kind="bump")


from hypothesis import given, settings
from hypothesis import strategies as st

_mm = st.floats(-8.0, 8.0, allow_nan=False)


@settings(max_examples=40, deadline=None)
@given(du=_mm, ds=_mm, t=st.floats(0.0, 3.0), u=_mm, s=_mm)
def test_any_rigid_translation_gives_exactly_zero_strain(du, ds, t, u, s):
    motion = MotionProfile.from_keyframes([(0, 0, 0, 0), (3.0, du, ds, 0.0)])
    d, h = DeformationModel(motion=motion).at(t).displacement(np.array([[u, s]]), with_gradient=True)
    assert np.all(green_lagrange(h) == 0.0)
    assert np.all(d == d[0])
