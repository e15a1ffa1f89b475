"""A longer span's motion registered directly between its two frames (``SubpixelRefiner.register_span``) and
combined with the chained motion (``SpanRegistration``: their mean, the direct one where the window is plainly
curved): exact on a known affine deformation of several per cent, where a translation-only window is biased, and on
a band of localized strain, which an affine window smooths; points it cannot measure keep the chained motion; and
the analysis uses it."""

import cv2
import numpy as np
import pytest
from scipy.special import erf

from skinstretch.processing.displacement_refinement import SubpixelParams, SubpixelRefiner
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.span_registration import SpanRegistration, direct_weight
from skinstretch.processing.tracking import MotionSample

CAL = Calibration(px_per_mm=62.0)
H, W = 240, 260


def _texture(seed=3):
    """A blotchy skin-like texture (texture in every direction), grey levels around 128."""
    t = cv2.GaussianBlur(np.random.default_rng(seed).uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 2.5)
    return (t - t.mean()) * (60 / t.std()) + 128


def _deformed(texture, u0, grad, centre):
    """``texture`` moved by the affine field u(x) = u0 + grad (x - centre): b(x + u(x)) = a(x)."""
    m = np.eye(2) + grad
    t = np.asarray(u0) + np.asarray(centre) - m @ np.asarray(centre)
    fwd = np.hstack([m, t[:, None]]).astype(np.float32)
    return cv2.warpAffine(texture, fwd, (W, H), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def _true(points, u0, grad, centre):
    return np.asarray(u0) + (points - np.asarray(centre)) @ np.asarray(grad).T


@pytest.fixture(scope="module")
def span_pair():
    """A stretch of 4 % along x, -2 % along y and a 2 % shear (an 11-frame span of a fast stretch), 0.8 px noise."""
    rng = np.random.default_rng(0)
    tex = _texture()
    u0, grad, centre = (1.7, -0.6), np.array([[0.04, 0.02], [0.0, -0.02]]), (130.0, 120.0)
    a = np.clip(tex + rng.normal(0, 0.8, tex.shape), 0, 255).astype(np.uint8)
    b = np.clip(_deformed(tex, u0, grad, centre) + rng.normal(0, 0.8, tex.shape), 0, 255).astype(np.uint8)
    pts = np.array([[x, y] for x in (90.0, 120.3, 150.6, 170.0) for y in (80.0, 110.5, 140.2, 160.0)])
    return a, b, pts, _true(pts, u0, grad, centre)


def test_register_span_recovers_an_affine_deformation_a_translation_window_misreads(span_pair):
    a, b, pts, truth = span_pair
    r = SubpixelRefiner(calibration=CAL)
    start = truth + np.random.default_rng(1).normal(0, 0.3, truth.shape)  # chained motion, a few tenths off
    d, ok, _, sigma = r.register_span(r.prepare(a), r.prepare(b), pts, start)
    assert ok.all()
    err = np.hypot(*(d - truth).T)
    assert err.max() < 0.03, err
    # its predicted standard error (the fit's residual over its texture) bounds the error, and is informative
    assert np.all(err <= 2.45 * sigma) and np.all(sigma < 0.05), (err, sigma)
    # The same windows registered by translation only (refine): the deformation across them biases it more.
    lk = r.refine(r.prepare(a), r.prepare(b), pts, start)
    assert np.sqrt(np.mean(np.hypot(*(lk.displacement - truth).T) ** 2)) > 3 * np.sqrt(np.mean(err ** 2))


@pytest.fixture(scope="module")
def band_pair():
    """A -8 % compression band across y (Gaussian profile, 0.56 mm at half height: a slip front's band over a span):
    the displacement is curved across a 0.8 mm window. Frames, points, true displacement, a start 0.3 px off."""
    amp, sigma, y0 = -0.08, 15.0, 120.0

    def u_y(y):  # the integral of the strain amp * exp(-(y - y0)^2 / (2 sigma^2))
        return amp * sigma * np.sqrt(np.pi / 2) * (1 + erf((y - y0) / (sigma * np.sqrt(2))))

    tex = _texture()
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    src_y = ys.copy()
    for _ in range(20):  # b(x + u(x)) = a(x): the source row of each pixel of b, by fixed-point iteration
        src_y = ys - u_y(src_y)
    rng = np.random.default_rng(0)
    a = np.clip(tex + rng.normal(0, 0.8, tex.shape), 0, 255).astype(np.uint8)
    warped = cv2.remap(tex.astype(np.float32), xs, src_y.astype(np.float32), cv2.INTER_CUBIC,
                       borderMode=cv2.BORDER_REFLECT)
    b = np.clip(warped + rng.normal(0, 0.8, tex.shape), 0, 255).astype(np.uint8)
    pts = np.array([[x, y] for x in (80.0, 110.0, 140.0, 170.0) for y in np.arange(90.0, 151.0, 6.0)])
    truth = np.column_stack([np.zeros(len(pts)), u_y(pts[:, 1])])
    return a, b, pts, truth, truth + np.random.default_rng(1).normal(0, 0.3, truth.shape)


def test_register_span_follows_a_band_of_localized_strain_that_an_affine_window_smooths(band_pair):
    """The second-order terms are kept where they are significant, and the band is read within a few hundredths
    of a pixel; the affine model alone (a threshold no fit reaches) reads it smoothed, a tenth of a pixel and more
    off at the band's edges."""
    a, b, pts, truth, start = band_pair

    def rms_error(threshold):
        r = SubpixelRefiner(calibration=CAL, params=SubpixelParams(span_curvature_threshold=threshold))
        d, ok, *_ = r.register_span(r.prepare(a), r.prepare(b), pts, start)
        assert ok.all()
        return np.sqrt(np.mean(np.sum((d - truth) ** 2, axis=1)))

    selected, affine = rms_error(SubpixelParams().span_curvature_threshold), rms_error(1e12)
    assert selected < 0.04 and affine > 0.1, (selected, affine)


def test_span_registration_trusts_the_direct_registration_where_the_band_curves(band_pair):
    """A chain of frame-to-frame windows reads the band smoothed (here: 85 % of it); where the span's window is
    plainly curved its direct registration gets the weight, and the combination errs far less than the mean."""
    a, b, pts, truth, _ = band_pair
    chained = 0.85 * truth
    out = SpanRegistration(SubpixelRefiner(calibration=CAL), {0: a, 11: b}.__getitem__).refine(
        MotionSample(0, 11, pts, chained, np.arange(len(pts))))
    r = SubpixelRefiner(calibration=CAL)
    fit = r.register_span(r.prepare(a), r.prepare(b), pts, chained)
    weight = direct_weight(fit.curvature, r.params.span_curvature_threshold, r.params.span_direct_full)
    assert fit.ok.all() and weight.max() == 1.0 and weight.min() >= 0.5
    np.testing.assert_allclose(out.displacement, weight[:, None] * fit.displacement + (1 - weight[:, None]) * chained,
                               rtol=0, atol=1e-12)
    rms = lambda d: np.sqrt(np.mean(np.sum((d - truth) ** 2, axis=1)))  # noqa: E731
    assert rms(out.displacement) < 0.6 * rms(0.5 * (fit.displacement + chained)), (
        rms(out.displacement), rms(0.5 * (fit.displacement + chained)))


def test_register_span_keeps_the_start_where_it_cannot_measure(span_pair):
    a, b, pts, truth = span_pair
    r = SubpixelRefiner(calibration=CAL)
    edge = np.array([[5.0, 120.0], [130.0, 120.0]])  # the first window leaves the image
    start = _true(edge, (1.7, -0.6), np.array([[0.04, 0.02], [0.0, -0.02]]), (130.0, 120.0)) + 0.2
    flat = np.full_like(a, 200)  # a flat field: skin out of contact, no texture to register
    d, ok, *_ = r.register_span(r.prepare(a), r.prepare(b), edge, start)
    assert ok.tolist() == [False, True] and np.array_equal(d[0], start[0])
    d, ok, *_ = r.register_span(r.prepare(flat), r.prepare(flat), pts[:3], truth[:3])
    assert not ok.any() and np.array_equal(d, truth[:3]) and np.isfinite(d).all()
    d, ok, *_ = r.register_span(a, b, np.zeros((0, 2)), np.zeros((0, 2)))
    assert d.shape == (0, 2) and ok.shape == (0,)
    with pytest.raises(InvalidInputError, match="displacement has shape"):
        r.register_span(a, b, pts, truth[:2])


def test_span_registration_averages_the_direct_and_the_chained_motion(span_pair):
    a, b, pts, truth = span_pair
    frames = {0: a, 11: b}
    asked = []

    def frame(j):
        asked.append(j)
        return frames[j]

    reg = SpanRegistration(SubpixelRefiner(calibration=CAL), frame)
    chained = truth + np.where(np.arange(len(pts))[:, None] % 2 == 0, 0.2, -0.2)  # a chain's accumulated error
    out = reg.refine(MotionSample(0, 11, pts, chained, np.arange(len(pts))))
    r = SubpixelRefiner(calibration=CAL)
    direct, ok, *_ = r.register_span(r.prepare(a), r.prepare(b), pts, chained)
    assert ok.all() and out.frame_a == 0 and out.frame_b == 11 and np.array_equal(out.ids, np.arange(len(pts)))
    np.testing.assert_allclose(out.displacement, 0.5 * (direct + chained), rtol=0, atol=1e-12)
    # the chained error is halved
    np.testing.assert_allclose(np.abs(out.displacement - truth), 0.1, atol=0.03)
    assert sorted(asked) == [0, 11]  # each frame prepared once
    empty = MotionSample(0, 11, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64))
    assert len(reg.refine(empty)) == 0
    # Several spans at once on threads: in order, the same numbers as one at a time, each frame prepared once.
    frames.update({1: a, 12: b, 2: a, 13: b})
    asked.clear()
    samples = [MotionSample(k, k + 11, pts + 0.1 * k, chained, np.arange(len(pts))) for k in range(3)]
    samples.insert(1, MotionSample(1, 12, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64)))
    together = reg.refine_all(samples, threads=2)
    one_by_one = [SpanRegistration(SubpixelRefiner(calibration=CAL), frames.__getitem__).refine(s) for s in samples]
    assert [(s.frame_a, len(s)) for s in together] == [(0, 16), (1, 0), (1, 16), (2, 16)]
    for x, y in zip(together, one_by_one):
        np.testing.assert_array_equal(x.displacement, y.displacement)
    assert sorted(asked) == [1, 2, 12, 13]  # frames 0 and 11 kept from the span above


