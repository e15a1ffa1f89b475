"""Every measurement with its uncertainty, every gross failure flagged: the predicted standard errors
(:mod:`skinstretch.processing.measurement_uncertainty`) cover the true error, and the analysis' self-checks doubt a
registration locked onto wrong ridges, in the results, the summary and the report."""

import numpy as np
import pytest

from skinstretch.experiments.analysis import analyze_frames
from skinstretch.experiments.results_file import PairStatus
from skinstretch.processing.displacement_refinement import SubpixelRefiner
from skinstretch.processing.flow import DenseFlow, FlowParams
from skinstretch.processing.measurement_uncertainty import (
    MIN_MATCH, RADIUS_95_2D, Regularisation, area_change_sigma, edge_change_sigma, larger_axis_sigma, variance_factor,
)
from skinstretch.processing.pixel_scale import Calibration
from tests.print_clips import print_frame, print_image, true_x

SHAPE = (240, 320)
SLIDE, STRETCH = 0.5, 0.0005


def _true_dx(x0, frame_a, frame_b):
    """True x displacement from frame_a to frame_b of the point at x0 in frame_a."""
    skin = (np.asarray(x0) - SHAPE[1] / 2 - SLIDE * frame_a) / (1 + STRETCH * frame_a) + SHAPE[1] / 2
    return true_x(skin, frame_b, width=SHAPE[1], slide_px=SLIDE, stretch=STRETCH) - x0


def test_the_weakest_direction_bounds_the_error():
    assert float(larger_axis_sigma(4.0, 0.0, 1.0, 0.25)) == pytest.approx(0.5)
    assert float(larger_axis_sigma(1.0, 1.0, 1.0, 0.25)) == np.inf  # parallel ridges only: no bound along them
    assert np.isnan(larger_axis_sigma(1.0, 0.0, 1.0, np.nan))


def test_strain_errors_follow_the_points_errors():
    """First-order propagation against a Monte Carlo of the same independent point errors."""
    rng = np.random.default_rng(0)
    tri = np.array([[0.0, 0.0], [30.0, 2.0], [8.0, 25.0]])
    sigma = np.array([0.02, 0.03, 0.025])
    noisy = tri + rng.normal(size=(20000, 3, 2)) * sigma[None, :, None]
    length = np.hypot(*(tri[1] - tri[0]))
    change = np.hypot(*(noisy[:, 1] - noisy[:, 0]).T) / length - 1
    assert float(edge_change_sigma(sigma[0], sigma[1], length)) == pytest.approx(change.std(), rel=0.05)

    def area(v):
        return 0.5 * ((v[..., 1, 0] - v[..., 0, 0]) * (v[..., 2, 1] - v[..., 0, 1])
                      - (v[..., 2, 0] - v[..., 0, 0]) * (v[..., 1, 1] - v[..., 0, 1]))

    predicted = area_change_sigma(tri[None], sigma[None], area(tri))[0]
    assert predicted == pytest.approx((area(noisy) / area(tri) - 1).std(), rel=0.05)


def test_correlated_points_strain_errors_follow_them():
    """The same with the points' errors correlated as a dense registration's (:class:`Regularisation`): a Monte
    Carlo of errors drawn with that correlation."""
    rng = np.random.default_rng(1)
    tri = np.array([[0.0, 0.0], [12.0, 0.0], [0.0, 12.0]])
    sigma = np.array([0.02, 0.03, 0.025])
    model = Regularisation(grid_step_px=3.0, window_nodes=13 / 3, membrane=3.0, prior_nodes=2.0)
    corr = np.array([[1.0 if i == j else float(model.correlation(tri[j] - tri[i])) for j in range(3)]
                     for i in range(3)])
    assert 0.2 < corr[0, 1] < 0.6 and corr[1, 2] < corr[0, 1]  # falls with distance
    chol = np.linalg.cholesky(corr * np.outer(sigma, sigma))
    noisy = tri + np.transpose(rng.normal(size=(40000, 2, 3)) @ chol.T, (0, 2, 1))  # each axis alike
    change = np.hypot(*(noisy[:, 1] - noisy[:, 0]).T) / 12.0 - 1
    assert float(edge_change_sigma(sigma[0], sigma[1], 12.0, corr[0, 1])) == pytest.approx(change.std(), rel=0.05)
    assert float(edge_change_sigma(sigma[0], sigma[1], 12.0, corr[0, 1])) < float(edge_change_sigma(sigma[0],
                                                                                                    sigma[1], 12.0))

    def area(v):
        return 0.5 * ((v[..., 1, 0] - v[..., 0, 0]) * (v[..., 2, 1] - v[..., 0, 1])
                      - (v[..., 2, 0] - v[..., 0, 0]) * (v[..., 1, 1] - v[..., 0, 1]))

    predicted = area_change_sigma(tri[None], sigma[None], area(tri), model)[0]
    assert predicted == pytest.approx((area(noisy) / area(tri) - 1).std(), rel=0.05)


