"""Feature matching and trajectories (seed 5.1), robust prediction and sub-pixel refinement."""

import numpy as np
import pytest

from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.feature_table import empty_features, make_features
from skinstretch.processing.global_motion import GlobalMotionEstimator, local_predictions
from skinstretch.processing.displacement_refinement import SubpixelParams, SubpixelRefiner
from skinstretch.processing.tracking import FeatureTracker, TrackingParams, match_features, smooth_positions
from tests.test_track_support import affine_field, moving_features, render

CAL = Calibration(px_per_mm=62.0)


def _truth_ids(tr, truth):
    """For every trajectory sample, the index of the nearest true point (within 2 px), else -1."""
    ids = np.full(tr.present.shape, -1)
    for k in range(tr.n_frames):
        have = np.nonzero(tr.present[k])[0]
        d = np.hypot(tr.raw_x[k, have, None] - truth[k][None, :, 0], tr.raw_y[k, have, None] - truth[k][None, :, 1])
        j = d.argmin(axis=1)
        ids[k, have] = np.where(d[np.arange(have.size), j] < 2.0, j, -1)
    return ids


def test_match_same_kind_only_and_one_to_one():
    a = make_features([10.0, 12.0], [10.0, 10.0], [0, 2], orientation=[0.0, np.nan])
    b = make_features([11.0, 13.0, 11.5], [10.0, 10.0, 10.0], [2, 0, 2], orientation=[np.nan, 0.0, np.nan])
    m = match_features(a, b, calibration=CAL)
    pairs = dict(zip(m.prev_index.tolist(), m.curr_index.tolist()))
    assert pairs[0] == 1  # valley ending -> the only valley ending
    assert pairs[1] in (0, 2) and len(set(pairs.values())) == len(pairs)


def test_orientation_breaks_ties_eq_5_1():
    a = make_features([50.0], [50.0], [0], orientation=[90.0])
    # two candidates at the same distance; the one with the closer orientation wins
    b = make_features([52.0, 48.0], [50.0, 50.0], [0, 0], orientation=[270.0, 80.0])
    m = match_features(a, b, calibration=CAL)
    assert m.curr_index.tolist() == [1]
    assert m.confidence[0] == pytest.approx((180 - 10) / 180 + (CAL.px(0.3) - 2) / CAL.px(0.3))


def test_prediction_moves_the_search_window():
    a = make_features([10.0], [10.0], [2])
    b = make_features([40.0], [10.0], [2])
    assert len(match_features(a, b, calibration=CAL)) == 0  # 30 px > 0.3 mm window
    assert len(match_features(a, b, calibration=CAL, predicted_displacement=[29.0, 0.0])) == 1


def test_bad_inputs_are_named():
    a = make_features([1.0], [1.0], [2])
    with pytest.raises(InvalidInputError, match="search_radius_mm"):
        match_features(a, a, calibration=CAL, search_radius_mm=0)
    with pytest.raises(InvalidInputError, match="predicted_displacement"):
        match_features(a, a, calibration=CAL, predicted_displacement=np.zeros((3, 2)))
    with pytest.raises(InvalidInputError, match="min_length_frames"):
        TrackingParams(min_length_frames=0)
    with pytest.raises(InsufficientDataError):
        FeatureTracker(calibration=CAL).finish().dense()


@pytest.mark.parametrize("step", [(2.0, 0.5), (10.0, 0.0)])  # 10 px/frame: fast sliding
def test_tracks_with_noise_misses_and_spurious_features(step):
    tables, truth = moving_features(40, n=60, step=step, noise=0.3, missing=0.05, spurious=8, seed=3)
    tracker = FeatureTracker(calibration=CAL, params=TrackingParams(min_length_frames=10))
    for t in tables:
        tracker.add_frame(t)
    tr = tracker.finish().dense()
    assert tr.n_tracks >= 40
    ids = _truth_ids(tr, truth)
    linked = tr.linked[1:] & (ids[1:] >= 0) & (ids[:-1] >= 0)
    wrong = linked & (ids[1:] != ids[:-1])
    assert linked.sum() > 1000
    assert wrong.sum() / linked.sum() < 0.005
    assert np.all(np.isnan(tr.x[~tr.present])) and np.all(np.isfinite(tr.x[tr.present]))


