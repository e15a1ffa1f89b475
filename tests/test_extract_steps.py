"""Feature extraction steps (seed 4.1-4.8) on small hand-made images."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.extraction import ExtractionParams, FeatureExtractor, extract_features
from skinstretch.processing.feature_filters import feature_density_mask
from skinstretch.processing.feature_localization import refine_pores
from skinstretch.processing.feature_table import FEATURE_DTYPE, FeatureKind
from skinstretch.processing.illumination import compensate_illumination, illumination_map
from skinstretch.processing.pixel_scale import Calibration
from skinstretch.processing.pores import detect_blob_pores
from skinstretch.processing.preprocess import binarize, contact_map, ridge_statistics
from skinstretch.processing.skeleton_editing import (
    GapEvidence,
    heal_broken_valleys,
    line_pixels,
    remove_bridges,
    remove_short_spurs,
    remove_short_valleys,
)
from skinstretch.processing.skeleton_graph_lists import node_kind, node_orientation, trace_skeleton
from skinstretch.processing.thinning import thin
from tests.helpers import y_shaped_skeleton

PPM = 62.0
CAL = Calibration(px_per_mm=PPM)


def _kinds(graph):
    return sorted(node_kind(graph, n) for n in graph.alive_nodes())


def test_single_valley_gives_two_endings():
    b = np.zeros((40, 80), np.uint8)
    b[17:24, 10:70] = 255
    g = trace_skeleton(thin(b))
    assert _kinds(g) == [FeatureKind.VALLEY_ENDING] * 2
    xs = sorted(g.node_x[n] for n in g.alive_nodes())
    assert xs[0] < 15 and xs[1] > 64
    # Endings point into their valley (seed Figure 30(a)): the left one along +x (0 deg), the right one 180 deg.
    orient = {round(g.node_x[n]): node_orientation(g, n, n_px=10) for n in g.alive_nodes()}
    left, right = orient[min(orient)], orient[max(orient)]
    assert left == pytest.approx(0.0, abs=1e-6) and right == pytest.approx(180.0, abs=1e-6)


def test_y_gives_one_bifurcation():
    sk = y_shaped_skeleton()
    g = trace_skeleton(sk)
    kinds = _kinds(g)
    assert kinds.count(FeatureKind.VALLEY_BIFURCATION) == 1 and kinds.count(FeatureKind.VALLEY_ENDING) == 3
    bif = next(n for n in g.alive_nodes() if node_kind(g, n) == FeatureKind.VALLEY_BIFURCATION)
    assert abs(g.node_x[bif] - 29.3) < 1.5 and abs(g.node_y[bif] - 30) < 1.0
    # Bisector of the smallest angle (the two arms) points along +x.
    assert node_orientation(g, bif, n_px=10) == pytest.approx(0.0, abs=1.0)


def test_thick_y_through_thinning_gives_one_bifurcation():
    b = np.zeros((80, 100), np.uint8)
    import cv2

    cv2.line(b, (5, 40), (50, 40), 255, 7)
    cv2.line(b, (50, 40), (95, 10), 255, 7)
    cv2.line(b, (50, 40), (95, 70), 255, 7)
    g = trace_skeleton(thin(b))
    assert _kinds(g).count(FeatureKind.VALLEY_BIFURCATION) == 1


@pytest.mark.parametrize("diameter_mm, is_pore", [(0.15, True), (0.2, True), (0.35, False)])
def test_bright_disc_is_a_pore_below_quarter_mm(diameter_mm, is_pore):
    import cv2

    img = np.full((80, 80), 40, np.uint8)
    r = CAL.px(diameter_mm) / 2
    cv2.circle(img, (40, 41), int(round(r - 0.5)), 220, -1)
    b = (img > 128).astype(np.uint8) * 255
    pores = detect_blob_pores(b, grey=img.astype(np.float32), max_diameter_px=CAL.px(0.25))
    assert (pores.x.size == 1) == is_pore
    if is_pore:
        assert pores.x[0] == pytest.approx(40, abs=1e-9) and pores.y[0] == pytest.approx(41, abs=1e-9)
        assert not pores.binary_without_pores.any()
    else:
        assert pores.binary_without_pores.any()


def test_pore_refinement_is_subpixel():
    yy, xx = np.mgrid[0:40, 0:40]
    img = (40 + 180 * np.exp(-((xx - 20.37) ** 2 + (yy - 18.81) ** 2) / (2 * 2.0**2))).astype(np.float32)
    rx, ry, ok = refine_pores(img, threshold=np.full_like(img, 100.0), x=np.array([20.0]), y=np.array([19.0]), radius_px=5)
    assert ok[0] and abs(rx[0] - 20.37) < 0.02 and abs(ry[0] - 18.81) < 0.02


def _two_endings_graph(gap_px, third_valley=False):
    sk = np.zeros((60, 120), np.uint8)
    sk[30, 5:55] = 1
    sk[30, 55 + gap_px : 115] = 1
    if third_valley:
        sk[10:50, 55 + gap_px // 2] = 1
    return trace_skeleton(sk)


def test_healing_joins_two_aligned_endings():
    g = _two_endings_graph(20)
    g.add_pore(64.0, 31.0)  # in the 8-neighbourhood of the bridging line: part of the healed valley
    g.add_pore(64.0, 40.0)  # far from it: stays
    healed = heal_broken_valleys(g, max_distance_px=CAL.px(0.6), max_angle_deg=30, orientation_px=10)
    assert _kinds(healed) == [FeatureKind.VALLEY_ENDING] * 2
    xs = sorted(healed.node_x[n] for n in healed.alive_nodes())
    assert xs == [5.0, 114.0]
    assert healed.skeleton[30, 55:75].all()
    assert [a for a in healed.pore_alive] == [False, True]
    # The input graph is not modified.
    assert len(_kinds(g)) == 4


def test_healing_never_crosses_a_third_valley():
    g = _two_endings_graph(20, third_valley=True)
    before = _kinds(g)
    healed = heal_broken_valleys(g, max_distance_px=CAL.px(0.6), max_angle_deg=30, orientation_px=10)
    assert _kinds(healed) == before
    assert not healed.skeleton[30, 56:64].any()


def test_healing_rejects_gaps_above_distance_or_angle():
    g = _two_endings_graph(45)  # 0.74 mm > 0.6 mm
    assert len(heal_broken_valleys(g, max_distance_px=CAL.px(0.6), max_angle_deg=30, orientation_px=10).alive_nodes()) == 4
    sk = np.zeros((80, 120), np.uint8)
    sk[30, 5:55] = 1
    sk[50, 65:115] = 1  # offset by 20 px over a 10 px gap: ~63 deg
    g = trace_skeleton(sk)
    assert len(heal_broken_valleys(g, max_distance_px=CAL.px(0.6), max_angle_deg=30, orientation_px=10).alive_nodes()) == 4


def _stripes_with_gap(gap_level):
    """Valleys (bright) along x every 27 px, one on row 30 (the skeleton of _two_endings_graph), its stretch
    x 55..74 (the gap between the two endings) of grey level ``gap_level``."""
    y = np.arange(60, dtype=np.float32)[:, None]
    image = np.repeat(128 + 60 * np.cos(2 * np.pi * (y - 30) / 27.0), 120, axis=1).astype(np.float32)
    image[24:37, 55:75] = gap_level
    return image


def test_healing_leaves_a_gap_across_a_ridge_open():
    heal = dict(max_distance_px=CAL.px(0.6), max_angle_deg=30, orientation_px=10)
    g = _two_endings_graph(20)
    # Two valleys that end facing each other across skin as dark as the ridges (68): two true endings.
    ridge = GapEvidence(image=_stripes_with_gap(68.0), window_px=27, max_ridge_px=CAL.px(0.1))
    assert ridge.crosses_ridge(54, 30, 75, 30)
    assert len(heal_broken_valleys(g, **heal, gaps=ridge).alive_nodes()) == 4
    # A valley broken by skin a little darker than the mean (118 against ridges at 68, valleys at 188): healed.
    weak = GapEvidence(image=_stripes_with_gap(118.0), window_px=27, max_ridge_px=CAL.px(0.1))
    assert not weak.crosses_ridge(54, 30, 75, 30)
    assert _kinds(heal_broken_valleys(g, **heal, gaps=weak)) == [FeatureKind.VALLEY_ENDING] * 2
    # A dark spot shorter than max_ridge_px in the gap does not stop it either.
    spot = _stripes_with_gap(118.0)
    spot[27:34, 63:67] = 68.0
    assert not GapEvidence(image=spot, window_px=27, max_ridge_px=CAL.px(0.1)).crosses_ridge(54, 30, 75, 30)
    with pytest.raises(InvalidInputError, match="gaps"):
        heal_broken_valleys(g, **heal, gaps="dark")
    with pytest.raises(InvalidInputError, match="window_px"):
        GapEvidence(image=spot, window_px=0, max_ridge_px=6.0)
    with pytest.raises(InvalidInputError, match="max_ridge_px"):
        GapEvidence(image=spot, window_px=27, max_ridge_px=-1.0)


def test_short_valley_becomes_pore():
    sk = np.zeros((30, 60), np.uint8)
    sk[15, 20:28] = 1  # 7 px < 0.2 mm (12.4 px)
    g = remove_short_valleys(trace_skeleton(sk), max_length_px=CAL.px(0.2))
    assert not g.alive_nodes() and g.pore_alive == [True]
    assert g.pore_x[0] == pytest.approx(23.5) and g.pore_y[0] == pytest.approx(15.0)


def _valleys_and_cross_line(rows, line_from, line_to, x=60):
    """Horizontal valleys at ``rows`` and one vertical line at column ``x`` from row ``line_from`` to ``line_to``."""
    sk = np.zeros((100, 120), np.uint8)
    for r in rows:
        sk[r, 5:115] = 1
    sk[line_from : line_to + 1, x] = 1
    return trace_skeleton(sk)


BRIDGE = dict(min_length_px=CAL.px(0.1), max_length_px=CAL.px(1.0), max_deviation_deg=60.0, orientation_px=10)
SPUR = dict(min_length_px=CAL.px(0.1), max_length_px=CAL.px(0.3), max_deviation_deg=60.0, orientation_px=10)


def test_bridge_between_two_valleys_becomes_a_pore():
    g = remove_bridges(_valleys_and_cross_line((30, 55), 30, 55), **BRIDGE)
    assert _kinds(g) == [FeatureKind.VALLEY_ENDING] * 4
    assert g.pore_alive == [True] and g.pore_x[0] == pytest.approx(60.0) and 40 < g.pore_y[0] < 45


def test_a_row_of_bridges_across_several_valleys_becomes_pores():
    # Pores in a row across the ridges, each joining its two valleys: the line crosses the middle valleys
    # (nodes of four valleys). Every bridge of the chain goes, each leaving a pore.
    g0 = _valleys_and_cross_line((20, 40, 60, 80), 20, 80)
    assert _kinds(g0).count(FeatureKind.VALLEY_BIFURCATION) == 4
    g = remove_bridges(g0, **BRIDGE)
    assert _kinds(g) == [FeatureKind.VALLEY_ENDING] * 8
    assert sum(g.pore_alive) == 3
    assert sorted(round(y) for y, a in zip(g.pore_y, g.pore_alive) if a) == [30, 50, 70]


def test_a_spur_continuing_a_bridge_through_a_crossing_goes_then_the_bridges():
    g = remove_short_spurs(_valleys_and_cross_line((20, 40, 60), 20, 70), **SPUR)  # last 10 px: a spur
    g = remove_bridges(g, **BRIDGE)
    assert _kinds(g) == [FeatureKind.VALLEY_ENDING] * 6
    assert sum(g.pore_alive) == 3  # the spur tip (10 px > 0.1 mm) and the two bridges


def test_a_true_crossing_of_oblique_valleys_is_not_a_bridge():
    sk = np.zeros((100, 120), np.uint8)
    sk[50, 5:115] = 1
    for i in range(-40, 41):
        sk[50 + i, 60 + i] = 1  # 45 degrees: neither perpendicular nor a bridge's continuation
    g = remove_bridges(trace_skeleton(sk), **BRIDGE)
    assert sum(g.pore_alive) == 0


def test_density_filter_deletes_crowded_features_per_kind():
    x = np.array([10, 12, 14, 16, 100, 10, 12.0])
    y = np.array([10, 10, 10, 10, 100, 11, 11.0])
    kind = np.array([2, 2, 2, 2, 2, 0, 0])
    keep = feature_density_mask(x, y, kind, radius_px=15.5, max_count=3)
    assert keep.tolist() == [False, False, False, False, True, True, True]


def test_background_and_binarization():
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:200, 0:300]
    img = 128 + 90 * np.cos(2 * np.pi * xx / 27.0)
    img[:, 200:] = 235  # uncovered prism: bright, flat
    img = np.clip(img + rng.normal(0, 2, img.shape), 0, 255).astype(np.uint8)
    stats = ridge_statistics(img.astype(np.float32), sigma_px=13.5, cell_px=3)
    bg, _ = contact_map(stats, shape=img.shape, min_contact=0.5)
    assert bg[:, 230:].all() and not bg[:, :170].any()
    binary = binarize(img.astype(np.float32), local_average=stats.mean, background=bg)
    assert binary[:, 230:].max() == 0
    assert binary[100, 0] == 255 and binary[100, 13] == 0  # valley bright, ridge dark


def test_the_skeleton_rules_see_a_band_along_the_outline_as_open_to_the_background():
    from skinstretch.processing.extraction import _open_to_background

    background = np.zeros((40, 80), bool)
    background[:, 60:] = True  # out of contact beyond x = 60
    valleys = np.zeros((40, 80), np.uint8)
    valleys[:, 48:60] = 255  # a band 12 px wide along the outline: the skin fading out of contact
    valleys[18:23, 10:40] = 255  # a valley well inside, a ridge (x 40..47) between it and the band
    open_ = _open_to_background(valleys, background)
    assert open_[:, 60:].all()  # the background itself
    assert open_[20, 54] and open_[5, 56]  # the band's middle (its skeleton) and beyond: their discs reach it
    assert not open_[20, 50]  # the band's inner side is nearer the ridge
    assert not open_[20, 10:40].any()  # the valley inside is bounded by ridges
    assert not _open_to_background(valleys, np.zeros_like(background)).any()


def test_illumination_compensation_flattens_the_valleys():
    yy, xx = np.mgrid[0:120, 0:160]
    gain = 0.6 + 0.4 * xx / 159.0
    frames = [np.clip(gain * (128 + 100 * np.cos(2 * np.pi * (xx + 3 * k) / 27.0)), 0, 255).astype(np.uint8) for k in range(9)]
    imap = illumination_map(frames, calibration=Calibration(px_per_mm=62.0), lowpass_sigma_mm=0.3)
    out = compensate_illumination(frames[0], illumination=imap)
    left, right = out[:, 10:40].max(), out[:, 120:150].max()
    assert abs(int(left) - int(right)) <= 8 and right >= 245


def test_line_pixels_are_8_connected():
    p = line_pixels(0, 0, 7, 3)
    assert p[0].tolist() == [0, 0] and p[-1].tolist() == [7, 3]
    assert np.all(np.max(np.abs(np.diff(p, axis=0)), axis=1) == 1)


# ----------------------------------------------------------------------------------------- whole chain


def _print(shape=(220, 260), shift=(0, 0), seed=0):
    """A small synthetic print: straight ridges with one ending (a spiral point) and a few pores."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x = xx - shift[0]
    y = yy - shift[1]
    phase = 2 * np.pi * y / 27.0 + np.arctan2(y - 110.3, x - 120.6)
    img = 0.5 + 0.5 * np.cos(phase)
    for px, py in [(60.2, 67.5 - 13.5 + 27), (180.4, 94.5 + 27 * 2), (70.7, 175.5)]:
        img = np.maximum(img, 0.95 * np.exp(-((x - px) ** 2 + (y - py) ** 2) / (2 * 2.2**2)))
    rng = np.random.default_rng(seed)
    return np.clip(40 + 190 * img + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)


