"""Fitting the pixel-to-surface mapping (seed 3.4, 7.2.1): accuracy against the true optics, failures, storage."""

import json

import cv2
import numpy as np
import pytest

from skinstretch.drivers.camera_modes import CAMERA_MODES
from skinstretch.drivers.session_file import open_session, write_calibration, write_session
from skinstretch.cli import main as cli_main
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.drivers.errors import SessionFileError
from skinstretch.processing.errors import CalibrationError, InvalidInputError
from skinstretch.processing.geometric_calibration import (
    GridMapping,
    calibrate_grid_image,
    calibrate_grid_images,
    fit_grid_mapping,
    mapping_from_dict,
)
from skinstretch.simulators.dot_grid_images import render_calibration_grid
from skinstretch.simulators.prism_optics import PrismOptics
from skinstretch.simulators.surfaces import RuledSurface

KINDS = ("flat", "ridge", "valley")


def _optics(kind):
    return PrismOptics(surface=RuledSurface(kind=kind, center_mm=0.3))


def _grid(optics, k=0):
    return render_calibration_grid(
        optics, missing_fraction=0.1, n_spurious=5, offset_mm=(0.13 + 0.17 * k, 0.21 + 0.12 * k), seed=20 + k
    )


@pytest.fixture(scope="module")
def fitted():
    out = {}
    for kind in KINDS:
        optics = _optics(kind)
        g = _grid(optics)
        mapping, report = calibrate_grid_image(g.image, px_per_mm=optics.px_per_mm)
        out[kind] = (optics, g, mapping, report)
    return out


def _field(optics, step=16):
    yy, xx = np.mgrid[0 : optics.height : step, 0 : optics.width : step].astype(float)
    return np.stack([xx.ravel(), yy.ravel()], -1)


def _error_um(mapped, truth):
    """Distances after the best rigid alignment (the grid fixes the surface frame up to a rigid motion)."""
    ac, bc = mapped.mean(0), truth.mean(0)
    u, _, vt = np.linalg.svd((mapped - ac).T @ (truth - bc))
    r = (u @ vt).T
    assert np.linalg.det(r) > 0  # no mirror image
    return np.linalg.norm((mapped - ac) @ r.T + bc - truth, axis=1) * 1000


@pytest.mark.parametrize("kind", KINDS)
def test_fit_matches_the_true_optics(fitted, kind):
    optics, g, mapping, report = fitted[kind]
    assert mapping.surface == kind  # "auto" recognises the surface
    assert report.rms_px < 0.05 and report.n_used > 300
    assert report.n_outliers <= 10
    xy = _field(optics)
    err = _error_um(mapping.image_to_surface(xy), optics.image_to_surface(xy))
    assert np.sqrt(np.mean(err**2)) < 2.0  # target 5 um; measured ~0.05-0.3 um
    assert err.max() < 6.0
    # The frame is the documented one: image centre at the origin, u along image x, s down the rows.
    c = optics.center_px
    np.testing.assert_allclose(mapping.image_to_surface(c), [0.0, 0.0], atol=1e-9)
    d = mapping.image_to_surface(np.array([c + [50, 0], c + [0, 50]]))
    assert d[0, 0] > 0.7 and abs(d[0, 1]) < 0.02 and d[1, 1] > 0.5
    assert mapping.px_per_mm == pytest.approx(optics.px_per_mm, rel=0.02)


@pytest.mark.parametrize("kind", ("flat", "ridge"))
def test_mapping_round_trip(fitted, kind, rng):
    _, _, mapping, _ = fitted[kind]
    us = rng.uniform(-4.0, 4.0, (200, 2))
    np.testing.assert_allclose(mapping.image_to_surface(mapping.surface_to_image(us)), us, atol=1e-8)
    xy = rng.uniform([0, 0], [639, 483], (200, 2))
    np.testing.assert_allclose(mapping.surface_to_image(mapping.image_to_surface(xy)), xy, atol=1e-7)


def test_json_round_trip(fitted):
    _, _, mapping, _ = fitted["valley"]
    text = json.dumps(mapping.to_dict())
    again = GridMapping.from_dict(json.loads(text))
    xy = np.array([[10.0, 20.0], [320.0, 240.0], [600.0, 470.0]])
    np.testing.assert_array_equal(again.image_to_surface(xy), mapping.image_to_surface(xy))
    assert again.surface == "valley" and again.report["n_used"] == mapping.report["n_used"]
    with pytest.raises(CalibrationError, match="not a skinstretch grid mapping"):
        mapping_from_dict({"kind": "something else"})
    bad = json.loads(text)
    del bad["rig"]
    with pytest.raises(CalibrationError, match="incomplete"):
        mapping_from_dict(bad)


