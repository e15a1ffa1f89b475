"""The span registration kernel's linear algebra: one Cholesky factor gives every solve and statistic."""

import cv2
import numpy as np
import pytest

from skinstretch.processing.warp_registration import (
    _ORDER,
    _chol_solve,
    _cholesky_permuted,
    _fit_statistics,
    second_order_kernel,
)

AFFINE = [0, 1, 2, 6, 7, 8]
CURVATURE = [3, 4, 5, 9, 10, 11]


def _spd(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    j = rng.normal(size=(200, 12)) * rng.uniform(0.1, 100.0, 12)  # badly scaled columns, as image moments are
    return j.T @ j


@pytest.mark.parametrize("seed", range(5))
def test_the_factor_gives_the_solve_the_wald_statistic_the_affine_translation_and_the_variances(seed):
    hess = _spd(seed)
    q = np.random.default_rng(100 + seed).normal(size=12)
    rhs = np.random.default_rng(200 + seed).normal(size=12)
    chol = np.zeros((12, 12))
    assert _cholesky_permuted(hess, chol)
    p = hess[np.ix_(_ORDER, _ORDER)]
    np.testing.assert_allclose(chol @ chol.T, p, rtol=1e-10, atol=1e-8 * np.abs(p).max())
    np.testing.assert_allclose(_chol_solve(chol, rhs), np.linalg.solve(hess, rhs), rtol=1e-8)
    wald, ax, ay, v2x, v2y, v1x, v1y = _fit_statistics(chol, q)
    hinv = np.linalg.inv(hess)
    c22 = hinv[np.ix_(CURVATURE, CURVATURE)]
    q1, q2 = q[AFFINE], q[CURVATURE]
    affine = q1 + np.linalg.solve(hess[np.ix_(AFFINE, AFFINE)], hess[np.ix_(AFFINE, CURVATURE)] @ q2)
    h11inv = np.linalg.inv(hess[np.ix_(AFFINE, AFFINE)])
    np.testing.assert_allclose(wald, q2 @ np.linalg.solve(c22, q2), rtol=1e-8)
    np.testing.assert_allclose([ax, ay], affine[[0, 3]], rtol=1e-8)
    np.testing.assert_allclose([v2x, v2y], [hinv[0, 0], hinv[6, 6]], rtol=1e-8)
    np.testing.assert_allclose([v1x, v1y], [h11inv[0, 0], h11inv[3, 3]], rtol=1e-8)


def test_a_singular_system_is_refused():
    hess = _spd(0)
    hess[:, 4] = hess[:, 3]  # two columns alike: ridges all one way leave the warp's terms inseparable
    hess[4, :] = hess[3, :]
    assert not _cholesky_permuted(hess, np.zeros((12, 12)))
    nearly = _spd(1)
    nearly[4, :] = nearly[:, 4] = nearly[:, 3] * (1 + 1e-9)
    nearly[4, 4] = nearly[3, 3] * (1 + 2e-9)
    assert not _cholesky_permuted(nearly, np.zeros((12, 12)))


def test_a_window_without_texture_is_not_ok_and_a_textured_one_finds_its_shift():
    rng = np.random.default_rng(0)
    a = cv2.GaussianBlur(rng.uniform(0, 255, (120, 120)).astype(np.float32), (0, 0), 2.0)
    shift = (0.3, -0.2)
    m = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    b = cv2.warpAffine(a, m, (120, 120), flags=cv2.INTER_CUBIC)  # b(x) = a(x - shift): d = shift
    gy, gx = np.gradient(a)
    a8, b8 = np.clip(a, 0, 255).astype(np.uint8), np.clip(b, 0, 255).astype(np.uint8)
    points = np.array([[60.0, 60.0]])
    out, ok = second_order_kernel(a8, b8, gx.astype(np.float32), gy.astype(np.float32), points, np.zeros((1, 2)),
                                  15, 8)
    assert ok[0]
    np.testing.assert_allclose(out[0, 6:8], shift, atol=0.05)
    assert np.all(out[0, 9:13] > 0)
    flat = np.full((120, 120), 100, np.uint8)
    zero = np.zeros((120, 120), np.float32)
    _, ok = second_order_kernel(flat, flat, zero, zero, points, np.zeros((1, 2)), 15, 2)
    assert not ok[0]