def test_the_feature_analysis_registers_its_long_spans_on_a_flat_surface_only(sim_session, monkeypatch):
    """On a flat surface every 11-frame pair goes through the direct registration, and its strain is measured against
    the truth as well as before; over a ridge (glass-fixed patterns the skin moves through) it is left out."""
    from skinstretch.experiments.analysis import analysis_params, analyze_frames
    from skinstretch.experiments.evaluation.tracking import evaluate_tracking

    calls = []
    original = SpanRegistration.refine_all

    def counting(self, samples, **kwargs):
        calls.extend((sample.frame_a, sample.frame_b) for sample in samples)
        return original(self, samples, **kwargs)

    monkeypatch.setattr(SpanRegistration, "refine_all", counting)
    s = sim_session
    r = analyze_frames(s.frames, calibration=s.calibration, method="features", params=analysis_params(),
                       surface="flat")
    n = len(s.frames)
    assert calls == [(k, k + 11) for k in range(n - 11)]  # the strain's 11-frame span: pairs (k, k + 11)
    ev = evaluate_tracking(r, s.truth)
    assert ev["strain"]["n_edges_11"] > 0 and ev["strain"]["edge_rmse_11"] < 0.002
    calls.clear()
    analyze_frames(s.frames, calibration=s.calibration, method="features", params=analysis_params(), surface="ridge")
    assert calls == []