def test_empty_frame_mid_sequence_is_flagged_not_fatal():
    tables, _ = moving_features(10, n=20, step=(2.0, 0.0), seed=5)
    tables[4] = empty_features(0)
    tracker = FeatureTracker(calibration=CAL, params=TrackingParams(min_length_frames=2))
    for t in tables:
        tracker.add_frame(t)
    assert tracker.pair_status[3] == "fewer than 3 matches" and tracker.pair_status[4] == "fewer than 3 matches"
    table = tracker.finish()
    tr = table.dense()
    assert not tr.present[4].any()
    assert len(table.motion(3, 5)) == 0  # nothing is measured across the empty frame
    assert len(table.motion(6, 7)) > 10


def test_smoothing_is_normalised_and_keeps_lines():
    n = 9
    pos = np.stack([np.arange(n, dtype=float), np.full(n, 5.0)], axis=1)[:, None, :]
    present = np.ones((n, 1), bool)
    linked = present.copy()
    linked[0] = False
    out = smooth_positions(pos, present, linked, radius_frames=3, sigma_frames=2.0)
    np.testing.assert_allclose(out[3:-3, 0], pos[3:-3, 0], atol=1e-12)  # a straight line stays
    np.testing.assert_allclose(out[:, 0, 1], 5.0)  # no pull toward zero at the ends
    noisy = pos + np.random.default_rng(0).normal(0, 0.5, pos.shape)
    sm = smooth_positions(noisy, present, linked, radius_frames=1, sigma_frames=1.0)
    assert np.std(sm - pos) < np.std(noisy - pos)


def test_minimum_length_filter():
    tables, _ = moving_features(20, n=10, step=(1.0, 0.0), seed=6)
    tables[10] = tables[10][:5]  # five features lost mid-way: their tracks are split in two of 10 frames
    tracker = FeatureTracker(calibration=CAL, params=TrackingParams(min_length_frames=15))
    for t in tables:
        tracker.add_frame(t)
    assert tracker.finish().dense().n_tracks == 5


def test_global_motion_and_local_prediction():
    f0 = render(affine_field(0, 0), shape=(200, 240))
    f1 = render(affine_field(-7.0, 3.0), shape=(200, 240))
    m = GlobalMotionEstimator().estimate(f0, f1)
    assert m.reliable and np.abs(m.shift - [-7.0, 3.0]).max() < 1.0
    flat = np.full((200, 240), 128, np.uint8)
    assert not GlobalMotionEstimator().estimate(flat, flat).reliable
    pts = np.array([[0.0, 0.0], [100.0, 0.0]])
    mp = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [99.0, 0.0], [101.0, 0.0], [100.0, 1.0], [100.0, 2.0]])
    md = np.array([[1.0, 0], [1.0, 0], [9.0, 9], [-2.0, 0], [-2.0, 0], [-2.0, 0], [5.0, 5]])
    pred = local_predictions(pts, mp, md, neighbours=3)
    np.testing.assert_allclose(pred, [[1.0, 0.0], [-2.0, 0.0]])  # the median rejects the odd neighbour


