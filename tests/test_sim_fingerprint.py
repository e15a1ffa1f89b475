"""The synthetic print: minutia kinds and positions agree with the binarised skeleton, pores are bright spots on
dark ridges, FTIR polarity, the ridge period."""

import numpy as np
import pytest
from scipy import ndimage as ndi
from skimage.morphology import skeletonize

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.feature_table import FeatureKind
from skinstretch.simulators.fingerprint import Fingerprint, FingerprintParams
from skinstretch.simulators.scene import SceneRenderer, load_scene


@pytest.fixture(scope="module")
def flat_frame0():
    """Noise-free frame 0 of a flat scene, divided by the illumination gain, with its renderer."""
    scene = load_scene("flatL").model_copy(update={"n_frames": 2})
    r = SceneRenderer(scene, seed=3, noise=0)
    return r, r.radiance(0) / r._gain


def _skeleton_points(binary):
    sk = skeletonize(binary)
    nb = ndi.convolve(sk.astype(int), np.ones((3, 3), int), mode="constant") - 1
    return sk, np.argwhere(sk & (nb == 1)), np.argwhere(sk & (nb >= 3))


def test_minutiae_sit_on_skeleton_endings_and_junctions(flat_frame0):
    r, rad = flat_frame0
    cam = r.scene.camera
    valley = rad > (cam.ridge_level + cam.valley_level) / 2  # FTIR: valleys bright
    _, ends, juncs = _skeleton_points(valley)
    xy, vis = r.feature_positions(0)
    _, kinds, skin = r.fingerprint.features()
    vis = vis & (r._ellipse_contact(skin, 0.0) > 0.999)  # the soft contact edge thins the valleys
    h, w = rad.shape
    checked = {0: 0, 1: 0}
    dists = []
    for (x, y), v, k in zip(xy, vis, kinds):
        if k == FeatureKind.PORE or not v or not (15 < x < w - 15 and 15 < y < h - 15):
            continue
        d_end = np.min(np.hypot(ends[:, 1] - x, ends[:, 0] - y))
        d_junc = np.min(np.hypot(juncs[:, 1] - x, juncs[:, 0] - y))
        if k == FeatureKind.VALLEY_ENDING:
            # A thinned valley end moves by a pixel or two with the pixel grid (thinning retracts ends by about a
            # pixel at any resolution, and the truth is read at 4 um); the junction is steadier.
            assert d_end <= 2.5, f"valley ending at ({x:.1f}, {y:.1f}): nearest skeleton end {d_end:.2f} px"
            dists.append(d_end)
            assert d_junc > 5, "a valley ending must not sit on a junction"
        else:
            assert d_junc <= 1.5, f"valley bifurcation at ({x:.1f}, {y:.1f}): nearest junction {d_junc:.2f} px"
            dists.append(d_junc)
            assert d_end > 5, "a valley bifurcation must not sit on a skeleton end"
        checked[int(k)] += 1
    assert checked[0] >= 2 and checked[1] >= 2, checked
    assert np.mean(dists) < 1.2


def test_pores_are_bright_maxima_inside_dark_ridges(flat_frame0):
    r, rad = flat_frame0
    cam = r.scene.camera
    mid = (cam.ridge_level + cam.valley_level) / 2
    xy, vis = r.feature_positions(0)
    _, kinds, _ = r.fingerprint.features()
    radius = r.fingerprint.pore_radius_mm
    n_minutiae = int(np.sum(kinds != FeatureKind.PORE))
    smooth = ndi.gaussian_filter(rad.astype(np.float64), 0.7)
    h, w = rad.shape
    _, _, skin = r.fingerprint.features()
    full_contact = r._ellipse_contact(skin, 0.0) > 0.999  # away from the soft contact edge
    n = 0
    for i in np.flatnonzero((kinds == FeatureKind.PORE) & vis & full_contact):
        x, y = xy[i]
        if not (12 < x < w - 12 and 12 < y < h - 12):
            continue
        xi, yi = int(round(x)), int(round(y))
        win = smooth[yi - 2 : yi + 3, xi - 2 : xi + 3]
        # The brightest pixel around the true centre is within one pixel of it.
        iy, ix = np.unravel_index(np.argmax(win), win.shape)
        assert abs(ix - 2) <= 1 and abs(iy - 2) <= 1, (x, y)
        assert smooth[yi, xi] > mid
        # Along the ridge, just outside the pore, the image is dark ridge on both sides.
        _, grad = r.fingerprint.phase_and_gradient(r.fingerprint.pore_xy[i - n_minutiae][None])
        tangent = np.array([grad[0, 1], -grad[0, 0]]) / np.linalg.norm(grad[0])
        off = (radius[i - n_minutiae] + 0.05) * r.calibration.px_per_mm
        for sgn in (-1, 1):
            px, py = x + sgn * off * tangent[0], y + sgn * off * tangent[1]
            assert ndi.map_coordinates(rad, [[py], [px]], order=1)[0] < mid, "pore not inside a dark ridge"
        n += 1
    assert n >= 50


def test_polarity_and_ridge_period(flat_frame0):
    r, rad = flat_frame0
    fp = r.fingerprint
    phi, grad = fp.phase_and_gradient(fp.pore_xy[:200])
    period = 2 * np.pi / np.hypot(*grad.T)
    assert 0.36 < np.median(period) < 0.50
    # Ridge centres (phi = 0 mod 2 pi) are dark: sample the master print there.
    master = fp.render(u0=-1.0, s0=-1.0, step_mm=0.01, shape=(200, 200))
    assert master.min() < 0.1 and master.max() > 0.9
    assert np.all(np.abs(((phi + np.pi) % (2 * np.pi)) - np.pi) < 1e-3)  # pores sit on ridge centre lines


def test_feature_spacing_is_unambiguous(flat_frame0):
    r, _ = flat_frame0
    fp = r.fingerprint
    m = fp.minutia_xy
    d = np.hypot(m[:, None, 0] - m[None, :, 0], m[:, None, 1] - m[None, :, 1]) + np.eye(len(m)) * 1e9
    assert d.min() > 0.4
    dp = np.hypot(fp.pore_xy[:, None, 0] - m[None, :, 0], fp.pore_xy[:, None, 1] - m[None, :, 1])
    assert dp.min() >= fp.params.pore_minutia_clearance_mm - 1e-9
    assert fp.minutia_skeleton_found.all()
    area = np.prod(np.diff(np.reshape(fp.bounds_mm, (2, 2)), axis=1))
    assert 0.05 < len(m) / area < 0.4
    assert 1.0 < len(fp.pore_xy) / area < 6.0


def test_generation_is_seeded_and_validated():
    p = FingerprintParams()
    a = Fingerprint.generate(p, bounds_mm=(-2, 2, -2, 2), rng=np.random.default_rng(5))
    b = Fingerprint.generate(p, bounds_mm=(-2, 2, -2, 2), rng=np.random.default_rng(5))
    np.testing.assert_array_equal(a.minutia_xy, b.minutia_xy)
    np.testing.assert_array_equal(a.pore_xy, b.pore_xy)
    with pytest.raises(InvalidInputError, match="ridge_period_mm"):
        FingerprintParams(ridge_period_mm=0.05)
    with pytest.raises(InvalidInputError, match="bounds_mm"):
        Fingerprint.generate(p, bounds_mm=(2, -2, -2, 2), rng=np.random.default_rng(0))
