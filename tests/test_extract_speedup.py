"""Faster illumination compensation and grey-level minutia tips (issue 3: speed and repeatability)."""

import numpy as np
import pytest
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_localization import locate_minutiae_tips
from skinstretch.processing.illumination import apply_illumination_gain, compensate_illumination, illumination_gain


def test_gain_matches_eq_3_7_up_to_rounding():
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, size=(60, 80), dtype=np.uint8)
    illum = rng.uniform(40.0, 255.0, size=(60, 80)).astype(np.float32)
    ref = compensate_illumination(frame, illumination=illum)
    out = apply_illumination_gain(frame, gain=illumination_gain(illum))
    assert out.dtype == np.uint8
    assert np.abs(out.astype(int) - ref).max() <= 1
    assert np.count_nonzero(out != ref) <= 3  # only exact half-way values may round the other way
    assert out.max() == 255  # clipped, not wrapped


def test_gain_rejects_bad_maps():
    with pytest.raises(InvalidInputError, match="positive"):
        illumination_gain(np.zeros((4, 4), np.float32))
    with pytest.raises(InvalidInputError, match="gain"):
        apply_illumination_gain(np.zeros((4, 4), np.uint8), gain=np.ones((4, 5), np.float32))


def _valley_ending(tip_x, centre_y, shape=(50, 90)):
    """Excess image of a bright Gaussian valley along x that fades out smoothly at ``tip_x`` (minus local mean)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    across = np.exp(-((yy - centre_y) ** 2) / (2 * 3.0**2))
    along = 1.0 / (1.0 + np.exp((xx - tip_x) / 1.5))
    return (40.0 * across * along - 10.0).astype(np.float32)


@pytest.mark.parametrize("shift", [0.0, 0.25, 0.5, 0.8])
def test_tip_follows_subpixel_motion_of_the_grey_image(shift):
    # The skeleton position stays on the same pixel; the located tip must move with the image, not the pixel.
    base = _valley_ending(50.0, 24.0)
    moved = _valley_ending(50.0 + shift, 24.0 + shift / 2)
    kw = dict(x=np.array([47.0]), y=np.array([24.0]), direction_deg=np.array([180.0]), is_ending=np.array([True]),
              reach_px=9.0)
    x0, y0, ok0 = locate_minutiae_tips(base, **kw)
    x1, y1, ok1 = locate_minutiae_tips(moved, **kw)
    assert ok0[0] and ok1[0]
    assert x1[0] - x0[0] == pytest.approx(shift, abs=0.03)
    assert y1[0] - y0[0] == pytest.approx(shift / 2, abs=0.03)
    assert y0[0] == pytest.approx(24.0, abs=0.02)


def test_tip_is_independent_of_the_skeleton_start_point():
    img = _valley_ending(50.3, 24.4)
    xs = np.array([46.0, 47.0, 48.0, 47.0])
    ys = np.array([24.0, 25.0, 23.0, 24.0])
    dirs = np.array([180.0, 175.0, 185.0, 190.0])
    rx, ry, ok = locate_minutiae_tips(img, x=xs, y=ys, direction_deg=dirs, is_ending=np.ones(4, bool), reach_px=9.0)
    assert ok.all()
    assert np.ptp(rx) < 0.05 and np.ptp(ry) < 0.05


def test_second_pass_anchors_the_tip_to_itself_on_a_curved_narrowing_valley():
    # One pass takes its profiles relative to the skeleton start, so on a curved valley that narrows toward its
    # tip the result depends on the start; the second pass starts from the tip and forgets it.
    yy, xx = np.mgrid[0:50, 0:90].astype(np.float64)
    centre = 24.0 + 0.004 * (xx - 50.0) ** 2
    width = 2.0 + 0.03 * np.clip(60.0 - xx, 0.0, None)
    img = (40.0 * np.exp(-((yy - centre) ** 2) / (2 * width**2)) / (1.0 + np.exp((xx - 50.3) / 1.5)) - 10.0)
    img = img.astype(np.float32)
    kw = dict(x=np.array([44.0, 46.0, 47.0, 48.0, 49.0]), y=np.array([24.0, 25.0, 23.0, 24.0, 24.0]),
              direction_deg=np.array([180.0, 175.0, 185.0, 190.0, 178.0]), is_ending=np.ones(5, bool), reach_px=9.0)
    x1, y1, ok1 = locate_minutiae_tips(img, iterations=1, **kw)
    x2, y2, ok2 = locate_minutiae_tips(img, **kw)  # default: two passes
    assert ok1.all() and ok2.all()
    assert np.hypot(np.ptp(x1), np.ptp(y1)) > 0.2
    assert np.hypot(np.ptp(x2), np.ptp(y2)) < 0.05
    with pytest.raises(InvalidInputError, match="iterations"):
        locate_minutiae_tips(img, iterations=0, **kw)


def test_tip_is_found_when_the_skeleton_ends_past_it():
    # A faint valley's smoothed excess can reach zero before its skeleton ends: the first start already lies past
    # the crossing. It is searched again from further back, and lands where a normal start does.
    img = _valley_ending(50.3, 24.4)
    kw = dict(y=np.array([24.0]), direction_deg=np.array([180.0]), is_ending=np.array([True]), reach_px=9.0)
    x0, y0, ok0 = locate_minutiae_tips(img, x=np.array([47.0]), **kw)
    x1, y1, ok1 = locate_minutiae_tips(img, x=np.array([56.0]), **kw)  # 5.7 px past the tip, start 3 px back
    assert ok0[0] and ok1[0]
    assert x1[0] == pytest.approx(x0[0], abs=0.02) and y1[0] == pytest.approx(y0[0], abs=0.02)


def test_tip_leaves_unknown_orientation_and_missing_valleys_alone():
    img = _valley_ending(50.0, 24.0)
    flat = np.full_like(img, -5.0)  # no valley at all: nothing above the local mean
    rx, ry, ok = locate_minutiae_tips(img, x=np.array([47.0]), y=np.array([24.0]), direction_deg=np.array([np.nan]),
                                      is_ending=np.array([True]), reach_px=9.0)
    assert not ok[0] and (rx[0], ry[0]) == (47.0, 24.0)
    rx, ry, ok = locate_minutiae_tips(flat, x=np.array([47.0]), y=np.array([24.0]), direction_deg=np.array([180.0]),
                                      is_ending=np.array([True]), reach_px=9.0)
    assert not ok[0] and (rx[0], ry[0]) == (47.0, 24.0)


def test_tip_rejects_bad_inputs():
    img = _valley_ending(50.0, 24.0)
    with pytest.raises(InvalidInputError, match="n_centres"):
        locate_minutiae_tips(img, x=np.array([47.0]), y=np.array([24.0]), direction_deg=np.array([180.0]),
                             is_ending=np.array([True]), reach_px=9.0, n_centres=1)
    with pytest.raises(InvalidInputError, match="direction_deg"):
        locate_minutiae_tips(img, x=np.array([47.0]), y=np.array([24.0]), direction_deg=np.array([180.0, 0.0]),
                             is_ending=np.array([True]), reach_px=9.0)


def _fork(cx, cy, shape=(60, 60)):
    """A bright Y of three Gaussian valleys meeting at (cx, cy)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    img = np.zeros(shape)
    for ang in (0.0, 120.0, 240.0):
        ux, uy = np.cos(np.radians(ang)), np.sin(np.radians(ang))
        t = np.maximum((xx - cx) * ux + (yy - cy) * uy, 0.0)
        d2 = (xx - cx - t * ux) ** 2 + (yy - cy - t * uy) ** 2
        img = np.maximum(img, 100.0 * np.exp(-d2 / (2 * 2.5**2)))
    return img.astype(np.float32)


