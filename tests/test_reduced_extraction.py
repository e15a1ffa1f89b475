"""Features found on a halved frame (ReducedFeatureExtractor, the live view's): in the frame's own pixels."""

import numpy as np
from scipy.spatial import cKDTree
from skinstretch.processing.extraction import FeatureExtractor, ReducedFeatureExtractor
from skinstretch.processing.feature_table import FeatureKind
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.simulators.scene import load_scene, render_session


def test_at_the_rigs_scale_the_frame_is_halved_and_the_minutiae_land_where_the_full_frame_finds_them():
    r = render_session(load_scene("ridgeL"), n_frames=2, seed=0)
    reduced = ReducedFeatureExtractor(calibration=r.calibration)
    assert reduced.factor == 2 and reduced.extractor.calibration.px_per_mm == r.calibration.px_per_mm / 2
    full = FeatureExtractor(calibration=r.calibration).extract(r.frames[1], frame_index=1).features
    half = reduced.extract(r.frames[1], frame_index=1).features
    assert len(half) >= 0.85 * len(full)
    assert np.all(half["frame"] == 1)
    for kind in (FeatureKind.VALLEY_ENDING, FeatureKind.VALLEY_BIFURCATION, FeatureKind.PORE):
        a, b = full[full["kind"] == kind], half[half["kind"] == kind]
        dist, _ = cKDTree(np.column_stack([a["x"], a["y"]])).query(np.column_stack([b["x"], b["y"]]))
        # the same minutiae and pores, not shifted by the reduction (a half-pixel offset would show in the median)
        assert np.mean(dist < 2.0) >= 0.85, kind
        assert np.median(dist) < 0.6, kind


def test_where_a_halved_frame_would_blur_the_ridges_the_frame_is_used_as_it_is():
    r = render_session(load_scene("ridgeL"), n_frames=2, seed=0)
    cal = Calibration(px_per_mm=30.0)  # a ridge period of 12.9 px: halved it would fall below 12
    reduced = ReducedFeatureExtractor(calibration=cal)
    assert reduced.factor == 1
    a = FeatureExtractor(calibration=cal).extract(r.frames[1]).features
    b = reduced.extract(r.frames[1]).features
    assert a.tobytes() == b.tobytes()  # (byte for byte: an unknown orientation is NaN)
