"""Synthetic inputs with exact ground truth for the tracking/stretch tests (no tests in this module).

An analytic fingerprint-like pattern (ridges as a phase field with a few spiral points, seed 4 / FACTS) is
rendered under a known forward displacement field by inverting ``y = X + u(X)`` with fixed-point iterations, so
every frame is exact, with no interpolation error.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from skinstretch.processing.feature_table import make_features


def pattern(x: np.ndarray, y: np.ndarray, *, period: float = 27.0, seed: int = 0) -> np.ndarray:
    """Grey levels (float, ~[30, 220]) of a fingerprint-like pattern at skin coordinates (x, y) px."""
    rng = np.random.default_rng(seed)
    angle = 0.3
    phi = 2 * np.pi / period * (x * np.cos(angle) + y * np.sin(angle))
    phi += 6.0 * np.sin(x / 97.0 + 1.3) * np.cos(y / 83.0)  # slowly curving ridges
    for _ in range(6):  # spiral points: minutiae
        cx, cy = rng.uniform(0, 640), rng.uniform(0, 480)
        phi += rng.choice([-1, 1]) * np.arctan2(y - cy, x - cx)
    img = 125 + 85 * np.cos(phi)
    # pores: small bright blobs along ridges, fixed to the skin
    pores = np.column_stack([rng.uniform(-20, 660, 320), rng.uniform(-20, 500, 320)])
    dist, _ = cKDTree(pores).query(np.column_stack([x.ravel(), y.ravel()]))
    img += 60 * np.exp(-(dist.reshape(x.shape) ** 2) / (2 * 2.0**2))
    return img


def invert(field, yy: np.ndarray, xx: np.ndarray, iterations: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """Skin coordinates X seen at image points y, for y = X + field(X)."""
    X, Y = xx.copy(), yy.copy()
    for _ in range(iterations):
        u, v = field(X, Y)
        X, Y = xx - u, yy - v
    return X, Y


def render(field, *, shape=(240, 320), seed: int = 0, noise: float = 0.0, rng=None) -> np.ndarray:
    """uint8 image of the pattern under the forward displacement ``field(X, Y) -> (u, v)``."""
    yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    X, Y = invert(field, yy, xx)
    img = pattern(X, Y, seed=seed)
    if noise:
        img = img + (rng or np.random.default_rng(seed)).normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def affine_field(tx: float, ty: float, exx: float = 0.0, eyy: float = 0.0, center=(160.0, 120.0)):
    def f(X, Y):
        return tx + exx * (X - center[0]), ty + eyy * (Y - center[1])

    return f


def moving_features(n_frames: int, *, n: int = 60, step=(2.0, 0.0), noise: float = 0.0, seed: int = 0,
                    missing: float = 0.0, spurious: int = 0, area=(40, 600, 40, 440), stretch: float = 0.0):
    """Feature tables of ``n`` points moved by ``step`` px per frame (plus ``stretch`` x-strain per frame about
    the area centre), with position noise, random misses and spurious features. Returns (tables, true_xy)."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(area[0], area[1], n)
    y0 = rng.uniform(area[2], area[3], n)
    kinds = rng.integers(0, 3, n)
    orient = np.where(kinds < 2, rng.uniform(0, 360, n), np.nan)
    cx = 0.5 * (area[0] + area[1])
    tables, truth = [], []
    x, y = x0.copy(), y0.copy()
    for k in range(n_frames):
        if k:
            x = x + step[0] + stretch * (x - cx)
            y = y + step[1]
        truth.append(np.column_stack([x, y]))
        keep = rng.random(n) >= missing
        fx = x[keep] + rng.normal(0, noise, keep.sum()) if noise else x[keep]
        fy = y[keep] + rng.normal(0, noise, keep.sum()) if noise else y[keep]
        kk, oo = kinds[keep], orient[keep]
        if spurious:
            fx = np.concatenate([fx, rng.uniform(area[0], area[1], spurious)])
            fy = np.concatenate([fy, rng.uniform(area[2], area[3], spurious)])
            kk = np.concatenate([kk, rng.integers(0, 3, spurious)])
            oo = np.concatenate([oo, np.full(spurious, np.nan)])
        oo = np.where(kk < 2, np.nan_to_num(oo, nan=0.0), np.nan)
        tables.append(make_features(fx, fy, kk, orientation=oo, frame=k))
    return tables, truth
