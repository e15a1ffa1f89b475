"""Feature filters of seed 4.8.5-4.8.6: they work on feature columns (x, y, kind) and return a keep mask.

- :func:`feature_density_mask` (4.8.5): every feature in a 0.25 mm circle holding more than 3 features of its
  kind is deleted, for all features in parallel and each kind separately.
- :func:`border_mask` / :func:`outside_border` (4.8.6): features under the dilated background + image-edge mask
  are deleted.
"""

from __future__ import annotations

import cv2
import numpy as np
from skinstretch.processing.argument_checks import positive_number
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit

__all__ = ["feature_density_mask", "border_mask", "outside_border"]


def feature_density_mask(x: np.ndarray, y: np.ndarray, kind: np.ndarray, *, radius_px: float, max_count: int) -> np.ndarray:
    """Keep mask of the feature density filter (seed 4.8.5).

    For every feature, the features of the same kind within ``radius_px`` (itself included) are counted; when the
    count exceeds ``max_count`` all of them are deleted. Counts are taken before any deletion (in parallel).
    """
    radius_px = positive_number(radius_px, "radius_px")
    if not (isinstance(max_count, (int, np.integer)) and max_count >= 1):
        raise InvalidInputError(f"max_count must be a positive integer, got {max_count!r}")
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    kind = np.ascontiguousarray(kind, dtype=np.int64)
    if not x.shape == y.shape == kind.shape or x.ndim != 1:
        raise InvalidInputError(f"x, y and kind must be 1-D arrays of one length, got {x.shape}, {y.shape}, {kind.shape}")
    return _density_keep(x, y, kind, radius_px, int(max_count))


@njit(nogil=True)
def _density_keep(x, y, kind, radius, max_count):  # pragma: no cover - compiled
    """Keep mask of :func:`feature_density_mask`: pairwise distances within each kind (a frame holds a few hundred
    features), neighbours counted with the feature itself, at distance <= radius."""
    n = x.size
    r2 = radius * radius
    count = np.zeros(n, np.int64)
    for i in range(n):
        for j in range(i, n):
            if kind[j] != kind[i]:
                continue
            dx = x[j] - x[i]
            dy = y[j] - y[i]
            if dx * dx + dy * dy <= r2:
                count[i] += 1
                if j != i:
                    count[j] += 1
    keep = np.ones(n, np.bool_)
    for i in range(n):
        if count[i] <= max_count:
            continue
        for j in range(n):
            if kind[j] == kind[i]:
                dx = x[j] - x[i]
                dy = y[j] - y[i]
                if dx * dx + dy * dy <= r2:
                    keep[j] = False
    return keep


def border_mask(background: np.ndarray, *, dilation_px: int) -> np.ndarray:
    """Deletion mask of seed 4.8.6: the background plus a 1-pixel image border, dilated (square) by ``dilation_px``."""
    if background.ndim != 2:
        raise InvalidInputError(f"background must be 2-D, got shape {background.shape}")
    if dilation_px < 0:
        raise InvalidInputError(f"dilation_px must be >= 0, got {dilation_px!r}")
    m = background.astype(np.uint8)
    m[0, :] = m[-1, :] = 1
    m[:, 0] = m[:, -1] = 1
    if dilation_px > 0:
        d = 2 * int(dilation_px) + 1
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_RECT, (d, d)))
    return m.astype(bool)


def outside_border(x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Keep mask: True for features whose (rounded) position is not under ``mask``."""
    h, w = mask.shape
    xi = np.clip(np.rint(np.asarray(x)).astype(np.int64), 0, w - 1)
    yi = np.clip(np.rint(np.asarray(y)).astype(np.int64), 0, h - 1)
    return ~mask[yi, xi]
