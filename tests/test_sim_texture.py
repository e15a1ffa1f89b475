"""Scenes with a real print as the skin texture: the truth stays exact, the print is prepared as documented
(polarity, coverage, resolution), and evaluate says the features are not scored."""

import logging

import numpy as np
import pytest
from scipy import ndimage as ndi

from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.print_texture import RealPrintTexture, load_print, prepare_print
from skinstretch.simulators.prints import PRINT_NAMES, print_path
from skinstretch.simulators.scene import FEATURE_TRUTH_UNKNOWN, SceneRenderer, load_scene

DPI = 500.0
PPM = DPI / 25.4


def _ridges(shape=(300, 260), period_mm=0.45, *, dark_ridges=True, margin=40):
    """A synthetic 'ink print': sinusoidal ridges (with a slow bend) on a blank background beyond ``margin`` px."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    phase = 2 * np.pi * (y + 0.002 * (x - w / 2) ** 2) / (period_mm * PPM)
    ridge = 0.5 + 0.5 * np.cos(phase)  # 1 on ridge centres
    inside = (x > margin) & (x < w - margin) & (y > margin) & (y < h - margin)
    img = np.where(inside, 1.0 - 0.8 * ridge, 1.0)  # dark ridges on white
    if not dark_ridges:
        img = 1.0 - img
    return (img * 255).round().astype(np.uint8), inside


def test_polarity_is_read_from_the_background():
    dark, inside = _ridges()
    bright, _ = _ridges(dark_ridges=False)
    p = prepare_print(dark, dpi=DPI)
    q = prepare_print(bright, dpi=DPI)
    assert p.polarity == "dark_ridges" and q.polarity == "bright_ridges"
    core = ndi.binary_erosion(inside, iterations=30)
    # Both end up in FTIR polarity: the same texture (0 on ridges).
    np.testing.assert_allclose(p.brightness[core], q.brightness[core], atol=0.02)
    ridge_centres = core & (_ridges()[0] < 60)
    assert p.brightness[ridge_centres].mean() < 0.2
    # Given explicitly, the polarity is obeyed (the wrong one inverts the texture).
    wrong = prepare_print(dark, dpi=DPI, polarity="bright_ridges")
    assert wrong.brightness[ridge_centres].mean() > 0.8


def test_coverage_alpha_colour_and_ridge_period():
    grey, inside = _ridges(margin=40)
    p = prepare_print(grey, dpi=DPI)
    assert p.ridge_period_mm == pytest.approx(0.45, rel=0.1)
    assert p.coverage[~ndi.binary_dilation(inside, iterations=5)].max() < 0.01
    assert p.coverage[ndi.binary_erosion(inside, iterations=30)].min() > 0.99
    # Colour with an alpha channel: transparent pixels are not print.
    bgra = np.dstack([grey, grey, grey, np.full(grey.shape, 255, np.uint8)])
    bgra[:, :130, 3] = 0
    q = prepare_print(bgra, dpi=DPI)
    assert q.coverage[:, :120].max() == 0.0 and q.coverage[150:250, 150:200].min() > 0.99
    np.testing.assert_allclose(prepare_print(bgra[..., :3], dpi=DPI).brightness, p.brightness, atol=1e-6)


def test_ridge_period_of_a_blotchy_print(caplog):
    # A faint latent print, its ridges broken, on a mottled surface (blotches 0.1-0.5 mm, a natural image's
    # falling spectrum): the mottle must not pass for the ridge period (it read 1.21 mm), nor set off the dpi
    # warning.
    h = w = 400
    y, x = np.mgrid[0:h, 0:w].astype(float)
    rng = np.random.default_rng(5)
    ridge = 0.5 + 0.5 * np.cos(2 * np.pi * (y + 0.002 * (x - w / 2) ** 2) / (0.42 * PPM))
    quality = np.clip(ndi.gaussian_filter(rng.normal(size=(h, w)), 10) * 30 + 0.5, 0, 1)
    mottle = sum(ndi.gaussian_filter(rng.normal(size=(h, w)), s) * s for s in (6, 12))
    mottle *= 0.1 / mottle.std()
    inside = (x > 20) & (x < w - 20) & (y > 20) & (y < h - 20)
    img = np.clip(np.where(inside, 0.6 - 0.15 * ridge * quality + mottle, 1.0), 0, 1)
    with caplog.at_level(logging.WARNING, logger="skinstretch.simulators.print_texture"):
        p = prepare_print((img * 255).round().astype(np.uint8), dpi=DPI)
    assert p.ridge_period_mm == pytest.approx(0.42, rel=0.1)
    assert "is the dpi right" not in caplog.text


def test_wrong_dpi_is_warned_and_bad_images_refused(caplog):
    grey, _ = _ridges(period_mm=0.45)
    with caplog.at_level(logging.WARNING, logger="skinstretch.simulators.print_texture"):
        prepare_print(grey, dpi=200.0)  # read at 200 dpi the ridges would be 1.1 mm apart
    assert "is the dpi right" in caplog.text
    with pytest.raises(InvalidInputError, match="no fingerprint"):
        prepare_print(np.full((200, 200), 255, np.uint8), dpi=DPI)
    with pytest.raises(InvalidInputError, match="dpi"):
        prepare_print(grey, dpi=-1.0)
    with pytest.raises(InvalidInputError, match="no such print image"):
        load_print("no_such_print.png")


def test_faint_print_small_on_a_large_page_transparent_border_and_16_bit():
    """The print is found and its polarity read whatever share of the image it takes or of itself the ridges take."""
    grey, inside = _ridges(shape=(200, 180), margin=0)
    # Faint and broken ridges (thin dark lines on white: the print's median is the background's level), pasted on
    # a page 8x larger than the print, a little greyer than the print's own white.
    faint = np.where(grey < 60, grey, 255).astype(np.uint8)
    page = np.full((1600, 1440), 248, np.uint8)
    page[700:900, 600:780] = faint
    p = prepare_print(page, dpi=DPI)
    assert p.polarity == "dark_ridges"
    assert p.area_mm2 == pytest.approx(200 * 180 / PPM**2, rel=0.25)  # the print, not the pasted rectangle
    assert p.coverage[:650].max() == 0.0 and p.coverage[760:840, 660:720].min() > 0.99
    inverted = prepare_print(255 - page, dpi=DPI)
    assert inverted.polarity == "bright_ridges"
    np.testing.assert_allclose(inverted.brightness[760:840, 660:720], p.brightness[760:840, 660:720], atol=0.02)
    # A transparent border (black under alpha 0) is no contrast: the print, not the alpha edge, is found.
    bgra = np.zeros((400, 380, 4), np.uint8)
    bgra[100:300, 100:280] = np.dstack([grey, grey, grey, np.full(grey.shape, 255, np.uint8)])
    q = prepare_print(bgra, dpi=DPI)
    assert q.area_mm2 == pytest.approx(prepare_print(grey, dpi=DPI).area_mm2, rel=0.05)
    # 16 bits: the same print as 8 bits.
    np.testing.assert_allclose(prepare_print(grey.astype(np.uint16) * 257, dpi=DPI).brightness,
                               prepare_print(grey, dpi=DPI).brightness, atol=1e-6)


def test_unreadable_print_files_and_bad_dpi_are_one_line(tmp_path, capsys):
    from skinstretch.cli import main

    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "text.png").write_text("not an image")
    with pytest.raises(InvalidInputError, match="empty"):
        load_print(tmp_path / "empty.png", dpi=DPI)
    with pytest.raises(InvalidInputError, match="not an image"):
        load_print(tmp_path / "text.png", dpi=DPI)
    with pytest.raises(InvalidInputError, match="folder"):
        load_print(tmp_path, dpi=DPI)
    for args in (["--texture", str(tmp_path / "empty.png")], ["--texture", "afis_p1_2", "--dpi", "50"],
                 ["--texture", "afis_p1_2", "--dpi", "nan"]):
        assert main(["simulate", "flatS", *args, "-o", str(tmp_path / "x.h5"), "--frames", "1", "--no-progress"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err and "simulate: error:" in err, err
    assert not (tmp_path / "x.h5").exists()


def test_builtin_prints_ship_with_their_licence():
    assert set(PRINT_NAMES) == {"afis_p1_2", "afis_p2_1"}
    licence = print_path("afis_p1_2").with_name("LICENSE-afis.txt").read_text()
    assert "MIT License" in licence and "Permission is hereby granted" in licence
    p = load_print("afis_p2_1")
    assert p.polarity == "dark_ridges" and p.brightness.shape == (500, 400)
    assert 0.35 < p.ridge_period_mm < 0.6


def _texture_scene(texture="afis_p1_2", n=12):
    scene = load_scene("flatL").with_texture(texture)
    camera = scene.camera.model_copy(update={"vignetting": 0.0, "illumination_tilt": 0.0})
    return scene.model_copy(update={"n_frames": n, "camera": camera})


def test_texture_scene_truth_reproduces_the_frames():
    """Frame k predicted by warping frame 0 with the true displacement, on a real print (noiseless)."""
    r = SceneRenderer(_texture_scene(n=12), seed=3, noise=0)
    t = r.truth()
    k = 11
    f0, fk = r.render_frame(0).astype(float), r.render_frame(k).astype(float)
    h, w = f0.shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    step = t.grid_x[1] - t.grid_x[0]

    def u(px, py, c):
        return ndi.map_coordinates(t.displacement[k, ..., c].astype(float), [py / step, px / step], order=3,
                                   mode="nearest")

    X, Y = x.copy(), y.copy()
    for _ in range(8):
        X, Y = x - u(X, Y, 0), y - u(X, Y, 1)
    pred = ndi.map_coordinates(f0, [Y, X], order=3, mode="nearest")
    valid = ndi.map_coordinates(t.displacement_valid[k].astype(float), [Y / step, X / step], order=1) > 0.999
    inner = np.zeros_like(valid)
    inner[12:-12, 12:-12] = True
    core = ndi.binary_erosion(valid & inner, iterations=20)
    assert core.sum() > 50_000
    assert np.abs(t.displacement[k][t.displacement_valid[k]]).max() > 5  # the skin moved several pixels
    resid = np.sqrt(np.mean((pred - fk)[core] ** 2))
    assert resid < 2.0 and np.sqrt(np.mean((f0 - fk)[core] ** 2)) > 10 * resid
    # No feature truth, said so; the texture is recorded.
    assert t.feature_x.shape == (12, 0) and t.attrs["feature_truth"] == FEATURE_TRUTH_UNKNOWN
    assert t.attrs["texture"] == "afis_p1_2" and len(t.attrs["texture_sha256"]) == 64
    t.validate(12)


def test_a_print_smaller_than_the_field_leaves_skin_out_of_contact(tmp_path):
    grey, inside = _ridges(shape=(200, 160), margin=20)  # ~7 x 5.5 mm of print: smaller than the contact
    path = tmp_path / "small.png"
    import cv2

    cv2.imwrite(str(path), grey)
    r = SceneRenderer(_texture_scene(str(path), n=2), seed=0, noise=0)
    assert r.print_coverage is not None and r.print_coverage < 0.7
    t = r.truth()
    frame = r.render_frame(0).astype(float)
    # Where the truth says out of contact the frame is flat and bright (no ridges), inside it has ridges.
    gx, gy = np.meshgrid(t.grid_x.astype(int), t.grid_y.astype(int))
    out = ~t.displacement_valid[0]
    bright = frame[gy[out], gx[out]]
    assert np.percentile(bright, 10) > 150
    tex = r.fingerprint
    assert isinstance(tex, RealPrintTexture)
    assert tex.coverage_at(np.array([[0.0, 0.0]]))[0] > 0.99 and tex.coverage_at(np.array([[5.0, 4.0]]))[0] == 0.0
    # A scene file names its texture relative to itself.
    (tmp_path / "scene.yaml").write_text("name: mine\nn_frames: 2\ntexture: {image: small.png, dpi: 500}\n")
    scene = load_scene(tmp_path / "scene.yaml")
    assert scene.texture.image == str(path.resolve())
    assert SceneRenderer(scene, seed=0).fingerprint.image.sha256 == tex.image.sha256


def test_simulate_with_texture_and_evaluate_says_features_are_not_scored(tmp_path, capsys):
    from skinstretch.cli import main
    from skinstretch.drivers.session_file import open_session
    from skinstretch.experiments.evaluation.trajectories import feature_truth_known

    out = tmp_path / "t.h5"
    assert main(["simulate", "flatS", "--texture", "afis_p2_1", "--dpi", "500", "-o", str(out), "--frames", "3",
                 "--no-progress"]) == 0
    with open_session(out) as s:
        known, why = feature_truth_known(s.truth)
        assert s.metadata["texture"] == "afis_p2_1"
    assert not known and "afis_p2_1" in why and "not known" in why
    assert main(["simulate", "flatS", "--dpi", "500", "-o", str(tmp_path / "x.h5"), "--no-progress"]) == 2
    assert "--texture" in capsys.readouterr().err
