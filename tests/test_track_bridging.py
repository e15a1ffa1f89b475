"""Trajectories through missed detections (points followed by registration), the registration's deformation bias,
local displacement gradients and the strain mesh's minimum spacing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.processing.displacement_refinement import SubpixelRefiner
from skinstretch.processing.feature_table import make_features
from skinstretch.processing.global_motion import local_gradients
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.stretch import triangulation_strain, triangulation_strains
from skinstretch.processing.tracking import FeatureTracker, MotionSample, TrackingParams, step_consistency
from tests.test_track_support import affine_field, render

CAL = Calibration(px_per_mm=62.0)
CENTRE = (160.0, 120.0)


def _sequence(n_frames, *, step=(1.3, 0.4), stretch=0.002, seed=5):
    """Frames of the test pattern sliding by ``step`` px and stretching by ``stretch`` along x per frame, and the
    true position of the skin points ``p0`` in every frame."""
    rng = np.random.default_rng(seed)
    p0 = np.column_stack([rng.uniform(50, 270, 30), rng.uniform(50, 190, 30)])
    frames, truth = [], []
    for k in range(n_frames):
        tx, ty, exx = step[0] * k, step[1] * k, stretch * k
        frames.append(render(affine_field(tx, ty, exx, 0.0, CENTRE), shape=(240, 320), noise=1.0,
                             rng=np.random.default_rng(100 + k)))
        truth.append(np.column_stack([p0[:, 0] + tx + exx * (p0[:, 0] - CENTRE[0]), p0[:, 1] + ty]))
    return frames, truth


def _track(frames, truth, missed, bridge):
    tracker = FeatureTracker(
        calibration=CAL, refiner=SubpixelRefiner(calibration=CAL),
        params=TrackingParams(min_length_frames=len(frames), smoothing_radius_frames=0, max_bridge_frames=bridge),
    )
    for k, (img, xy) in enumerate(zip(frames, truth)):
        keep = ~missed[k]
        tracker.add_frame(make_features(xy[keep, 0], xy[keep, 1], np.full(int(keep.sum()), 2), frame=k), image=img)
    return tracker.finish()


def _full_length(trajectories, truth, n_frames):
    """Indices of the skin points (rows of ``truth[0]``) followed over the whole clip by one trajectory, and the
    error (px) of every position of those trajectories, and whether it was bridged (no feature found)."""
    rows = trajectories.rows
    start = rows[rows["frame"] == 0]
    point = np.argmin(np.hypot(truth[0][None, :, 0] - start["raw_x"][:, None],
                               truth[0][None, :, 1] - start["raw_y"][:, None]), axis=1)
    full = trajectories.lengths[start["track"]] == n_frames
    errors, bridged = [], []
    for t, i in zip(start["track"][full], point[full]):
        r = rows[rows["track"] == t]
        true = np.array([truth[f][i] for f in r["frame"]])
        errors.append(np.hypot(r["x"] - true[:, 0], r["y"] - true[:, 1]))
        bridged.append(r["feature_index"] < 0)
    cat = lambda v: np.concatenate(v) if v else np.zeros(0)  # noqa: E731
    return set(point[full].tolist()), cat(errors), cat(bridged).astype(bool)


def test_a_feature_missed_for_several_frames_keeps_its_trajectory():
    n = 16
    frames, truth = _sequence(n)
    missed = np.zeros((n, 30), bool)
    missed[3:11, :10] = True  # ten features missed for 8 frames
    followed = _track(frames, truth, missed, None)
    kept, err, bridged = _full_length(followed, truth, n)
    # Followed by registration through the gap (a window on ridges alone may slide along them and is let go).
    assert len(kept & set(range(10))) >= 8 and len(kept) >= 26
    assert bridged.sum() >= 8 * 8
    # The positions through the gap are measured, not guessed: as good as the detected ones (the test pattern's
    # ridges without a pore let a few windows slide along them, found or not).
    assert np.median(err[bridged]) < 0.05 and np.median(err[bridged]) < 1.5 * np.median(err[~bridged]) + 0.01
    # Without bridging beyond the gap those trajectories break: none of the ten is kept over the whole clip.
    kept0, _, _ = _full_length(_track(frames, truth, missed, 0), truth, n)
    assert not kept0 & set(range(10)) and len(kept0) >= 18


def test_deformation_bias_is_what_stretch_inside_the_window_adds():
    s = 0.005  # a frame-to-frame strain
    f0 = render(affine_field(0, 0), shape=(240, 320))
    f1 = render(affine_field(0.8, -0.5, s, -s, CENTRE), shape=(240, 320))
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(40, 280, 40), rng.uniform(40, 200, 40)])
    true = np.column_stack([0.8 + s * (pts[:, 0] - CENTRE[0]), -0.5 - s * (pts[:, 1] - CENTRE[1])])
    ref = SubpixelRefiner(calibration=CAL)
    a, b = ref.prepare(f0), ref.prepare(f1)
    r = ref.refine(a, b, pts, true)
    bias = ref.deformation_bias(a, pts, np.tile([[s, 0.0], [0.0, -s]], (40, 1, 1)))
    before = np.median(np.hypot(*(r.displacement - true)[r.refined].T))
    after = np.median(np.hypot(*(r.displacement - bias - true)[r.refined].T))
    assert r.refined.sum() >= 20 and before > 0.02 and after < 0.3 * before
    # No deformation, no bias; a window off the image has none either.
    assert np.allclose(ref.deformation_bias(a, pts, np.zeros((40, 2, 2))), 0.0)
    assert np.allclose(ref.deformation_bias(a, np.array([[1.0, 1.0]]), np.ones((1, 2, 2))), 0.0)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-0.05, 0.05), min_size=4, max_size=4), st.integers(0, 1000))
def test_local_gradients_of_an_affine_field_are_exact(g, seed):
    grad = np.array(g).reshape(2, 2)
    p = np.random.default_rng(seed).uniform(0, 300, (25, 2))
    d = np.array([1.5, -0.7]) + p @ grad.T
    np.testing.assert_allclose(local_gradients(p, d), np.broadcast_to(grad, (25, 2, 2)), atol=1e-9)


def test_min_spacing_keeps_the_oldest_of_close_points():
    p = np.array([[0.0, 0.0], [40.0, 0.0], [0.0, 40.0], [40.0, 40.0], [3.0, 2.0], [42.0, 41.0]])
    ids = np.array([5, 1, 2, 3, 0, 9])
    s = MotionSample(0, 1, p, np.zeros_like(p), ids)
    assert sorted(triangulation_strain(s).ids.tolist()) == [0, 1, 2, 3, 5, 9]
    # (0, 0) id 5 is within 10 px of (3, 2) id 0: the older (0) stays; (42, 41) id 9 goes for id 3.
    assert sorted(triangulation_strain(s, min_spacing_px=10.0).ids.tolist()) == [0, 1, 2, 3]
    with pytest.raises(Exception, match="min_spacing_px"):
        triangulation_strains([s], min_spacing_px=-1.0)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.0, 60.0), st.floats(-0.05, 0.05))
def test_a_uniform_strain_is_exact_whatever_the_spacing(seed, spacing, e):
    rng = np.random.default_rng(seed)
    p = rng.uniform(0, 400, (80, 2))
    s = MotionSample(0, 1, p, e * p, rng.permutation(80))
    r = triangulation_strain(s, min_spacing_px=spacing)
    np.testing.assert_allclose(r.edge_change, e, atol=1e-9)
    if r.points.shape[0] > 1:
        gaps = np.hypot(*(r.points[:, None] - r.points[None]).transpose(2, 0, 1))
        assert gaps[np.triu_indices(r.points.shape[0], 1)].min() >= spacing


def test_local_gradients_at_some_points_are_those_rows_of_all():
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 300, (40, 2))
    d = rng.normal(0, 0.5, (40, 2))
    at = np.array([3, 17, 39])
    np.testing.assert_array_equal(local_gradients(p, d, at=at), local_gradients(p, d)[at])
    assert local_gradients(p, d, at=np.zeros(0, np.int64)).shape == (0, 2, 2)



def test_a_step_by_registration_alone_is_held_to_the_frames_spread():
    """A step measured by registration alone that departs from its neighbours by less than the absolute bound but
    far outside the frame's spread of such departures is let go (at a valley's bottom a window locks onto what the
    shading step leaves and drifts 0.3-0.5 px a frame); where the skin stretches fast every step departs from its
    neighbours' median and the spread grows with it: nothing is let go."""
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(0, 300, 40), rng.uniform(0, 200, 40)])
    valid = np.ones(40, bool)
    # 0.05 % a frame and a 0.3 px stray step; 0.8 % a frame (deviations from the neighbours' median up to 0.45 px)
    for exx, outlier in ((0.0005, (0.25, 0.2)), (0.008, (0.0, 0.0))):
        disp = np.column_stack([0.5 + exx * (pts[:, 0] - 150), np.full(40, 0.1)]) + rng.normal(0, 0.005, (40, 2))
        disp[0] += outlier
        close, alone = step_consistency(pts, disp, valid, max_deviation_px=0.5, bridge_spreads=10.0)
        assert close.all()  # the absolute bound lets every step through
        assert alone[1:].all() and alone[0] == (outlier == (0.0, 0.0)), exx
        assert step_consistency(pts, disp, valid, max_deviation_px=0.5, bridge_spreads=None)[1].all()
