"""Fusing each point's registered displacement with its neighbours' local affine (processing.neighbour_fusion)."""

import numpy as np
import pytest

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.neighbour_fusion import fuse_with_neighbours

RADIUS, MODEL = 93.0, 0.012  # the analysis' 1.5 mm and 0.0002 mm at 62 px/mm


def _scatter(n=260, seed=0, size=(640, 484)):
    rng = np.random.default_rng(seed)
    return rng.uniform((20, 20), (size[0] - 20, size[1] - 20), (n, 2)), rng


def _ridge_covariances(points, along_px=0.04, across_px=0.02):
    """Covariances long along 'ridges' whose direction turns slowly over the image (a whorl's arcs)."""
    theta = np.arctan2(points[:, 1] - 242.0, points[:, 0] - 320.0) + np.pi / 2  # along the arcs
    t = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    cov = along_px**2 * t[:, :, None] * t[:, None, :] + across_px**2 * n[:, :, None] * n[:, None, :]
    return cov, t, n


def _noisy(true, cov, rng):
    return true + np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=true.shape))


def test_fusion_takes_the_motion_along_the_ridges_from_the_neighbours():
    # An affine frame-to-frame motion (a slide with 0.3 % stretch), measured with twice the noise along the ridges
    # as across them: the fused error along them falls, across them it does not grow.
    points, rng = _scatter()
    grad = np.array([[0.003, 0.0005], [-0.0005, -0.001]])
    true = np.array([1.4, -0.3]) + (points - 320.0) @ grad.T
    cov, along, across = _ridge_covariances(points)
    errs = {"measured": [], "fused": []}
    for _ in range(8):
        meas = _noisy(true, cov, rng)
        fused, changed = fuse_with_neighbours(points, meas, cov, radius_px=RADIUS, model_sigma_px=MODEL)
        assert changed.mean() > 0.95
        errs["measured"].append(meas - true)
        errs["fused"].append(fused - true)
    e = {k: np.concatenate(v) for k, v in errs.items()}
    t, nrm = np.tile(along, (8, 1)), np.tile(across, (8, 1))

    def rms(x, direction):
        return float(np.sqrt(np.mean(np.sum(x * direction, axis=1) ** 2)))

    assert rms(e["fused"], t) < 0.6 * rms(e["measured"], t)
    assert rms(e["fused"], nrm) < 1.0 * rms(e["measured"], nrm)
    # No bias on the affine motion itself.
    assert np.abs(e["fused"].mean(axis=0)).max() < 0.004


def test_a_slip_band_the_window_gradient_sees_is_not_pulled_to_the_affine():
    # A compression band 0.8 mm (50 px) wide across x: the displacement steps down by 0.15 px across it. Without
    # the points' own gradients the neighbours' affine pulls the band's points; with them, less.
    points, rng = _scatter(seed=1)
    centre, width, step = 300.0, 50.0, 0.15
    s = np.clip((points[:, 0] - (centre - width / 2)) / width, 0, 1)
    true = np.stack([1.0 - step * s, np.zeros(len(points))], axis=1)
    in_band = (s > 0.05) & (s < 0.95)
    grad = np.zeros((len(points), 2, 2))
    grad[in_band, 0, 0] = -step / width
    cov, _, _ = _ridge_covariances(points)
    meas = true.copy()  # noise-free: only the pull
    blind, _ = fuse_with_neighbours(points, meas, cov, radius_px=RADIUS, model_sigma_px=MODEL)
    seen, _ = fuse_with_neighbours(points, meas, cov, gradient=grad, radius_px=RADIUS, model_sigma_px=MODEL)
    bias_blind = np.abs(blind - true)[in_band].mean()
    bias_seen = np.abs(seen - true)[in_band].mean()
    assert bias_blind > 0.005  # (0.0084 px; the neighbours' misfit already loosens the pull somewhat)
    assert bias_seen < 0.7 * bias_blind  # (0.0049 px)


def test_points_without_a_covariance_or_neighbours_are_left_alone_and_bad_input_is_one_line():
    points, rng = _scatter(n=40, seed=2)
    disp = rng.normal(size=(40, 2))
    cov = np.tile(np.eye(2) * 1e-3, (40, 1, 1))
    cov[3] = np.nan
    fused, changed = fuse_with_neighbours(points, disp, cov, radius_px=RADIUS, model_sigma_px=MODEL)
    assert not changed[3] and np.array_equal(fused[3], disp[3])
    assert np.all(np.isfinite(fused))
    # Too few points for an affine of the neighbours: nothing changes.
    few, ch = fuse_with_neighbours(points[:4], disp[:4], cov[:4], radius_px=RADIUS, model_sigma_px=MODEL)
    assert not ch.any() and np.array_equal(few, disp[:4])
    # A point far from every other keeps its own measurement.
    far = np.concatenate([points, [[5000.0, 5000.0]]])
    out, ch = fuse_with_neighbours(far, np.concatenate([disp, [[9.0, 9.0]]]), np.concatenate([cov, cov[:1]]),
                                   radius_px=RADIUS, model_sigma_px=MODEL)
    assert not ch[-1] and np.array_equal(out[-1], [9.0, 9.0])
    with pytest.raises(InvalidInputError, match="one row per point"):
        fuse_with_neighbours(points, disp[:5], cov, radius_px=RADIUS, model_sigma_px=MODEL)
    with pytest.raises(InvalidInputError, match="positive"):
        fuse_with_neighbours(points, disp, cov, radius_px=0.0, model_sigma_px=MODEL)
    with pytest.raises(InvalidInputError, match="gradient has"):
        fuse_with_neighbours(points, disp, cov, gradient=np.zeros((3, 2, 2)), radius_px=RADIUS, model_sigma_px=MODEL)
