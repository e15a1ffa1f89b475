"""Scenes and the renderer: the truth is true, rendering is deterministic, scene files are validated, the CLI works."""

import numpy as np
import pytest
from scipy import ndimage as ndi

from skinstretch.drivers.session_file import open_session
from skinstretch.processing.errors import ConfigError, InvalidInputError
from skinstretch.simulators.scene import SCENE_NAMES, SceneRenderer, load_scene, parse_scene, render_session


def _flat_uniform(name="flatL", n=16, **update):
    scene = load_scene(name)
    camera = scene.camera.model_copy(update={"vignetting": 0.0, "illumination_tilt": 0.0})
    return scene.model_copy(update={"n_frames": n, "camera": camera, **update})


def _predict_from_frame0(frame0, truth, k):
    """Frame k predicted by warping frame 0 with the true Lagrangian displacement (inverted by fixed point)."""
    h, w = frame0.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    gx, gy = truth.grid_x, truth.grid_y
    step_x, step_y = gx[1] - gx[0], gy[1] - gy[0]

    def u(px, py, c):
        return ndi.map_coordinates(truth.displacement[k, ..., c].astype(np.float64), [py / step_y, px / step_x], order=3, mode="nearest")

    X, Y = x.copy(), y.copy()
    for _ in range(8):
        X, Y = x - u(X, Y, 0), y - u(X, Y, 1)
    pred = ndi.map_coordinates(frame0.astype(np.float64), [Y, X], order=3, mode="nearest")
    valid = ndi.map_coordinates(truth.displacement_valid[k].astype(float), [Y / step_y, X / step_x], order=1) > 0.999
    return pred, valid


@pytest.mark.parametrize("name,k", [("flatL", 15), ("flat1", 179)])
def test_truth_displacement_reproduces_the_frames(name, k):
    scene = _flat_uniform(name, n=k + 1)
    r = SceneRenderer(scene, seed=2, noise=0)
    truth = r.truth()
    f0, fk = r.render_frame(0).astype(np.float64), r.render_frame(k).astype(np.float64)
    pred, valid = _predict_from_frame0(f0, truth, k)
    # Away from the image border and from the soft contact edge (the contact mask is not part of the warp).
    inner = np.zeros_like(valid)
    inner[12:-12, 12:-12] = True
    _, _, skin = r.fingerprint.features()
    core = ndi.binary_erosion(valid & inner, iterations=20)
    assert core.sum() > 50_000
    motion = np.abs(truth.displacement[k][truth.displacement_valid[k]]).max()
    assert motion > 5  # the test is meaningful: the skin moved several pixels
    resid = np.sqrt(np.mean((pred - fk)[core] ** 2))
    still = np.sqrt(np.mean((f0 - fk)[core] ** 2))
    assert resid < 2.0, f"residual {resid:.2f} grey levels"
    assert still > 10 * resid


def test_pure_translation_truth_has_zero_strain():
    scene = _flat_uniform("flatL", n=12)
    scene = scene.model_copy(update={"plastic": scene.plastic.model_copy(update={"lag_mm": 0.0, "stick_slip_mm": 0.0}),
                                     "motion": scene.motion.model_copy(update={"keyframes": [(0, 0, 0, 0), (1, 0.5, 2.0, 0)]})})
    truth = SceneRenderer(scene, seed=0).truth()
    assert np.all(truth.strain == 0.0)
    d = truth.displacement[11][truth.displacement_valid[11]]
    np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), atol=1e-9)
    assert np.all(truth.rigid[:, 2] == 0.0)


def test_feature_truth_agrees_with_the_displacement_field():
    r = SceneRenderer(load_scene("flat1").model_copy(update={"n_frames": 180}), seed=1)
    t = r.truth()
    k = 170
    step = t.grid_x[1] - t.grid_x[0]
    inside = (t.feature_x[0] < t.grid_x[-1] - step) & (t.feature_y[0] < t.grid_y[-1] - step)
    inside &= (t.feature_x[0] > step) & (t.feature_y[0] > step)
    ok = t.feature_visible[0] & t.feature_visible[k] & inside
    x0, y0 = t.feature_x[0, ok], t.feature_y[0, ok]
    dx = ndi.map_coordinates(t.displacement[k, ..., 0].astype(float), [y0 / step, x0 / step], order=3)
    dy = ndi.map_coordinates(t.displacement[k, ..., 1].astype(float), [y0 / step, x0 / step], order=3)
    err = np.hypot(t.feature_x[k, ok] - x0 - dx, t.feature_y[k, ok] - y0 - dy)
    # The grid is 8 px: bicubic interpolation of it is exact up to the curvature of the field (strong in flat1).
    assert ok.sum() > 100 and np.median(err) < 0.01 and np.max(err) < 0.3
    assert t.rigid[k, 2] == pytest.approx(r.deformation.motion.pose(k / 60.0)[2])
    assert np.max(np.abs(t.strain[k])) > 0.01  # the band around the sticking centre is strained