@pytest.mark.parametrize("ratio", [0.9, 3.0])
def test_the_membrane_model_matches_a_lattice_of_windows(ratio):
    """:func:`variance_factor` and :meth:`Regularisation.correlation` against the system they model, solved
    directly: white pixel noise summed over each node's 13 px window (nodes 3 px apart, unit gradients: data weight
    169 per node), the nodes tied to their neighbours by a membrane ``ratio`` times that weight."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    rng = np.random.default_rng(2)
    n, step, win, samples = 40, 3, 13, 300
    side = (n - 1) * step + win
    noise = rng.normal(size=(samples, side, side))
    ii = np.pad(noise.cumsum(1).cumsum(2), ((0, 0), (1, 0), (1, 0)))
    at = np.arange(n) * step
    r0, c0 = at[:, None], at[None, :]
    b = (ii[:, r0 + win, c0 + win] - ii[:, r0, c0 + win] - ii[:, r0 + win, c0] + ii[:, r0, c0]).reshape(samples, -1)
    g = float(win * win)
    path = sp.diags([np.r_[1.0, 2.0 * np.ones(n - 2), 1.0]], [0]) - sp.diags([np.ones(n - 1)] * 2, [-1, 1])
    lap = sp.kron(sp.eye(n), path) + sp.kron(path, sp.eye(n))
    u = splu(sp.csc_matrix(g * sp.eye(n * n) + ratio * g * lap)).solve(b.T).T.reshape(samples, n, n)
    mid = u[:, 14:26, 14:22]  # nodes away from the lattice's edge, and the same 4 nodes (12 px) to their right
    right = u[:, 14:26, 18:26]
    assert np.mean(mid**2) * g == pytest.approx(float(variance_factor(ratio, win / step)), rel=0.1)
    measured = np.mean(mid * right) / np.sqrt(np.mean(mid**2) * np.mean(right**2))
    model = Regularisation(grid_step_px=step, window_nodes=win / step, membrane=ratio)
    assert measured == pytest.approx(float(model.correlation(np.array([12.0, 0.0]))), abs=0.06)


@pytest.fixture(scope="module")
def print_pair():
    image = print_image()
    return [print_frame(image, k, px_per_mm=19.7, background=255.0, shape=SHAPE) for k in (0, 1)]


def test_a_point_registered_a_ridge_astray_is_unbounded(print_pair):
    refiner = SubpixelRefiner(calibration=Calibration(px_per_mm=19.7))
    a, b = (refiner.prepare(f) for f in print_pair)
    pts = np.array([[150.0, 110.0], [170.0, 130.0], [140.0, 100.0]])
    right = np.column_stack([_true_dx(pts[:, 0], 0, 1), np.zeros(3)])
    ok = refiner.registration_check(a, b, pts, right)
    assert np.all(ok.match > 0.9) and np.all(np.isfinite(ok.sigma)) and np.all(ok.sigma < 0.05)
    astray = right + [4.0, 0.0]  # half a ridge period at 19.7 px/mm
    bad = refiner.registration_check(a, b, pts, astray)
    assert np.all(bad.match < MIN_MATCH) and np.all(np.isinf(bad.sigma))


def test_a_frame_prepared_without_its_gradient_measures_the_same(print_pair):
    """The live view prepares frames without the gradient (it has no uncertainty step): the registration and,
    where asked for, the covariance (its gradient then computed on demand) are the same."""
    refiner = SubpixelRefiner(calibration=Calibration(px_per_mm=19.7))
    full = [refiner.prepare(f) for f in print_pair]
    lean = [refiner.prepare(f, gradient=False) for f in print_pair]
    assert lean[0].gradient is None and full[0].gradient is not None
    assert np.array_equal(lean[0].image, full[0].image)
    pts = np.array([[150.0, 110.0], [170.0, 130.0], [140.0, 100.0]])
    start = np.column_stack([_true_dx(pts[:, 0], 0, 1), np.zeros(3)]) + 0.3
    r_full, r_lean = refiner.refine(*full, pts, start), refiner.refine(*lean, pts, start)
    assert r_full.refined.all() and np.array_equal(r_full.displacement, r_lean.displacement)
    cov = [refiner.displacement_covariance(*p, pts, r_full.displacement) for p in (full, lean)]
    np.testing.assert_array_equal(cov[0], cov[1])


@pytest.mark.parametrize("px_per_mm", [19.7, 62.0])
def test_the_flow_s_sigma_covers_its_error(px_per_mm):
    image = print_image()
    a, b = (print_frame(image, k, px_per_mm=px_per_mm, background=255.0, shape=SHAPE) for k in (0, 3))
    f = DenseFlow(calibration=Calibration(px_per_mm=px_per_mm)).compute(a, b)
    assert f.status == "ok"
    X, _ = np.meshgrid(f.grid_x, f.grid_y)
    err = np.hypot(f.displacement[..., 0] - _true_dx(X, 0, 3), f.displacement[..., 1])[f.valid]
    sigma = f.sigma[f.valid]
    assert np.mean(np.isfinite(sigma)) > 0.9  # unbounded: windows that do not match (the contact's edge)
    assert np.mean(err <= RADIUS_95_2D * sigma) >= 0.9
    assert np.median(f.match[f.valid]) > 0.9


def test_the_flow_s_sigma_holds_part_of_what_its_membrane_smooths(monkeypatch):
    """A 0.4 mm band of 5 % stretch travelling across a print at 100 px/mm: the membrane flattens it, a bias the
    windows' noise does not show. The smoothing's bias estimated from the solved field (``membrane_bias``) brings
    most of the points inside their 95 % intervals, where the noise alone covered fewer than half."""
    from skinstretch.processing import flow as flow_module
    from skinstretch.simulators.moved_print import ClipConditions, PrintMotion, TravellingBand, render_print_clip

    clip = render_print_clip(ClipConditions(px_per_mm=100.0, shape=(240, 320), n_frames=12, background="grey"),
                             PrintMotion(slide_px=(0.5, 0.0), band=TravellingBand(0.05, 0.4, -1.0, 0.1)))

    def coverage():
        fields = DenseFlow(calibration=Calibration(px_per_mm=100.0)).compute_sequence(clip.frames, threads=1)
        inside = []
        for f in fields:
            m = f.motion()
            true, _ = clip.field.between(m.points, f.frame_a, f.frame_b)
            inside.append(np.hypot(*(m.displacement - true).T) <= RADIUS_95_2D * m.sigma)
        return float(np.mean(np.concatenate(inside)))

    with_bias = coverage()
    monkeypatch.setattr(flow_module, "membrane_bias", lambda field, membrane, contact, *a, **k: np.zeros(contact.shape))
    noise_only = coverage()
    assert with_bias >= 0.75 and noise_only < 0.5, (with_bias, noise_only)


@pytest.fixture(scope="module")
def wide_clip():
    """A 19.7 px/mm print on white in a 640x484 frame: two pyramid levels alias its ridges (the fault the
    scale-derived levels fixed) and lock some pairs' fields onto wrong ridges."""
    image = print_image()
    return np.stack([print_frame(image, k, px_per_mm=19.7, background=255.0, shape=(484, 640), contact=None)
                     for k in range(6)])