def test_moving_grid_fit_is_at_least_as_good_on_a_ridge(fitted):
    optics, _, single, _ = fitted["ridge"]
    images = [_grid(optics, k).image for k in range(2)]
    multi, report = calibrate_grid_images(images, px_per_mm=optics.px_per_mm)
    assert report.n_used > 2 * 300 and set(report.image.tolist()) == {0, 1}
    xy = _field(optics)
    truth = optics.image_to_surface(xy)
    e_multi = np.sqrt(np.mean(_error_um(multi.image_to_surface(xy), truth) ** 2))
    e_single = np.sqrt(np.mean(_error_um(single.image_to_surface(xy), truth) ** 2))
    assert e_multi < 1.0 and e_multi <= 1.5 * e_single


def test_blank_image_is_a_calibration_error():
    with pytest.raises(CalibrationError, match="grid not found"):
        calibrate_grid_image(np.full((484, 640), 200, np.uint8), px_per_mm=62.1)


def test_random_dots_are_a_calibration_error(rng):
    img = np.full((484, 640), 200, np.uint8)
    for x, y in rng.uniform([10, 10], [630, 474], (250, 2)):
        cv2.ellipse(img, (int(x), int(y)), (6, 4), 0, 0, 360, 30, -1)
    with pytest.raises(CalibrationError):
        calibrate_grid_image(img, px_per_mm=62.1)


def test_too_few_dots_is_a_calibration_error():
    optics = PrismOptics(width=160, height=100, field_width_mm=2.6)
    g = render_calibration_grid(optics, seed=1)
    with pytest.raises(CalibrationError, match="too few|grid not found"):
        calibrate_grid_image(g.image, px_per_mm=optics.px_per_mm)


def test_large_residuals_are_a_calibration_error(fitted):
    _, g, _, report = fitted["flat"]
    used = report.used
    xy = report.xy[used] + np.random.default_rng(0).normal(0, 0.6, (used.sum(), 2))
    with pytest.raises(CalibrationError, match="residuals too large"):
        fit_grid_mapping([(report.ij[used], xy)], image_shape=g.image.shape, surface="flat", outlier_px=50.0)


def test_fit_validates_its_inputs():
    with pytest.raises(InvalidInputError, match="surface"):
        fit_grid_mapping([(np.zeros((50, 2)), np.zeros((50, 2)))], image_shape=(484, 640), surface="dome")
    with pytest.raises(InvalidInputError, match="px_per_mm"):
        calibrate_grid_image(np.zeros((100, 100)), px_per_mm=-2.0)


def test_session_stores_and_rebuilds_the_mapping(fitted, tmp_path):
    _, g, mapping, _ = fitted["ridge"]
    path = tmp_path / "s.h5"
    write_session(path, g.image[None], timestamps=np.zeros(1), camera_mode=CAMERA_MODES["full"],
                  calibration=Calibration(62.1))
    with open_session(path) as s:
        assert s.calibration.mapping is None
    write_calibration(path, Calibration(mapping.px_per_mm, mapping=mapping))
    with open_session(path) as s:
        assert s.calibration.px_per_mm == pytest.approx(mapping.px_per_mm)
        xy = np.array([[100.0, 400.0]])
        np.testing.assert_array_equal(s.calibration.mapping.image_to_surface(xy), mapping.image_to_surface(xy))
    import h5py

    with h5py.File(path, "r+") as f:
        f["calibration"].attrs["mapping_json"] = '{"kind": "nope"}'
    with pytest.raises(SessionFileError, match="mapping"):
        open_session(path)


