"""The refinement's second, wider window: points whose first window measures the displacement less precisely than
the target (clean parallel ridges: the displacement along them is poorly determined) are registered again wider;
windows with texture in every direction keep the first one."""

import warnings

import cv2
import numpy as np

from skinstretch.experiments.viewer.live_analysis import _SyntheticPrint
from skinstretch.processing.displacement_refinement import SubpixelParams, SubpixelRefiner
from skinstretch.processing.pixel_scale import Calibration

CAL = Calibration(px_per_mm=62.0)


def _pair(texture, shift, noise, seed):
    rng = np.random.default_rng(seed)
    h, w = texture.shape
    m = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(texture, m, (w, h), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    a = np.clip(texture + rng.normal(0, noise, texture.shape), 0, 255).astype(np.uint8)
    b = np.clip(moved + rng.normal(0, noise, texture.shape), 0, 255).astype(np.uint8)
    return a, b


def _ridges(h=200, w=200, period=28.0, breaks=0.0, seed=0, at=()):
    """Parallel ridges along x (their normal is y), dark, on bright valleys, broken at random places (a clean print's
    only landmarks along a ridge: its ends and gaps), ``breaks`` of them per 1000 px^2, and at the points ``at``
    (features: landmarks)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    ridge = 0.5 + 0.5 * np.cos(2 * np.pi * y / period)
    gaps = np.zeros((h, w), np.float32)
    n = int(breaks * h * w / 1000)
    for cx, cy in [*at, *zip(rng.uniform(0, w, n), rng.uniform(0, h, n))]:
        cy = period * np.round(cy / period)  # on a ridge
        cv2.circle(gaps, (int(cx), int(cy)), 5, 1.0, -1)
    gaps = cv2.GaussianBlur(gaps, (0, 0), 2.0)
    return (200 - 120 * ridge * (1 - np.clip(gaps, 0, 1))).astype(np.float32)


def _blotchy(seed=1):
    t = cv2.GaussianBlur(np.random.default_rng(seed).uniform(0, 255, (200, 200)).astype(np.float32), (0, 0), 2.5)
    return (t - t.mean()) * (60 / t.std()) + 128


def test_parallel_ridges_get_the_wide_window_blotches_keep_the_narrow_one():
    r = SubpixelRefiner(calibration=CAL)
    narrow, wide = r.window_px, CAL.odd_px(SubpixelParams().wide_window_mm, minimum=7)
    assert wide > narrow
    pts = np.array([[100.0, 100.0], [90.0, 110.0], [110.0, 95.0]])
    shift = (0.7, 0.4)
    a, b = _pair(_blotchy(), shift, 2.0, 0)
    out = r.refine(a, b, pts, np.tile(shift, (3, 1)) + 0.3)
    assert out.refined.all() and (out.window_px == narrow).all()
    np.testing.assert_allclose(out.displacement, np.tile(shift, (3, 1)), atol=0.05)
    # Texture in one direction only: the displacement along the ridges is not determined by the first window.
    a, b = _pair(_ridges(), shift, 2.0, 0)
    out = r.refine(a, b, pts, np.tile(shift, (3, 1)))
    assert out.refined.all() and (out.window_px == wide).all()
    np.testing.assert_allclose(out.displacement[:, 1], shift[1], atol=0.05)  # across the ridges
    # One window for every point when asked.
    one = SubpixelRefiner(calibration=CAL, params=SubpixelParams(wide_window_mm=None)).refine(a, b, pts,
                                                                                            np.tile(shift, (3, 1)))
    assert (one.window_px == narrow).all()


def test_predicted_precision_follows_the_scatter_over_noise_draws():
    """The precision the choice rests on (s^2 T^-1 of the window) follows the displacement's scatter over noise
    draws: the same ratio at two noise levels, the prediction a lower bound within a factor 2.5 (the noise of the
    gradients and of the interpolated second image is not in it; the target allows for it)."""
    r = SubpixelRefiner(calibration=CAL, params=SubpixelParams(wide_window_mm=None))
    texture = _blotchy(seed=4) * 0.25 + 96  # low contrast: noise-limited
    pts = np.array([[x, y] for x in (60.0, 100.0, 140.0) for y in (60.0, 100.0, 140.0)])
    shift = np.array([0.35, 0.6])
    ratios = []
    for noise in (2.0, 4.0):
        errors, predicted = [], []
        for seed in range(8):
            a, b = _pair(texture, shift, noise, seed)
            out = r.refine(a, b, pts, np.tile(shift, (9, 1)))
            errors.append(out.displacement - shift)
            predicted.append(r._predicted_variance(a, b, pts, out.displacement, r.window_px))
        actual = float(np.sqrt(np.mean(np.sum(np.concatenate(errors) ** 2, axis=1))))
        ratios.append(actual / float(np.sqrt(np.mean(np.concatenate(predicted)))))
    assert all(1.0 < q < 2.5 for q in ratios) and abs(ratios[0] / ratios[1] - 1) < 0.3, ratios


def test_deformation_bias_uses_each_points_window():
    r = SubpixelRefiner(calibration=CAL)
    texture = _blotchy().astype(np.uint8)
    pts = np.array([[95.0, 103.0], [95.0, 103.0]])
    g = np.tile(np.array([[0.01, 0.0], [0.0, -0.01]]), (2, 1, 1))
    narrow = r.deformation_bias(texture, pts, g)
    per_point = r.deformation_bias(texture, pts, g, np.array([r.window_px, 61]))
    np.testing.assert_array_equal(per_point[0], narrow[0])
    assert not np.allclose(per_point[1], narrow[1])


def test_a_flat_field_prepares_without_nan():
    """Flat glass round a contact: its local variance rounds either side of 0; the normalised image is the
    middle grey or brighter there (a NaN cast to 0 before), and the gradients are finite."""
    frame = _SyntheticPrint().frame(0)  # ridges inside an ellipse, flat 230 outside
    flat = frame == 230
    refiner = SubpixelRefiner(calibration=Calibration(px_per_mm=62.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        prepared = refiner.prepare(frame)
    assert (prepared.image[flat] >= 128).all()
    assert all(np.isfinite(g).all() for g in prepared.gradient)