def test_robust_tracker_survives_direction_reversal():
    """A 9 px/frame slide that reverses: the seed predictor expects +9 and looks 18 px away from the truth."""
    rng = np.random.default_rng(7)
    p0 = np.column_stack([rng.uniform(60, 260, 40), rng.uniform(50, 190, 40)])
    kinds = rng.integers(0, 3, 40)
    shifts = [0.0, 9.0, 18.0, 9.0, 0.0, -9.0]
    def run(estimator):
        tracker = FeatureTracker(
            calibration=CAL, params=TrackingParams(min_length_frames=1, search_radius_mm=0.25),
            motion_estimator=estimator,
        )
        for s in shifts:
            img = render(affine_field(s, 0.0), shape=(240, 320))
            tracker.add_frame(make_features(p0[:, 0] + s, p0[:, 1], kinds), image=img)
        return tracker.finish().dense()
    robust = run(GlobalMotionEstimator())
    assert robust.n_tracks == 40 and robust.lengths.min() == len(shifts)
    tables = [make_features(p0[:, 0] + s, p0[:, 1], kinds) for s in shifts]
    seed = FeatureTracker(calibration=CAL, params=TrackingParams(min_length_frames=1, search_radius_mm=0.25))
    for t in tables:
        seed.add_frame(t)
    assert seed.finish().dense().n_tracks > 40  # the seed's predictor loses them at the reversal


def test_subpixel_refinement_reaches_hundredths_of_a_pixel():
    f0 = render(affine_field(0, 0), shape=(200, 240), noise=1.0)
    f1 = render(affine_field(2.37, -1.62), shape=(200, 240), noise=1.0, rng=np.random.default_rng(9))
    pts = np.array([[60.0, 60.0], [120.0, 100.0], [180.0, 140.0]])
    r = SubpixelRefiner(calibration=CAL).refine(f0, f1, pts, np.tile([2.0, -2.0], (3, 1)))
    assert r.refined.all()
    err = np.abs(r.displacement - [2.37, -1.62])
    assert np.median(err) < 0.01 and err.max() < 0.08  # along a ridge without pore the window sees less
    # a start 2 px off along x is beyond max_correction_mm = 0.01 mm (0.62 px): kept, flagged
    strict = SubpixelRefiner(calibration=CAL, params=SubpixelParams(max_correction_mm=0.01))
    r2 = strict.refine(f0, f1, pts, np.tile([0.3, -1.6], (3, 1)))
    assert not r2.refined.any() and np.allclose(r2.displacement, [0.3, -1.6])
    edge = SubpixelRefiner(calibration=CAL).refine(f0, f1, np.array([[2.0, 2.0]]), np.zeros((1, 2)))
    assert not edge.refined[0] and np.isnan(edge.residual[0])


def test_refined_tracker_positions_are_subpixel():
    rng = np.random.default_rng(11)
    p0 = np.column_stack([rng.uniform(50, 270, 30), rng.uniform(50, 190, 30)])
    kinds = np.full(30, 2)
    steps = np.array([[0.0, 0.0], [1.3, 0.4], [2.9, 0.7], [4.2, 1.3], [5.9, 1.2]])
    tracker = FeatureTracker(
        calibration=CAL, params=TrackingParams(min_length_frames=5, smoothing_radius_frames=0),
        refiner=SubpixelRefiner(calibration=CAL),
    )
    for s in steps:
        img = render(affine_field(*s), shape=(240, 320))
        noisy = p0 + s + rng.normal(0, 0.5, p0.shape)  # extraction noise of half a pixel
        tracker.add_frame(make_features(noisy[:, 0], noisy[:, 1], kinds), image=img)
    m = tracker.finish().motion(0, 4)
    assert len(m) >= 20
    err = np.hypot(*(m.displacement - (steps[4] - steps[0])).T)
    assert np.median(err) < 0.03 and np.sqrt(np.mean(err**2)) < 0.06  # vs 0.7 px for the extracted positions


