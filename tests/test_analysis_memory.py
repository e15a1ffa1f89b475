"""A session of any length in bounded memory: trajectories stored as the tracker hands frames out, percentiles of
more values than are held, the tactile movie a block of frames at a time (skinstretch.experiments.analysis
.trajectories, .percentiles, .derive), to the bit."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from skinstretch.experiments.analysis import analysis_params, analyze_frames
from skinstretch.experiments.analysis import derive as derive_module
from skinstretch.experiments.analysis import trajectories as trajectories_module
from skinstretch.experiments.analysis.derive import Derived, tactile_movie_blocks
from skinstretch.experiments.analysis.percentiles import StreamedPercentiles
from skinstretch.experiments.analysis.trajectories import TrajectoryStore
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.display_mapping import DisplayMappingParams, tactile_movie
from skinstretch.processing.fingertip import fingertip_motion, visibility_window
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.tracking import FeatureTracker, MotionSample, TrackingParams
from tests.helpers import sliding_feature_grid

scene = pytest.importorskip("skinstretch.simulators.scene")


@pytest.mark.parametrize("smoothing", [0, 1, 2])
@pytest.mark.parametrize("take_every", [1, 3, 7])
def test_stored_trajectories_are_those_of_finish_to_the_bit(smoothing, take_every):
    params = TrackingParams(min_length_frames=3, smoothing_radius_frames=smoothing)
    cal = Calibration(px_per_mm=62.0)
    whole, taken = FeatureTracker(calibration=cal, params=params), FeatureTracker(calibration=cal, params=params)
    n = 40
    with TrajectoryStore(n_frames=n, params=params) as store:
        for k in range(n):
            whole.add_frame(sliding_feature_grid(k))
            taken.add_frame(sliding_feature_grid(k))
            if k % take_every == 0:
                store.add(taken.take_frames())
        store.add(taken.take_frames(last=True))
        ref = whole.finish()
        blocks = list(store.blocks(block_frames=5))
        rows = np.concatenate([b.rows for b in blocks])
        assert [b.first for b in blocks] == list(range(0, n, 5))
        assert all(np.all((b.rows["frame"] >= b.first) & (b.rows["frame"] < b.stop)) for b in blocks)
        for name in ref.rows.dtype.names:
            np.testing.assert_array_equal(rows[name], ref.rows[name], err_msg=name)
        np.testing.assert_array_equal(store.kinds, ref.kind)
        table = store.track_table()
        np.testing.assert_array_equal(table["n_frames"], ref.lengths)
        assert table["first_frame"].tolist() == [int(ref.rows["frame"][ref.rows["track"] == t].min())
                                                 for t in range(ref.n_tracks)]


def test_a_tracker_that_handed_frames_out_cannot_finish_and_the_store_wants_every_frame():
    params = TrackingParams(min_length_frames=3, max_bridge_frames=1)
    tracker = FeatureTracker(calibration=Calibration(px_per_mm=62.0), params=params)
    for k in range(6):
        tracker.add_frame(sliding_feature_grid(k))
    frames = tracker.take_frames()
    assert [f.frame for f in frames] == [0, 1, 2]  # the last max_bridge_frames + 2 stay for matching
    assert all(np.all(np.diff(f.track) > 0) for f in frames)
    with pytest.raises(InvalidInputError):
        tracker.finish()
    with TrajectoryStore(n_frames=6, params=params) as store:
        with pytest.raises(InvalidInputError, match="in order"):
            store.add(frames[1:])
        store.add(frames)
        with pytest.raises(InsufficientDataError, match="3 of 6 frames"):
            next(store.blocks())


_FLOATS = st.floats(allow_nan=False, allow_infinity=False, width=64) | st.sampled_from([0.0, -0.0, 1e-3, -2.5, 7.0])


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.integers(1, 300), elements=_FLOATS), st.lists(st.floats(0, 100), min_size=1, max_size=4),
       st.integers(1, 50), st.integers(1, 64))
def test_streamed_percentiles_are_numpys_to_the_bit(values, q, in_memory, block):
    with StreamedPercentiles(in_memory=in_memory, block=block) as sp:
        for i in range(0, values.size, 37):
            sp.add(values[i : i + 37])
        got = sp.percentiles(q)
    np.testing.assert_array_equal(np.array(got), np.percentile(values, q))


def test_streamed_percentiles_of_many_values_narrow_the_bin_in_passes():
    rng = np.random.default_rng(0)
    v = np.concatenate([rng.normal(0, 0.01, 200_000), np.zeros(50_000), rng.standard_cauchy(1000)])
    rng.shuffle(v)
    with StreamedPercentiles(in_memory=1000, block=1 << 14) as sp:
        for part in np.array_split(v, 7):
            sp.add(part)
        assert sp.count == v.size
        assert sp.percentiles([5, 50, 95]) == np.percentile(v, [5, 50, 95]).tolist()
    with StreamedPercentiles() as empty, pytest.raises(InsufficientDataError):
        empty.percentiles([5])


@pytest.mark.parametrize("axis, horizontal", [(0, "projection"), (1, "rotation")])
def test_the_movie_in_blocks_is_the_whole_movie(axis, horizontal):
    rng = np.random.default_rng(1)
    cal, shape, n = Calibration(px_per_mm=20.0), (400, 400), 30
    samples = [MotionSample(k, k + 1, rng.uniform(0, 400, (300, 2)), rng.normal(0, 0.5, (300, 2)) + [0.3, 0.1],
                            np.arange(300)) for k in range(n - 1)]
    ft = fingertip_motion(samples, n_frames=n)
    win = visibility_window(ft, image_shape=shape)
    params = DisplayMappingParams(horizontal=horizontal, range_um=20.0)
    whole = tactile_movie(samples, fingertip=ft, window=win, calibration=cal, image_shape=shape, params=params,
                          motion_axis=axis)
    derived = Derived(ft, win, "ok", "xy"[axis], profile=None)
    blocks = list(tactile_movie_blocks(samples, derived, calibration=cal, image_shape=shape, display_params=params,
                                       block_frames=7))
    assert [b.positions_um.shape[0] for b in blocks] == [7, 7, 7, 7, 2]
    assert whole.clipped.any() and whole.reset.any()
    for name in ("positions_um", "reset", "clipped", "ideal_um", "stretch_change"):
        np.testing.assert_array_equal(np.concatenate([getattr(b, name) for b in blocks]), getattr(whole, name))
    assert list(tactile_movie_blocks(samples, Derived(ft, None, "no window", "x", profile=None), calibration=cal,
                                     image_shape=shape, display_params=params)) == []


class _SkinMapping:
    """A geometric mapping image px -> skin mm (a slight anisotropic scale and shift): enough to tell rectified
    positions from image ones."""

    def __init__(self, px_per_mm: float) -> None:
        self.px_per_mm = px_per_mm

    def image_to_surface(self, xy):
        return (np.asarray(xy, dtype=np.float64) * [1.02, 0.97] + [3.0, -2.0]) / self.px_per_mm


def test_small_blocks_give_the_same_rectified_results(monkeypatch):
    """Trajectories, motion of every span and movie built a few frames at a time (rows carried across blocks for the
    longer span) are those built in one block; the motion follows from the rectified trajectories."""
    s = scene.render_session("ridgeL", n_frames=40, seed=1)
    mapping = _SkinMapping(s.calibration.px_per_mm)
    params = analysis_params({"tracking": {"min_length_frames": 5}, "strain": {"spans": [1, 3]},
                              "execution": {"kind": "serial"}})
    kw = dict(calibration=s.calibration, surface="ridge", method="features", params=params, mapping=mapping)
    whole = analyze_frames(s.frames, **kw)
    monkeypatch.setattr(trajectories_module, "BLOCK_FRAMES", 4)
    monkeypatch.setattr(derive_module, "MOVIE_BLOCK_FRAMES", 6)
    blocks = analyze_frames(s.frames, **kw)
    rows = blocks.trajectories.rows
    for name in rows.dtype.names:
        np.testing.assert_array_equal(rows[name], whole.trajectories.rows[name], err_msg=name)
    np.testing.assert_array_equal(blocks.motion, whole.motion)
    for span in (1, 3):
        np.testing.assert_array_equal(blocks.strain[span].edges, whole.strain[span].edges)
    np.testing.assert_array_equal(blocks.tactile_positions_um, whole.tactile_positions_um)
    assert blocks.summary["strain_span_3"] == whole.summary["strain_span_3"]
    # rectified: the raw positions are the extracted features' mapped to the skin (none for a point bridged by
    # registration)
    seen = rows["feature_index"] >= 0
    assert np.all(np.isnan(rows["raw_x"][~seen]))
    feats = blocks.features[rows["feature_index"][seen]]
    xy = mapping.image_to_surface(np.column_stack([feats["x"], feats["y"]])) * s.calibration.px_per_mm
    np.testing.assert_allclose(np.column_stack([rows["raw_x"][seen], rows["raw_y"][seen]]), xy, atol=1e-9)
    pair = blocks.motion[blocks.motion["pair"] == 5]
    at5 = rows[rows["frame"] == 5]
    np.testing.assert_array_equal(pair["x"], at5["x"][np.searchsorted(at5["track"], pair["id"])])


@pytest.mark.parametrize("take_every", [1, 4])
def test_stored_trajectories_with_bridged_points_are_those_of_finish_to_the_bit(take_every):
    """Points followed by registration alone (no feature: NaN raw position, feature_index -1) and skin points
    detected twice (no track) are stored as finish() builds them."""
    from skinstretch.processing.displacement_refinement import SubpixelRefiner
    from skinstretch.processing.feature_table import make_features
    from tests.test_track_bridging import _sequence

    n = 12
    frames, truth = _sequence(n)
    missed = np.random.default_rng(3).random((n, truth[0].shape[0])) < 0.2
    missed[0] = False
    cal = Calibration(px_per_mm=62.0)
    params = TrackingParams(min_length_frames=4, smoothing_radius_frames=1, max_bridge_frames=None)
    trackers = [FeatureTracker(calibration=cal, refiner=SubpixelRefiner(calibration=cal), params=params)
                for _ in range(2)]
    with TrajectoryStore(n_frames=n, params=params) as store:
        for k in range(n):
            keep = ~missed[k]
            xy = truth[k][keep]
            x, y = np.append(xy[:, 0], xy[0, 0] + 1.0), np.append(xy[:, 1], xy[0, 1])  # one point found twice
            feats = make_features(x, y, np.full(x.size, 2), frame=k)
            for tracker in trackers:
                tracker.add_frame(feats, image=frames[k])
            if k % take_every == 0:
                store.add(trackers[1].take_frames())
        store.add(trackers[1].take_frames(last=True))
        ref = trackers[0].finish()
        rows = np.concatenate([b.rows for b in store.blocks(block_frames=5)])
    assert np.any(ref.rows["feature_index"] < 0), "the sequence should bridge some points"
    for name in ref.rows.dtype.names:
        np.testing.assert_array_equal(rows[name], ref.rows[name], err_msg=name)
    np.testing.assert_array_equal(store.kinds, ref.kind)