def test_a_flow_locked_onto_wrong_ridges_is_doubted(wide_clip):
    flow = DenseFlow(calibration=Calibration(px_per_mm=19.7), params=FlowParams(pyramid_levels=2))
    statuses = [flow.compute(wide_clip[k], wide_clip[k + 1]).status for k in range(5)]
    assert sum(s.startswith("doubted: ") for s in statuses) >= 2  # those fields are tens of px wrong
    assert flow.compute(wide_clip[1], wide_clip[2]).motion().doubt


@pytest.mark.parametrize("method", ["features", "flow"])
@pytest.mark.parametrize("background", [255.0, 0.0])
@pytest.mark.parametrize("px_per_mm", [19.7, 40.0, 62.0])
def test_the_analysis_is_right_or_says_so(px_per_mm, background, method):
    """A real print at three pixel scales, inside a contact on a white or black background: every measured point
    within 0.05 px (RMSE) with its 95 % interval covering the truth, or a warning in the summary."""
    image = print_image()
    frames = np.stack([print_frame(image, k, px_per_mm=px_per_mm, background=background, shape=SHAPE)
                       for k in range(14)])
    r = analyze_frames(frames, calibration=Calibration(px_per_mm=px_per_mm), method=method,
                       params={"strain": {"spans": [1, 5]}, "execution": {"kind": "serial"}})
    warnings = r.summary["warnings"]
    m, pairs = r.motion, r.motion_pairs
    err = np.hypot(m["dx"] - _true_dx(m["x"], pairs["frame_a"][m["pair"]], pairs["frame_b"][m["pair"]]), m["dy"])
    accurate = err.size > 0 and np.sqrt(np.mean(err**2)) <= 0.05 and np.mean(err <= RADIUS_95_2D * m["sigma"]) >= 0.9
    assert accurate or warnings, (px_per_mm, background, method, err.size)
    if method == "flow":  # the dense method is accurate on every one of these
        assert accurate and not warnings
        # ...and its edges' predicted errors, their ends correlated (Regularisation), cover their errors
        s = r.strain[5]
        e, fa, fb = s.edges, s.pairs["frame_a"][s.edges["pair"]], s.pairs["frame_b"][s.edges["pair"]]
        moved = (e["xb"] + _true_dx(e["xb"], fa, fb)) - (e["xa"] + _true_dx(e["xa"], fa, fb))
        err = e["change"] - (np.hypot(moved, e["yb"] - e["ya"]) / e["length"] - 1)
        assert np.mean(np.abs(err) <= 1.96 * e["change_sigma"]) >= 0.9
    # the motion from the reference frame (DIC's reference image) carries a sigma that covers its error too
    c = r.cumulative
    cm, frame_b = c.motion, c.pairs["frame_b"][c.motion["pair"]]
    cum_err = np.hypot(cm["dx"] - _true_dx(cm["x"], c.reference_frame, frame_b), cm["dy"])
    assert (cm.size > 0 and np.mean(cum_err <= RADIUS_95_2D * cm["sigma"]) >= 0.9) or warnings, method
    assert set(r.summary["uncertainty"]) == {"displacement_sigma_px", "edge_change_sigma_span_1",
                                             "edge_change_sigma_span_5"}


