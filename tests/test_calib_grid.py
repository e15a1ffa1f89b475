"""Calibration-grid rendering, dot detection (sub-pixel) and grid topology with missing and spurious dots."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.geometric_calibration import INDEX_NONE, detect_dots, index_grid
from skinstretch.simulators.dot_grid_images import render_calibration_grid
from skinstretch.simulators.prism_optics import PrismOptics
from skinstretch.simulators.surfaces import RuledSurface

KINDS = ("flat", "ridge", "valley")


@pytest.fixture(scope="module")
def grids():
    out = {}
    for kind in KINDS:
        optics = PrismOptics(surface=RuledSurface(kind=kind, center_mm=0.3))
        out[kind] = render_calibration_grid(
            optics, missing_fraction=0.1, n_spurious=6, offset_mm=(0.13, 0.21), seed=7
        )
    return out


def test_rendered_dots_are_dark_on_a_bright_surface(grids):
    g = grids["flat"]
    img = g.image.astype(float)
    centres = np.rint(g.xy_px[g.visible]).astype(int)
    at_dots = img[centres[:, 1], centres[:, 0]]
    assert np.median(at_dots) < 60 and np.median(img) > 150
    missing = g.inside & ~g.drawn
    assert 0.05 < missing.sum() / g.inside.sum() < 0.15
    hole = np.rint(g.xy_px[missing]).astype(int)
    assert np.median(img[hole[:, 1], hole[:, 0]]) > 150  # a missing dot shows the bare surface


def test_rendering_is_deterministic():
    optics = PrismOptics(width=200, height=120, field_width_mm=3.2)
    a = render_calibration_grid(optics, missing_fraction=0.1, n_spurious=2, seed=3)
    b = render_calibration_grid(optics, missing_fraction=0.1, n_spurious=2, seed=3)
    c = render_calibration_grid(optics, missing_fraction=0.1, n_spurious=2, seed=4)
    assert np.array_equal(a.image, b.image) and not np.array_equal(a.image, c.image)


def test_renderer_validates_options():
    with pytest.raises(InvalidInputError, match="dot_diameter_mm"):
        render_calibration_grid(PrismOptics(), dot_diameter_mm=0.6)
    with pytest.raises(InvalidInputError, match="missing_fraction"):
        render_calibration_grid(PrismOptics(), missing_fraction=1.0)


def _image_centroids(g):
    """Area centroid of each visible dot's image (its outline projected through the optics)."""
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = g.us_mm[g.visible][:, None, :] + 0.5 * g.dot_diameter_mm * np.stack([np.cos(t), np.sin(t)], -1)
    p = g.optics.surface_to_image(ring)
    x, y = p[..., 0], p[..., 1]
    xn, yn = np.roll(x, -1, 1), np.roll(y, -1, 1)
    c = x * yn - xn * y
    a = 0.5 * c.sum(1)
    return np.stack([((x + xn) * c).sum(1) / (6 * a), ((y + yn) * c).sum(1) / (6 * a)], -1)


@pytest.mark.parametrize("kind", KINDS)
def test_dot_centres_are_subpixel_accurate(grids, kind):
    g = grids[kind]
    dots = detect_dots(g.image, px_per_mm=g.optics.px_per_mm)
    truth = _image_centroids(g)
    dist, _ = cKDTree(truth).query(dots.xy)
    hit = dist < 1.5
    found, _ = cKDTree(dots.xy).query(truth)
    assert np.mean(found < 1.5) > 0.97  # nearly every visible dot is found
    assert (~hit).sum() <= 6 + 4  # the extras are the 6 specks (alone, or merged with a dot) and border dots
    # Sub-pixel: within a few hundredths of a pixel of the dot image's true centroid (which differs from the image
    # of the dot's centre by up to ~0.1 px on slopes; the fit models that offset). The worst are dots a speck
    # touches, and dots where the slope's shading has a kink.
    assert np.sqrt(np.mean(dist[hit] ** 2)) < 0.035
    assert np.percentile(dist[hit], 98) < 0.1


def test_detection_on_blank_and_bad_input():
    assert len(detect_dots(np.full((100, 120), 200, np.uint8), px_per_mm=62.0)) == 0
    with pytest.raises(InvalidInputError, match="px_per_mm"):
        detect_dots(np.zeros((50, 50)), px_per_mm=0.0)
    with pytest.raises(InvalidInputError, match="image"):
        detect_dots(np.zeros((5, 5, 3)), px_per_mm=62.0)


@pytest.mark.parametrize("kind", KINDS)
def test_topology_has_no_wrong_index(grids, kind):
    g = grids[kind]
    dots = detect_dots(g.image, px_per_mm=g.optics.px_per_mm)
    ij = index_grid(dots.xy, image_shape=g.image.shape)
    indexed = ij[:, 0] != INDEX_NONE
    dist, nb = cKDTree(g.xy_px).query(dots.xy)
    real = dist < 1.5
    # Every real dot found gets an index, and the indices differ from the truth by one constant shift; that
    # includes the few blobs where a speck merged with a dot (they carry the dot's index, and the fit rejects
    # them as outliers by their position).
    assert np.mean(indexed[real]) > 0.98
    shift = g.ij[nb[indexed]] - ij[indexed]
    assert len(np.unique(shift, axis=0)) == 1
    assert (indexed & ~real).sum() <= 6


def test_topology_of_a_synthetic_lattice_with_holes_and_clutter(rng):
    i, j = np.meshgrid(np.arange(-10, 11), np.arange(-8, 9), indexing="ij")
    ij_true = np.stack([i.ravel(), j.ravel()], -1)
    # A lattice whose row pitch halves and doubles again across a band (like a ridge), slightly rotated.
    yrow = np.cumsum(np.where(np.abs(np.arange(-8, 9)) < 2, 12.0, 22.0))
    xy = np.stack([320 + 31.0 * ij_true[:, 0] + 0.02 * ij_true[:, 1] * 22, yrow[ij_true[:, 1] + 8]], -1)
    xy += rng.normal(0, 0.05, xy.shape)
    keep = rng.random(len(xy)) > 0.15
    clutter = rng.uniform(xy.min(0), xy.max(0), (10, 2))
    pts = np.concatenate([xy[keep], clutter])
    ij = index_grid(pts, image_shape=(480, 640))
    got = ij[: keep.sum()]
    ok = got[:, 0] != INDEX_NONE
    assert ok.mean() > 0.95
    assert len(np.unique(ij_true[keep][ok] - got[ok], axis=0)) == 1


def test_topology_of_random_dots_is_small(rng):
    pts = rng.uniform([0, 0], [640, 484], (300, 2))
    ij = index_grid(pts, image_shape=(484, 640))
    assert (ij[:, 0] != INDEX_NONE).sum() < 0.5 * len(pts)