def test_extract_features_on_a_small_print():
    res = extract_features(_print(), calibration=CAL, frame_index=7)
    assert res.ok and not res.flags
    f = res.features
    assert f.dtype == FEATURE_DTYPE and np.all(f["frame"] == 7)
    assert np.all(f["id"] // 1_000_000 == 7) and len(np.unique(f["id"])) == f.size
    assert list(res.step_counts) == ["initial", "short_valleys", "healing", "short_spurs", "bridges", "density", "border"]
    minutiae = f[f["kind"] != FeatureKind.PORE]
    d = np.hypot(minutiae["x"] - 120.6, minutiae["y"] - 110.3)
    assert d.size >= 1 and d.min() < 6  # the spiral point is found
    assert np.count_nonzero(f["kind"] == FeatureKind.PORE) >= 2
    assert np.all(np.isfinite(f["x"])) and np.all(f["quality"] >= 0)


def test_editing_steps_are_switchable():
    params = ExtractionParams(
        remove_short_valleys=False,
        heal_broken_valleys=False,
        remove_short_spurs=False,
        remove_bridges=False,
        filter_feature_density=False,
        remove_border_features=False,
    )
    res = extract_features(_print(), calibration=CAL, params=params)
    assert list(res.step_counts) == ["initial"]
    assert res.features.size >= extract_features(_print(), calibration=CAL).features.size


@settings(max_examples=6, deadline=None)
@given(dx=st.integers(-12, 12), dy=st.integers(-12, 12))
def test_features_of_a_shifted_image_are_the_shifted_features(dx, dy):
    """Whole-pixel shift of the scene => every feature far from the image border shifts by that.

    To 0.03 px, not exactly: the ridge-scale statistics (threshold, light, flow) are taken on a grid of cells an
    eighth of a ridge period wide (preprocess.ridge_statistics), and a shift that is not a whole number of cells
    changes the cell means a little (~0.015 px seen in feature positions, five times below their frame-to-frame
    jitter on the simulated scenes)."""
    ex = FeatureExtractor(calibration=CAL, params=ExtractionParams(remove_border_features=False))
    # Noise is drawn per pixel, not per skin point, so the invariant is checked on noise-free renderings.
    a0 = ex.extract(_noise_free(0, 0)).features
    b0 = ex.extract(_noise_free(dx, dy)).features
    core = lambda t, sx, sy: t[(t["x"] - sx > 90) & (t["x"] - sx < 210) & (t["y"] - sy > 90) & (t["y"] - sy < 170)]
    ca, cb = core(a0, 0, 0), core(b0, dx, dy)
    assert ca.size == cb.size and ca.size > 0
    ia = np.lexsort((ca["y"], ca["x"], ca["kind"]))
    ib = np.lexsort((cb["y"] - dy, cb["x"] - dx, cb["kind"]))
    assert np.array_equal(ca["kind"][ia], cb["kind"][ib])
    np.testing.assert_allclose(cb["x"][ib] - dx, ca["x"][ia], atol=0.03)
    np.testing.assert_allclose(cb["y"][ib] - dy, ca["y"][ia], atol=0.03)


def _noise_free(dx, dy):
    h, w = 300, 340
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    x = xx - dx - 20
    y = yy - dy - 20
    phase = 2 * np.pi * y / 27.0 + np.arctan2(y - 110.3, x - 120.6)
    img = 0.5 + 0.5 * np.cos(phase)
    for px, py in [(60.2, 81.0), (180.4, 148.5), (70.7, 175.5)]:
        img = np.maximum(img, 0.95 * np.exp(-((x - px) ** 2 + (y - py) ** 2) / (2 * 2.2**2)))
    return np.clip(40 + 190 * img, 0, 255).round().astype(np.uint8)


# ----------------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "frame",
    [np.zeros((200, 200), np.float32), np.zeros((200, 200, 3), np.uint8), np.zeros((50, 300), np.uint8), "frame"],
)
def test_bad_frames_raise_invalid_input(frame):
    with pytest.raises(InvalidInputError, match="frame"):
        extract_features(frame, calibration=CAL)


