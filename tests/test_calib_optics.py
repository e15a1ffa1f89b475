"""PrismOptics: the forward model of the seed's prism rig and its numerical inverse (seed 3.2-3.4)."""

import math

import numpy as np
import pytest

from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.prism_optics import PrismOptics, prism_optics_for_scene
from skinstretch.simulators.surfaces import RuledSurface

KINDS = ("flat", "ridge", "valley")


def _optics(kind, **kw):
    return PrismOptics(surface=RuledSurface(kind=kind, center_mm=0.4), **kw)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize(
    "params",
    [{}, {"k1": 3.0, "k2": 500.0, "p1": 1e-3, "p2": -2e-3, "principal_offset_px": (5.0, -3.0), "roll_deg": 1.0,
          "view_angle_deg": 43.0}],
)
def test_round_trips_are_exact(kind, params, rng):
    optics = _optics(kind, **params)
    xy = rng.uniform([0, 0], [optics.width - 1, optics.height - 1], (500, 2))
    us = optics.image_to_surface(xy)
    assert np.all(np.isfinite(us))
    np.testing.assert_allclose(optics.surface_to_image(us), xy, atol=1e-8)
    us2 = rng.uniform(-4.5, 4.5, (300, 2))
    np.testing.assert_allclose(optics.image_to_surface(optics.surface_to_image(us2)), us2, atol=1e-9)


def test_flat_view_is_compressed_by_sqrt2_along_rows():
    optics = PrismOptics(k1=0.0)
    jac = optics.local_scale(np.zeros(2))
    assert jac[0, 0] == pytest.approx(optics.px_per_mm, rel=1e-6)
    assert jac[1, 1] / jac[0, 0] == pytest.approx(1 / math.sqrt(2), rel=1e-3)
    assert abs(jac[0, 1]) < 1e-6 and abs(jac[1, 0]) < 1e-6
    # 10.3 mm across 640 px; the rows then see ~11 mm of the surface (seed: ~10.3 x 10.8 mm).
    us = optics.image_to_surface(np.array([[0.0, 0.0], [639.0, 483.0]]))
    assert us[1, 0] - us[0, 0] == pytest.approx(10.3 * 639 / 640, rel=0.01)
    assert 10.5 < us[1, 1] - us[0, 1] < 11.5


@pytest.mark.parametrize("kind", ("ridge", "valley"))
def test_s_is_arc_length_on_the_3d_surface(kind):
    optics = _optics(kind)
    s = np.linspace(-3.0, 3.0, 6001)
    pts = optics.surface_points_3d(np.stack([np.zeros_like(s), s], axis=-1))
    length = np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))
    assert length == pytest.approx(6.0, abs=1e-5)
    # The shape really bends the surface: the 3-D chord is shorter than the arc.
    assert np.linalg.norm(pts[-1] - pts[0]) < 6.0 - 0.05


def test_ridge_slope_changes_the_image_spacing_strongly():
    ridge, flat = _optics("ridge", k1=0.0), PrismOptics(k1=0.0)
    s = np.array([[0.0, -0.35 + 0.4], [0.0, 0.35 + 0.4]])  # across the crest at 0.4 mm
    rising = ridge.local_scale(np.array([0.0, -0.35]))[1, 1]
    falling = ridge.local_scale(np.array([0.0, 1.2]))[1, 1]
    assert rising < 0.8 * flat.local_scale(np.zeros(2))[1, 1] < falling
    assert np.all(np.isfinite(ridge.surface_to_image(s)))


def test_invalid_parameters_are_named():
    with pytest.raises(InvalidInputError, match="field_width_mm"):
        PrismOptics(field_width_mm=-1.0)
    with pytest.raises(InvalidInputError, match="slopes"):
        PrismOptics(surface=RuledSurface(kind="ridge", height_mm=2.0, width_mm=2.0))
    with pytest.raises(InvalidInputError, match="trailing axis"):
        PrismOptics().image_to_surface(np.zeros((3, 3)))
    with pytest.raises(InvalidInputError, match="surface"):
        PrismOptics(surface="ridge")


def test_optics_for_a_scene_uses_its_surface_and_field():
    scene_mod = pytest.importorskip("skinstretch.simulators.scene")
    scene = scene_mod.load_scene("ridgeL")
    optics = prism_optics_for_scene(scene, k1=0.0)
    assert optics.surface.kind == "ridge"
    assert optics.px_per_mm == pytest.approx(optics.width / scene.camera.field_of_view_mm)
