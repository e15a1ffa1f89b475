"""How dense the measurement is (experiments/analysis/density.py): the fraction kept, the sparse-mesh warning, and
the report in the summary, the Python API and the command line, checked against the truth of a real-print scene."""

import json
import logging

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from skinstretch.cli import main
from skinstretch.experiments.analysis import analysis_params, analyze_frames
from skinstretch.experiments.analysis.density import MeshDensity, fraction_kept, mesh_density
from skinstretch.experiments.analysis.derive import motion_rows, span_strain
from skinstretch.experiments.evaluation.trajectories import truth_fraction_kept
from skinstretch.experiments.results_file import ResultsWriter
from skinstretch.processing.feature_table import make_features
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.tracking import MotionSample

scene = pytest.importorskip("skinstretch.simulators.scene")


class _Sliding:
    """Skin sliding +1 px along x per frame, in view for x < ``edge``."""

    def __init__(self, edge: float) -> None:
        self.edge = edge

    def move(self, points, frame_from, frame_to):
        return points + [frame_to - frame_from, 0.0], np.ones(points.shape[0], bool)

    def in_view(self, points, frame):
        return points[:, 0] < self.edge


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 12), st.integers(2, 20), st.lists(st.floats(0.0, 30.0), min_size=1, max_size=6),
       st.integers(0, 2**16))
def test_fraction_kept_counts_features_whose_point_stays_for_the_window(window, n_frames, x0, seed):
    # A skin point starting at x0 (frame 0) is at x0 + k in frame k and in view while x0 + k < 20: in view for
    # frames 0 .. ceil(20 - x0) - 1. Every point is found in every frame it is in view; some are kept.
    x0 = np.asarray(x0)
    kept_point = np.random.default_rng(seed).random(x0.size) < 0.5
    last = np.ceil(20.0 - x0).astype(int) - 1  # last frame in view
    visible = np.maximum(np.minimum(last, n_frames - 1) + 1, 0)  # frames in view within the clip (from frame 0)

    def features_of(k):
        here = k <= last
        return np.column_stack([x0[here] + k, np.zeros(int(here.sum()))]), kept_point[here]

    fk = fraction_kept(n_frames, window, features_of, _Sliding(20.0))
    stays = visible >= window
    assert fk.n_features == int(np.sum(visible))
    assert fk.n_in_view == int(np.sum(visible[stays]))
    assert fk.n_kept == int(np.sum(visible[stays & kept_point]))
    assert fk.fraction == (fk.n_kept / fk.n_in_view if fk.n_in_view else None)


def _sparse_results(feature_frames=range(6), *, strain=True):
    """A results file in memory holding a measurement of 4 far-apart points over 6 frames, their features found in
    ``feature_frames``."""
    w = ResultsWriter(None)
    p = np.array([[100.0, 100.0], [300.0, 100.0], [100.0, 300.0], [300.0, 300.0]])
    samples = [MotionSample(k, k + 1, p + k, np.ones((4, 2)), np.arange(4)) for k in range(5)]
    pairs, rows = motion_rows(samples)
    w.append("motion_pairs", pairs)
    w.append("motion", rows)
    if strain:
        s = span_strain(samples, span=1, max_edge_px=1e6)
        for part, table in (("pairs", s.pairs), ("edges", s.edges), ("triangles", s.triangles)):
            w.append(f"strain/span_1/{part}", table)
    feats = np.concatenate([make_features(p[:, 0] + k, p[:, 1] + k, [2] * 4, frame=k) for k in feature_frames])
    feats["id"] = np.arange(feats.shape[0])
    w.append("features", feats)
    return w


def test_a_sparse_mesh_is_flagged_and_logged(caplog):
    w = _sparse_results()
    with caplog.at_level(logging.WARNING, logger="skinstretch.experiments.analysis.density"):
        d = mesh_density(w.file, method="features", n_frames=6, px_per_mm=62.0, spans=[1], max_edge_px=1e6,
                         window=3)
    assert d.too_sparse and d.points_per_pair == 4
    assert d.mesh_edge_mm == pytest.approx(np.mean([200, 200, 200, 200, 200 * np.sqrt(2)]) / 62.0)
    assert d.features_per_frame == 4 and d.trajectories_kept == 0 and d.fraction_kept == 0.0
    assert "too sparse to map strain" in d.warning and "4 points measured per frame pair" in d.warning
    assert "mean mesh edge" in d.warning and "of the features that stay in view" in d.warning
    assert any("too sparse" in r.getMessage() for r in caplog.records)
    assert MeshDensity.from_dict(json.loads(json.dumps(d.to_dict()))) == d