def test_a_failed_registration_is_flagged_in_the_results_and_the_summary(wide_clip):
    r = analyze_frames(wide_clip, calibration=Calibration(px_per_mm=19.7), method="flow",
                       params={"flow": {"pyramid_levels": 2}, "strain": {"spans": [1, 3]},
                               "execution": {"kind": "serial"}})
    doubted = r.motion_pairs["status"] == PairStatus.DOUBTED
    assert doubted.sum() >= 2
    assert all(reason.startswith(b"the frames do not match") for reason in r.motion_pairs["reason"][doubted])
    assert any("consecutive frame pairs failed a self-check" in w for w in r.summary["warnings"])
    assert r.summary["strain_span_1"]["pairs_doubted"] >= 2


def test_an_error_neighbours_share_leaves_the_strain_s_sigma_alone():
    """A part of every point's error that all points share (a codec's, moving neighbours alike) moves no edge: with
    ``shared_sigma_px`` the edges' and triangles' predicted errors are those of the independent part alone, and the
    simulated edge errors agree with them."""
    from skinstretch.experiments.analysis.derive import span_strain
    from skinstretch.processing.tracking import MotionSample

    rng = np.random.default_rng(5)
    gx, gy = np.meshgrid(np.arange(8) * 20.0, np.arange(8) * 20.0)
    p = np.stack([gx.ravel(), gy.ravel()], 1)
    independent, shared = 0.02, 0.05
    sigma = np.full(len(p), np.hypot(independent, shared))
    samples = [MotionSample(k, k + 1, p, rng.normal(0, independent, p.shape) + rng.normal(0, shared, 2), np.arange(len(p)),
                            sigma=sigma) for k in range(200)]
    with_shared = span_strain(samples, span=1, max_edge_px=30.0, shared_sigma_px=shared)
    without = span_strain(samples[:1], span=1, max_edge_px=30.0)
    ratio = with_shared.edges["change"] / with_shared.edges["change_sigma"]  # true change 0: the error over its sigma
    assert np.std(ratio) == pytest.approx(1.0, abs=0.05)
    np.testing.assert_allclose(without.edges["change_sigma"] / with_shared.edges["change_sigma"][:len(without.edges)],
                               np.hypot(independent, shared) / independent)
    assert np.all(with_shared.triangles["change_sigma"][:len(without.triangles)]
                  < without.triangles["change_sigma"])