def test_calibrate_cli_writes_a_file_and_applies_it(fitted, tmp_path, capsys):
    _, g, _, _ = fitted["valley"]
    image = tmp_path / "grid.png"
    cv2.imwrite(str(image), g.image)
    session = tmp_path / "s.h5"
    write_session(session, g.image[None], timestamps=np.zeros(1), camera_mode=CAMERA_MODES["full"],
                  calibration=Calibration(62.1))
    out = tmp_path / "cal.json"
    assert cli_main(["calibrate", str(image), "-o", str(out), "--apply-to", str(session)]) == 0
    mapping = mapping_from_dict(json.loads(out.read_text()))
    assert mapping.surface == "valley"
    with open_session(session) as s:
        assert s.calibration.mapping is not None
    # A session whose frames show the grid is an input too.
    out2 = tmp_path / "cal2.json"
    assert cli_main(["calibrate", str(session), "-o", str(out2)]) == 0 and out2.exists()
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((484, 640), 200, np.uint8))
    assert cli_main(["calibrate", str(blank), "-o", str(tmp_path / "x.json")]) == 2
    assert "grid not found" in capsys.readouterr().err


def test_window_of_a_full_frame_calibration_serves_the_strip_mode(fitted):
    optics, _, mapping, _ = fitted["ridge"]
    strip = PrismOptics(height=100, surface=optics.surface)  # the 640x100 mode: the sensor's central rows
    window = mapping.for_window(x0=0, y0=192, width=640, height=100)
    xy = _field(strip, step=8)
    err = _error_um(window.image_to_surface(xy), strip.image_to_surface(xy))
    assert np.sqrt(np.mean(err**2)) < 2.0
    assert mapping_from_dict(window.to_dict()).height == 100
    with pytest.raises(InvalidInputError, match="does not fit"):
        mapping.for_window(x0=0, y0=400, width=640, height=100)
    # Calibrating the strip itself cannot resolve the ridge, and says what to do instead.
    g = render_calibration_grid(strip, seed=2)
    with pytest.raises(CalibrationError, match="for_window"):
        calibrate_grid_image(g.image, px_per_mm=strip.px_per_mm)


def test_a_rotated_grid_on_a_flat_surface_is_fitted_as_flat():
    optics = PrismOptics()
    g = render_calibration_grid(optics, rotation_deg=20.0, missing_fraction=0.1, n_spurious=3, seed=5)
    mapping, _ = calibrate_grid_image(g.image, px_per_mm=optics.px_per_mm)
    assert mapping.surface == "flat"
    xy = _field(optics)
    assert np.sqrt(np.mean(_error_um(mapping.image_to_surface(xy), optics.image_to_surface(xy)) ** 2)) < 1.0


def test_calibrate_cli_windows_a_full_frame_calibration_for_a_strip_session(fitted, tmp_path):
    optics, g, _, _ = fitted["ridge"]
    image = tmp_path / "grid.png"
    cv2.imwrite(str(image), g.image)
    session = tmp_path / "strip.h5"
    write_session(session, np.full((1, 100, 640), 200, np.uint8), timestamps=np.zeros(1),
                  camera_mode=CAMERA_MODES["strip"], calibration=Calibration(62.1))
    assert cli_main(["calibrate", str(image), "-o", str(tmp_path / "c.json"), "--apply-to", str(session)]) == 0
    strip = PrismOptics(height=100, surface=optics.surface)
    with open_session(session) as s:
        mapping = s.calibration.mapping
        assert (mapping.width, mapping.height) == (640, 100)
        xy = _field(strip, step=8)
        assert np.sqrt(np.mean(_error_um(mapping.image_to_surface(xy), strip.image_to_surface(xy)) ** 2)) < 2.0


def test_a_non_gaussian_ridge_gets_a_spline_profile():
    from skinstretch.simulators.prism_optics import SkewedRidgeSurface

    optics = PrismOptics(surface=SkewedRidgeSurface(kind="ridge", center_mm=0.3))
    g = render_calibration_grid(optics, missing_fraction=0.1, n_spurious=2, seed=9)
    mapping, report = calibrate_grid_image(g.image, px_per_mm=optics.px_per_mm)
    assert mapping.surface == "ridge" and len(mapping.rig.spline_coefs) > 5
    assert report.rms_px < 0.05  # the spline takes up what the Gaussian could not
    xy = _field(optics)
    err = _error_um(mapping.image_to_surface(xy), optics.image_to_surface(xy))
    assert np.sqrt(np.mean(err**2)) < 5.0  # the target; one image samples the profile only every 0.5 mm
    again = mapping_from_dict(json.loads(json.dumps(mapping.to_dict())))
    np.testing.assert_array_equal(again.image_to_surface(xy[:5]), mapping.image_to_surface(xy[:5]))