def test_features_not_kept_stay_in_view_through_frames_without_features():
    # 4 points measured in every pair; their features found in frames 0 and 5 only (extraction refused 1-4), two of
    # them kept. The in-view region is what was measured in a frame, not its features alone: the two features not
    # kept stay in view for the 6-frame window and count against (before: no region in frames 1-4, kept 1.0).
    w = _sparse_results((0, 5), strain=False)
    w.file.create_dataset("trajectories", data=np.array([(0,), (1,), (4,), (5,)], dtype=[("feature_index", np.int64)]))
    d = mesh_density(w.file, method="features", n_frames=6, px_per_mm=62.0, spans=[1], max_edge_px=1e6, window=6)
    assert d.features_in_view == 8 and d.fraction_kept == 0.5


@pytest.fixture(scope="module")
def real_print_session(tmp_path_factory):
    path = tmp_path_factory.mktemp("density") / "reversal_p2_1.h5"
    s = scene.load_scene("reversal").with_texture("afis_p2_1")
    scene.simulate_to_file(s, path, n_frames=24, seed=3)
    return path


def test_density_is_reported_and_agrees_with_the_truth(real_print_session, tmp_path, caplog):
    out = tmp_path / "features"
    with caplog.at_level(logging.INFO, logger="skinstretch"):
        assert main(["analyze", str(real_print_session), "-o", str(out), "--quiet"]) == 0
    from skinstretch.experiments.results_file import read_results

    r = read_results(out)
    d = r.density
    assert isinstance(d, MeshDensity) and not d.too_sparse and d.warning is None
    assert d.features_per_frame > 50 and d.trajectories_kept > 50 and d.window_frames == 12
    assert 0.4 < d.mesh_edge_mm < 1.0
    json_summary = json.loads((out / "summary.json").read_text())["density"]
    assert json_summary["fraction_kept"] == d.fraction_kept
    # The analysis' own estimate (its measured motion) against the same definition through the exact field.
    from skinstretch.drivers.session_file import open_session

    with open_session(real_print_session) as s:
        truth = s.truth
    fk = truth_fraction_kept(r, truth)
    assert fk.fraction >= 0.8 and d.fraction_kept >= 0.8 and abs(fk.fraction - d.fraction_kept) < 0.05
    assert fk.window_frames == 12 and fk.n_in_view > 0.5 * fk.n_features


def test_flow_density_has_no_features_but_a_mesh(real_print_session):
    from skinstretch.drivers.session_file import open_session

    with open_session(real_print_session) as s:
        frames, ppm = s.read_frames(0, 6), s.calibration.px_per_mm
    r = analyze_frames(frames, calibration=Calibration(px_per_mm=ppm), method="flow", params=analysis_params(),
                       surface="flat")
    d = r.density
    assert d.features_per_frame is None and d.fraction_kept is None and d.window_frames is None
    assert d.points_per_pair > 100 and 0.6 < d.mesh_edge_mm < 1.2 and not d.too_sparse


def test_the_in_view_region_kept_as_bits_answers_as_its_mask():
    """A frame's in-view region is kept as packed bits (both passes of the fraction kept read it): every point in
    and around it gets the answer of the mask it was drawn as."""
    from skinstretch.experiments.analysis.density import _REGION_PX, _in_region, _region

    rng = np.random.default_rng(5)
    xy = rng.uniform([40, 30], [600, 450], (300, 2))
    mask, origin = _region(xy, 60.0)
    region = (np.packbits(mask, axis=1), mask.shape, origin)
    q = rng.uniform([0, 0], [700, 520], (5000, 2))
    c = np.round((q[:, 0] - origin[0]) / _REGION_PX).astype(int)
    r = np.round((q[:, 1] - origin[1]) / _REGION_PX).astype(int)
    inside = (c >= 0) & (r >= 0) & (c < mask.shape[1]) & (r < mask.shape[0])
    want = np.zeros(len(q), bool)
    want[inside] = mask[r[inside], c[inside]] > 0
    assert 0.2 < want.mean() < 0.9
    np.testing.assert_array_equal(_in_region(region, q), want)
    assert not _in_region(None, q).any()