def test_rendering_is_deterministic_in_any_order():
    scene = load_scene("flatS").model_copy(update={"n_frames": 6})
    a = SceneRenderer(scene, seed=4)
    b = SceneRenderer(scene, seed=4)
    fa = [a.render_frame(k) for k in (5, 2)]
    fb = [b.render_frame(k) for k in (2, 5)][::-1]
    assert all(np.array_equal(p, q) for p, q in zip(fa, fb))
    # Row bands in one thread or two, and frames in parallel: the same bytes.
    assert np.array_equal(a.render_frame(5, threads=1), fa[0])
    assert np.array_equal(a.render_frame(5, threads=2), fa[0])
    # The banded pipeline (blur with a few rows of context per band) is the camera applied to the whole radiance.
    rng5 = np.random.default_rng(np.random.SeedSequence(4, spawn_key=(1, 5)))
    assert np.array_equal(a.camera.apply(a.radiance(5), rng5), fa[0])
    par = render_session(scene, seed=4, workers=2)
    assert np.array_equal(par.frames[5], fa[0]) and np.array_equal(par.frames[2], fa[1])
    c = SceneRenderer(scene, seed=5)
    assert not np.array_equal(c.render_frame(2), fb[1])
    assert fa[0].dtype == np.uint8 and fa[0].shape == (484, 640)
    with pytest.raises(InvalidInputError, match="frame index"):
        a.render_frame(6)


def test_frames_look_like_ftir(sim_session):
    f = sim_session.frames[0].astype(float)
    assert sim_session.frames.shape == (20, 484, 640)
    centre = f[140:340, 200:440]
    assert centre.std() > 25  # ridges and valleys
    assert np.percentile(centre, 10) < 100 and np.percentile(centre, 90) > 150
    assert sim_session.calibration.px_per_mm == pytest.approx(640 / 10.3)
    sim_session.truth.validate(20)


@pytest.mark.parametrize("name", SCENE_NAMES)
def test_builtin_scenes_load(name):
    scene = load_scene(name)
    assert scene.name == name and scene.n_frames == 180 and scene.camera.mode == "full"
    assert parse_scene(scene.to_yaml()) == scene


def test_scene_errors_name_file_field_and_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("name: bad\ncamera:\n  mode: full\n  noise_sigma: -1\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml:4: camera\.noise_sigma: "):
        load_scene(p)
    p.write_text("name: bad\nsurface: {kind: bump}\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml:2: surface\.kind: "):
        load_scene(p)
    p.write_text("name: bad\nmotoin: {}\n")
    with pytest.raises(ConfigError, match="motoin"):
        load_scene(p)
    p.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_scene(p)
    with pytest.raises(ConfigError, match="no such scene"):
        load_scene(tmp_path / "missing.yaml")


def test_cli_writes_a_readable_session(tmp_path, capsys):
    from skinstretch.cli import main

    out = tmp_path / "s.h5"
    assert main(["simulate", "flatS", "-o", str(out), "--frames", "3", "--seed", "2", "--noise", "1.5", "--no-progress"]) == 0
    with open_session(out) as s:
        assert s.n_frames == 3
        truth = s.truth
        assert truth.feature_x.shape[0] == 3 and truth.displacement.shape[0] == 3
        assert s.metadata["scene"] == "flatS" and s.metadata["simulated"]
        assert s.calibration.px_per_mm == pytest.approx(640 / 6.1)
    assert main(["simulate", "nosuchscene", "-o", str(tmp_path / "x.h5"), "--no-progress"]) == 2
    assert "nosuchscene" in capsys.readouterr().err


def test_render_session_round_trips_through_a_file(tmp_path, sim_session):
    from skinstretch.simulators.scene import simulate_to_file

    path = simulate_to_file("flatL", tmp_path / "f.h5", n_frames=20, seed=0)
    with open_session(path) as s:
        np.testing.assert_array_equal(s.read_frames(), sim_session.frames)
        np.testing.assert_array_equal(s.truth.feature_x, sim_session.truth.feature_x)


def test_renders_through_prism_optics():
    prism = pytest.importorskip("skinstretch.simulators.prism_optics")
    optics = prism.PrismOptics(field_width_mm=6.1)
    r = SceneRenderer(load_scene("flatS").model_copy(update={"n_frames": 3}), seed=0, optics=optics)
    frame = r.render_frame(2)
    assert frame.shape == (484, 640) and frame.std() > 20
    xy, vis = r.feature_positions(2)
    _, _, skin = r.fingerprint.features()
    np.testing.assert_allclose(xy, optics.surface_to_image(r.deformation.at(2 / 60).forward(skin)))
    assert vis.sum() > 20


def test_camera_noise_has_the_stated_sigma():
    from skinstretch.simulators.sensor_model import CameraModel

    cam = CameraModel(blur_sigma_px=0.0, noise_sigma=2.0, shot_noise_gain=0.05)
    img = np.full((484, 640), 100.3, np.float32)
    out = cam.apply(img, np.random.default_rng(0)).astype(np.float64)
    # Read + shot noise, plus the 1/12 grey level^2 of quantisation.
    sigma = np.sqrt(2.0**2 + 0.05 * 100.3 + 1 / 12)
    assert out.mean() == pytest.approx(100.3, abs=0.03)
    assert out.std() == pytest.approx(sigma, rel=0.01)
    # Gaussian tails: 4.55 % beyond 2 sigma of the noise (quantisation shifts it a little).
    z = np.abs(out - 100.3) / np.sqrt(2.0**2 + 0.05 * 100.3)
    assert 0.040 < np.mean(z > 2) < 0.052
    # Independent pixels: no correlation between neighbours.
    c = np.corrcoef(out[:, :-1].ravel(), out[:, 1:].ravel())[0, 1]
    assert abs(c) < 0.01