def _crotch(cx, cy, shape=(60, 60)):
    """Excess of three valleys 8 px wide leaving a crotch 12 px wide centred on (cx, cy) (a signed distance to the
    valleys' outline, positive inside)."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    inside = 6.0 - np.hypot(xx - cx, yy - cy)
    for ang in (0.0, 120.0, 240.0):
        ux, uy = np.cos(np.radians(ang)), np.sin(np.radians(ang))
        t = np.maximum((xx - cx) * ux + (yy - cy) * uy, 0.0)
        inside = np.maximum(inside, 4.0 - np.hypot(xx - cx - t * ux, yy - cy - t * uy))
    return (10.0 * inside).astype(np.float32)


def test_fork_is_the_centre_of_the_largest_disc_and_moves_with_the_fork():
    from skinstretch.processing.feature_localization import locate_forks

    # The skeleton's fork lies somewhere near the crotch: start from three points around it.
    starts_x, starts_y = np.array([28.0, 32.0, 30.0]), np.array([30.0, 28.0, 33.0])
    x0, y0, r0, ok0 = locate_forks(_crotch(30.0, 30.0), x=starts_x, y=starts_y, reach_px=6.0, max_radius_px=10.0)
    x1, y1, r1, ok1 = locate_forks(_crotch(30.4, 29.7), x=starts_x, y=starts_y, reach_px=6.0, max_radius_px=10.0)
    assert ok0.all() and ok1.all()
    np.testing.assert_allclose(x0, 30.0, atol=0.1)
    np.testing.assert_allclose(y0, 30.0, atol=0.1)
    np.testing.assert_allclose(r0, 6.0, atol=0.1)
    np.testing.assert_allclose(x1, 30.4, atol=0.1)
    np.testing.assert_allclose(y1, 29.7, atol=0.1)
    # No valley within reach: nothing found, the start is kept.
    xn, yn, rn, okn = locate_forks(np.full((60, 60), -1.0, np.float32), x=np.array([30.0]), y=np.array([30.0]),
                                   reach_px=5.0, max_radius_px=8.0)
    assert not okn[0] and xn[0] == 30.0 and np.isnan(rn[0])


def _naive_thin(binary):
    """Reference: every foreground pixel checked in every sub-iteration, then the four staircase passes."""
    from skinstretch.processing.thinning import neighbour_code, staircase_table, zhang_suen_tables

    first, second = zhang_suen_tables()
    stairs = staircase_table()
    img = (binary != 0).astype(np.uint8)
    img[0, :] = img[-1, :] = 0
    img[:, 0] = img[:, -1] = 0
    changed = True
    while changed:
        changed = False
        for table in (first, second):
            rr, cc = np.nonzero(img)
            dele = [(r, c) for r, c in zip(rr, cc) if table[neighbour_code(img, r, c)]]
            for r, c in dele:
                img[r, c] = 0
            changed |= bool(dele)
    for s in range(4):
        rr, cc = np.nonzero(img)
        for r, c in zip(rr, cc):
            if img[r, c] and stairs[s, neighbour_code(img, r, c)]:
                img[r, c] = 0
    return img


@pytest.mark.parametrize("density", [0.35, 0.6, 0.85])
def test_incremental_thinning_equals_checking_every_pixel(density):
    from skinstretch.processing.thinning import thin

    rng = np.random.default_rng(7)
    b = (rng.random((40, 50)) < density).astype(np.uint8)
    b = np.kron(b[:20, :25], np.ones((2, 2), np.uint8)) | b  # some thick blobs as well as noise
    np.testing.assert_array_equal(thin(b), _naive_thin(b))


def _cv2_blob_pores(binary, grey, max_diameter_px, min_area_px):
    """Reference for detect_blob_pores: cv2 labelling, moments summed in raster order."""
    import cv2

    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=4, ltype=cv2.CV_32S)
    wh = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    small = wh < max_diameter_px
    small[0] = False
    without = binary.copy()
    without[small[labels]] = 0
    xs, ys = [], []
    for lab in np.flatnonzero(small & (stats[:, cv2.CC_STAT_AREA] >= min_area_px)):
        rr, cc = np.nonzero(labels == lab)
        wts = grey[rr, cc].astype(np.float64)
        xs.append((wts * cc).sum() / wts.sum())
        ys.append((wts * rr).sum() / wts.sum())
    return np.array(xs), np.array(ys), without


@pytest.mark.parametrize("density", [0.3, 0.5, 0.62])
def test_run_based_blob_labelling_matches_opencv(density):
    from skinstretch.processing.pores import detect_blob_pores

    rng = np.random.default_rng(3)
    binary = np.where(rng.random((90, 130)) < density, 255, 0).astype(np.uint8)
    binary[40:45, :] = 255  # one long valley (not a pore), touching both image edges
    grey = rng.uniform(1.0, 50.0, binary.shape).astype(np.float32)
    got = detect_blob_pores(binary, grey=grey, max_diameter_px=5.0, min_area_px=2)
    x, y, without = _cv2_blob_pores(binary, grey, 5.0, 2)
    np.testing.assert_array_equal(got.binary_without_pores, without)
    np.testing.assert_allclose(got.x, x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.y, y, rtol=0, atol=1e-9)
    assert got.x.size > 20


def test_disk_cache_written_under_another_module_name_is_recompiled(tmp_path):
    # numba's cache files are named after the source file but store the importing module's name: a kernel compiled
    # once as top-level "kern" used to make every later "pkg.kern" call fail with "No module named 'kern'".
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "kern.py").write_text(
        "from skinstretch.processing.jit import njit\n\n\n@njit(nogil=True)\ndef twice(x):\n    return 2 * x\n"
    )
    env_path = {"first": f"{pkg}:{root}", "second": f"{tmp_path}:{root}"}
    calls = {"first": "import kern; print(kern.twice(21))", "second": "import pkg.kern as k; print(k.twice(21))"}
    for name in ("first", "second", "second"):
        out = subprocess.run(
            [sys.executable, "-c", calls[name]],
            env={"PYTHONPATH": env_path[name], "PATH": "/usr/bin:/bin"},
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert out.returncode == 0, out.stderr
        assert out.stdout.strip() == "42"
    assert any((pkg / "__pycache__").glob("kern.twice-*.nbi"))  # the cache is still used and written


@pytest.mark.parametrize("shape", [(3, 3), (4, 63), (5, 64), (6, 65), (9, 128), (11, 130), (30, 200)])
def test_bit_packed_thinning_at_word_boundaries(shape):
    # Widths around multiples of 64 exercise the shifts between packed words.
    from skinstretch.processing.thinning import thin

    rng = np.random.default_rng(shape[1])
    b = (rng.random(shape) < 0.7).astype(np.uint8)
    b[:, shape[1] // 2 :] |= (rng.random((shape[0], shape[1] - shape[1] // 2)) < 0.5).astype(np.uint8)
    np.testing.assert_array_equal(thin(b), _naive_thin(b))
    np.testing.assert_array_equal(thin(np.ones(shape, np.uint8)), _naive_thin(np.ones(shape, np.uint8)))


def test_blob_labelling_handles_empty_full_and_edge_blobs():
    from skinstretch.processing.pores import detect_blob_pores

    grey = np.ones((12, 70), np.float32)
    empty = detect_blob_pores(np.zeros((12, 70), np.uint8), grey=grey, max_diameter_px=5.0)
    full = detect_blob_pores(np.full((12, 70), 255, np.uint8), grey=grey, max_diameter_px=5.0)
    assert empty.x.size == 0 and full.x.size == 0
    assert np.count_nonzero(full.binary_without_pores) == 12 * 70  # one big blob is a valley, not a pore
    b = np.zeros((12, 70), np.uint8)
    b[0:2, 0:2] = 255  # corner blob
    b[10:12, 66:70] = 255  # blob on the last row and column
    b[5, 30:33] = 255
    b[6, 32] = 255  # 4-connected to the run above
    b[7, 33] = 255  # only 8-connected: a separate blob
    p = detect_blob_pores(b, grey=grey, max_diameter_px=5.0)
    assert p.x.size == 4
    np.testing.assert_allclose(p.x, [0.5, 31.25, 33.0, 67.5])
    np.testing.assert_allclose(p.y, [0.5, 5.25, 7.0, 10.5])
    assert p.area_px.tolist() == [4, 4, 1, 8]
    assert np.count_nonzero(p.binary_without_pores) == 0


def test_compiled_density_filter_matches_a_kd_tree_reference():
    from scipy.spatial import cKDTree
    from skinstretch.processing.feature_filters import feature_density_mask

    rng = np.random.default_rng(5)
    x, y = rng.uniform(0, 60, 300), rng.uniform(0, 60, 300)
    kind = rng.integers(0, 3, 300).astype(np.int8)
    ref = np.ones(300, bool)
    for k in range(3):
        idx = np.flatnonzero(kind == k)
        pts = np.stack([x[idx], y[idx]], axis=1)
        tree = cKDTree(pts)
        for i in np.flatnonzero(tree.query_ball_point(pts, 4.0, return_length=True) > 3):
            ref[idx[tree.query_ball_point(pts[i], 4.0)]] = False
    got = feature_density_mask(x, y, kind, radius_px=4.0, max_count=3)
    assert 0 < np.count_nonzero(~ref) < 300
    np.testing.assert_array_equal(got, ref)


def test_disk_cache_of_a_caller_is_recompiled_when_its_callee_in_another_file_changes(tmp_path):
    # numba links a compiled callee into its caller's cache entry but only checks the caller's own file: an edit of
    # the callee's file (e.g. processing/delaunay.py under processing/stretch.py) would otherwise leave the old
    # callee running until the caller's file changed.
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    callee = "from skinstretch.processing.jit import njit\n\nSCALE = {scale}\n\n\n@njit(nogil=True)\ndef inner(x):\n    return {body}\n"
    (pkg / "caller.py").write_text(
        "from skinstretch.processing.jit import njit\nfrom pkg.callee import inner\n\n\n@njit(nogil=True)\n"
        "def outer(x):\n    return inner(x) + 1\n"
    )

    def run():
        out = subprocess.run(
            [sys.executable, "-c", "from pkg.caller import outer; print(outer(10))"],
            # No .pyc: Python would reuse a stale one for a file rewritten within the same second at the same size.
            env={"PYTHONPATH": f"{tmp_path}:{root}", "PATH": "/usr/bin:/bin", "PYTHONDONTWRITEBYTECODE": "1"},
            capture_output=True, text=True, timeout=120,
        )
        assert out.returncode == 0, out.stderr
        return out.stdout.strip()

    (pkg / "callee.py").write_text(callee.format(scale=2, body="2 * x"))
    assert run() == "21"
    assert run() == "21"  # from the cache
    assert any((pkg / "__pycache__").glob("caller.outer-*.nbi"))
    (pkg / "callee.py").write_text(callee.format(scale=2, body="3 * x"))  # the callee's code changes
    assert run() == "31"
    (pkg / "callee.py").write_text(callee.format(scale=5, body="SCALE * x"))
    assert run() == "51"
    (pkg / "callee.py").write_text(callee.format(scale=7, body="SCALE * x"))  # only a constant it reads changes
    assert run() == "71"
