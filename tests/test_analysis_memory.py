"""A session of any length in bounded memory: trajectories stored as the tracker hands frames out, percentiles of
more values than are held (skinstretch.experiments.analysis.trajectories, .percentiles), to the bit."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from skinstretch.experiments.analysis.percentiles import StreamedPercentiles
from skinstretch.experiments.analysis.trajectories import TrajectoryStore
from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.tracking import FeatureTracker, TrackingParams
from tests.helpers import sliding_feature_grid


@pytest.mark.parametrize("smoothing", [0, 1, 2])
@pytest.mark.parametrize("take_every", [1, 3, 7])
def test_stored_trajectories_are_those_of_finish_to_the_bit(smoothing, take_every):
    params = TrackingParams(min_length_frames=3, max_gap_frames=3, smoothing_radius_frames=smoothing)
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
    params = TrackingParams(min_length_frames=3, max_gap_frames=1)
    tracker = FeatureTracker(calibration=Calibration(px_per_mm=62.0), params=params)
    for k in range(6):
        tracker.add_frame(sliding_feature_grid(k))
    frames = tracker.take_frames()
    assert [f.frame for f in frames] == [0, 1, 2]  # the last max_gap_frames + 2 stay for matching
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
