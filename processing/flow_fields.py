"""What is read off a displacement field on a grid: its small-strain tensor by finite differences
(:func:`grid_strain`), and a dense (per-pixel) flow sampled at points (:func:`sample_dense_flow`, e.g. OpenCV's
methods compared in the bench)."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.flow import FlowField

__all__ = ["grid_strain", "sample_dense_flow"]


def grid_strain(field: FlowField) -> tuple[np.ndarray, np.ndarray]:
    """Small-strain tensor (exx, eyy, exy) of a flow field by central differences on its grid.

    Returns ``(strain (GY, GX, 3), ok (GY, GX))``; strain is NaN exactly where ``ok`` is False (a node or one of
    its four neighbours invalid, or on the border).
    """
    d = field.displacement
    v = field.valid
    sx = field.grid_x[1] - field.grid_x[0]
    sy = field.grid_y[1] - field.grid_y[0]
    out = np.full(d.shape[:2] + (3,), np.nan)
    ok = np.zeros(v.shape, bool)
    ok[1:-1, 1:-1] = v[1:-1, 1:-1] & v[1:-1, 2:] & v[1:-1, :-2] & v[2:, 1:-1] & v[:-2, 1:-1]
    dudx = (d[1:-1, 2:, 0] - d[1:-1, :-2, 0]) / (2 * sx)
    dvdy = (d[2:, 1:-1, 1] - d[:-2, 1:-1, 1]) / (2 * sy)
    dudy = (d[2:, 1:-1, 0] - d[:-2, 1:-1, 0]) / (2 * sy)
    dvdx = (d[1:-1, 2:, 1] - d[1:-1, :-2, 1]) / (2 * sx)
    inner = np.stack([dudx, dvdy, 0.5 * (dudy + dvdx)], axis=-1)
    sub = out[1:-1, 1:-1]
    sub[ok[1:-1, 1:-1]] = inner[ok[1:-1, 1:-1]]
    return out, ok


def sample_dense_flow(flow: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Bilinear sample of a dense (H, W, 2) flow (e.g. from OpenCV) at ``points`` (n, 2) x, y px."""
    flow = np.asarray(flow, dtype=np.float32)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise InvalidInputError(f"flow must have shape (H, W, 2), got {flow.shape}")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    coords = np.vstack([p[:, 1], p[:, 0]])
    return np.stack([map_coordinates(flow[..., i], coords, order=1, mode="nearest") for i in range(2)], axis=1)