def _reference_match(a, b, pred, radius):
    """Eq. 5.1 matching written out pair by pair (the compiled matcher must give the same pairs)."""
    cands = []
    ax, ay, ao, bx, by, bo = (t[c].astype(np.float64) for t in (a, b) for c in ("x", "y", "orientation"))
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            d = np.hypot(bx[j] - (ax[i] + pred[i, 0]), by[j] - (ay[i] + pred[i, 1]))
            if d > radius or a["kind"][i] != b["kind"][j]:
                continue
            orient = 0.0
            if a["orientation_known"][i] and b["orientation_known"][j]:
                dtheta = abs((ao[i] - bo[j] + 180.0) % 360.0 - 180.0)
                orient = (180.0 - dtheta) / 180.0
            cands.append((-(orient + (radius - d) / radius), d, i, j))
    used_a, used_b, out = set(), set(), {}
    for negc, _, i, j in sorted(cands):
        if i not in used_a and j not in used_b:
            used_a.add(i), used_b.add(j)
            out[i] = (j, -negc)
    return out


def test_compiled_matching_equals_the_written_out_rule():
    rng = np.random.default_rng(5)
    radius = CAL.px(0.3)
    for trial in range(20):
        n, m = rng.integers(0, 60, 2)
        orient_a = np.where(rng.random(n) < 0.3, np.nan, rng.uniform(0, 360, n))
        orient_b = np.where(rng.random(m) < 0.3, np.nan, rng.uniform(0, 360, m))
        a = make_features(rng.uniform(0, 120, n), rng.uniform(0, 120, n), rng.integers(0, 3, n), orientation=orient_a)
        b = make_features(rng.uniform(0, 120, m), rng.uniform(0, 120, m), rng.integers(0, 3, m), orientation=orient_b)
        pred = rng.normal(0, 3, (n, 2))
        got = match_features(a, b, calibration=CAL, predicted_displacement=pred)
        ref = _reference_match(a, b, pred, radius)
        assert got.prev_index.tolist() == sorted(ref)  # sorted by row of the previous frame
        assert got.curr_index.tolist() == [ref[i][0] for i in sorted(ref)]
        np.testing.assert_allclose(got.confidence, [ref[i][1] for i in sorted(ref)], rtol=0, atol=1e-12)


def test_local_predictions_are_medians_of_nearest_neighbours():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(6)
    for k in (1, 4, 7):
        mp = rng.uniform(0, 300, (80, 2))
        md = rng.normal(0, 2, (80, 2))
        pts = np.concatenate([rng.uniform(0, 300, (50, 2)), mp[:10]])  # also at matched points themselves
        _, idx = cKDTree(mp).query(pts, k=k)
        expected = np.median(md[idx.reshape(len(pts), k)], axis=1)
        np.testing.assert_array_equal(local_predictions(pts, mp, md, neighbours=k), expected)


def test_prepared_images_give_the_same_tracks_as_raw_images():
    """The analysis prepares each frame's images on its worker threads (prepare_image); add_frame(prepared=...)
    must track exactly as add_frame(image=...)."""
    rng = np.random.default_rng(12)
    p0 = np.column_stack([rng.uniform(50, 270, 30), rng.uniform(50, 190, 30)])
    kinds = np.full(30, 2)
    steps = np.array([[0.0, 0.0], [1.3, 0.4], [2.9, 0.7], [4.2, 1.3]])
    images = [render(affine_field(*s), shape=(240, 320)) for s in steps]
    tables = [make_features(*(p0 + s + rng.normal(0, 0.5, p0.shape)).T, kinds) for s in steps]

    def tracker():
        return FeatureTracker(
            calibration=CAL, params=TrackingParams(min_length_frames=2), refiner=SubpixelRefiner(calibration=CAL),
            motion_estimator=GlobalMotionEstimator(),
        )

    a, b = tracker(), tracker()
    for img, t in zip(images, tables):
        a.add_frame(t, image=img)
        b.add_frame(t, prepared=b.prepare_image(img))
    ta, tb = a.finish().dense(), b.finish().dense()
    assert ta.n_tracks >= 25 and ta.refined.sum() > 50
    np.testing.assert_array_equal(ta.x, tb.x)
    np.testing.assert_array_equal(ta.refined, tb.refined)
    with pytest.raises(InvalidInputError, match="image is required"):
        tracker().add_frame(tables[0])
