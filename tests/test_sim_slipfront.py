"""The travelling slip front: its truth is consistent (forward, compiled inverse, gradient), it is the band the
scene file describes, and it moves as the keyframes say."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.deformation import DeformationModel, MotionProfile, SlipFront
from skinstretch.simulators.scene import SceneRenderer, load_scene


def _model(amplitude=-0.04, direction=-90.0, width=0.8, bulk=((0, 0, 0, 0), (3, 0.1, 1.5, 2.0))):
    return DeformationModel(
        motion=MotionProfile.from_keyframes(bulk),
        slip_front=SlipFront(amplitude=amplitude, width_mm=width, direction_deg=direction,
                             keyframes=((0.0, -6.0), (3.0, 6.0))),
    )


points = st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=1, max_size=30).map(np.array)


@settings(max_examples=40, deadline=None)
@given(points, st.floats(0.05, 3.0), st.floats(-0.2, 0.2), st.floats(-180, 180))
def test_inverse_undoes_forward(X, t, amplitude, direction):
    d = _model(amplitude=amplitude, direction=direction).at(t)
    x = d.forward(X)
    np.testing.assert_allclose(d.inverse(x, iterations=8), X, atol=1e-9)
    np.testing.assert_allclose(d.inverse(x, iterations=8), d.inverse_reference(x, iterations=8), atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(points, st.floats(0.1, 3.0))
def test_gradient_matches_finite_differences(X, t):
    d = _model().at(t)
    _, h = d.displacement(X, with_gradient=True)
    eps = 1e-6
    for j in range(2):
        e = np.zeros(2)
        e[j] = eps
        num = (d.displacement(X + e) - d.displacement(X - e)) / (2 * eps)
        np.testing.assert_allclose(h[..., :, j], num, atol=1e-7)


def test_band_strain_and_position():
    front = SlipFront(amplitude=-0.04, width_mm=0.8, direction_deg=-90.0, keyframes=((0.0, -6.0), (3.0, 6.0)))
    model = DeformationModel(motion=MotionProfile.from_keyframes([(0, 0, 0, 0)]), slip_front=front)
    assert np.all(model.at(0.0).displacement(np.random.default_rng(0).uniform(-5, 5, (50, 2))) == 0.0)
    s = np.linspace(-5, 5, 2001)
    X = np.column_stack([np.zeros_like(s), s])
    for t in (1.0, 1.5, 2.2):
        _, h = model.at(t).displacement(X, with_gradient=True)
        eyy = h[:, 1, 1]
        assert front.position(t) == pytest.approx(-6.0 + 4.0 * t)
        assert s[np.argmin(eyy)] == pytest.approx(front.position(t), abs=0.01)  # the band is where the front is
        assert eyy.min() == pytest.approx(-0.04, rel=1e-3)  # with the stated amplitude
        half = s[eyy <= -0.02]
        assert half.max() - half.min() == pytest.approx(0.8, abs=0.01)  # and width at half height
        np.testing.assert_allclose(h[:, 0, :], 0.0, atol=1e-15)  # uniaxial along the direction of travel
    # Skin the front has passed is shifted forward against skin it has not reached by -A sigma sqrt(2 pi).
    d = model.at(1.5).displacement(np.array([[0.0, -4.0], [0.0, 4.0]]))
    assert d[0, 1] - d[1, 1] == pytest.approx(0.04 * front.sigma_mm * np.sqrt(2 * np.pi), rel=1e-6)


def test_invalid_slip_fronts_are_named():
    with pytest.raises(InvalidInputError, match="amplitude"):
        SlipFront(amplitude=0.5)
    with pytest.raises(InvalidInputError, match="width_mm"):
        SlipFront(amplitude=0.01, width_mm=0.0)
    with pytest.raises(InvalidInputError, match="increase"):
        SlipFront(amplitude=0.01, keyframes=((1.0, 0.0), (0.5, 1.0)))


def test_slipfront_scene_truth_shows_the_band():
    scene = load_scene("slipfront")
    assert scene.slip_front.amplitude == -0.04 and scene.slip_front.width_mm == 0.8
    t = SceneRenderer(scene.model_copy(update={"n_frames": 91}), seed=0).truth()
    k = 90  # t = 1.5 s: the front at the skin's centre line
    eyy = np.where(t.displacement_valid[k], t.strain[k, ..., 1], 0.0)
    column = eyy[:, eyy.shape[1] // 2]
    assert column.min() == pytest.approx(-0.04, abs=0.004)
    # Between frames the band moves on: compression ahead of it, extension behind it.
    change = t.displacement[k, :, 40, 1] - t.displacement[k - 11, :, 40, 1]
    step = t.grid_y[1] - t.grid_y[0]
    strain11 = np.gradient(change, step)
    assert strain11.min() < -0.025 and strain11.max() > 0.025
    assert np.argmax(strain11) < np.argmin(strain11)  # extension above (behind), compression below (ahead)