@pytest.mark.parametrize(
    "frame, flag",
    [
        (np.zeros((200, 200), np.uint8), "all_black"),
        (np.full((200, 200), 255, np.uint8), "saturated"),
        (np.full((200, 200), 230, np.uint8), "no_finger"),
    ],
)
def test_degenerate_frames_give_empty_flagged_results(frame, flag):
    res = extract_features(frame, calibration=CAL)
    assert not res.ok and res.flags == {flag} and res.features.size == 0


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"pore_max_diameter_mm": -1.0}, "pore_max_diameter_mm"),
        ({"heal_max_angle_deg": 120.0}, "heal_max_angle_deg"),
        ({"spur_min_mm": 2.0}, "spur_min_mm"),
        ({"heal_broken_valleys": 1}, "heal_broken_valleys"),
        ({"ridge_period_mm": float("nan")}, "ridge_period_mm"),
        ({"min_contact": 1.5}, "min_contact"),
    ],
)
def test_bad_parameters_are_named(kwargs, name):
    with pytest.raises(InvalidInputError, match=name):
        ExtractionParams(**kwargs)


def test_extract_many_matches_single_frames():
    ex = FeatureExtractor(calibration=CAL)
    frames = [_print(seed=s) for s in range(3)]
    many = ex.extract_many(frames, frame_indices=[4, 5, 6], workers=2)
    for k, (f, r) in enumerate(zip(frames, many)):
        single = ex.extract(f, frame_index=4 + k).features
        assert single.tobytes() == r.features.tobytes()  # bit-identical (NaN orientations included)


def test_extractor_applies_a_fitted_illumination_map():
    frames = [_print(seed=s) for s in range(3)]
    dimmed = [(f * np.linspace(0.6, 1.0, f.shape[1])[None, :]).astype(np.uint8) for f in frames]
    ex = FeatureExtractor(calibration=CAL)
    imap = ex.fit_illumination(dimmed)
    assert imap.shape == frames[0].shape and ex.illumination is imap
    res = ex.extract(dimmed[0])
    assert res.ok and np.any(res.features["kind"] == FeatureKind.PORE)
    with pytest.raises(InvalidInputError, match="illumination"):
        ex.extract(np.zeros((200, 200), np.uint8) + 100)
    with pytest.raises(InvalidInputError, match="illumination"):
        ex.illumination = np.zeros((10, 10))
