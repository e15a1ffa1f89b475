"""Feature filters of seed 4.8.5-4.8.6: they work on feature columns (x, y, kind) and return a keep mask.

- :func:`feature_density_mask` (4.8.5): every feature in a 0.25 mm circle holding more than 3 features of its
  kind is deleted, for all features in parallel and each kind separately.
- :func:`clear_of_background` (4.8.6): features within a distance of the background or of the image edge are
  deleted. The distance is Euclidean: a square dilation (as cv2.dilate with a rectangle does it) reaches 1.4
  times as far along the diagonals, and deleted true minutiae up to 0.4 mm from an oblique edge of contact.
"""

from __future__ import annotations

import cv2
import numpy as np
from skinstretch.processing.argument_checks import positive_number
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit

__all__ = ["feature_density_mask", "clear_of_background"]


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


def clear_of_background(
    x: np.ndarray, y: np.ndarray, background: np.ndarray, *, radius_px: float, edge_px: float
) -> np.ndarray:
    """Keep mask of seed 4.8.6: False for features within ``radius_px`` of a background pixel or within ``edge_px``
    of the image edge.

    Distances are Euclidean, from the feature's (sub-pixel) position to the background pixels' centres and to the
    image's outer rows and columns.

    Examples
    --------
    >>> import numpy as np
    >>> bg = np.zeros((40, 40), bool)
    >>> bg[:, 30:] = True
    >>> clear_of_background(np.array([10.0, 21.5, 22.5, 4.0]), np.array([20.0, 20.0, 20.0, 20.0]), bg, radius_px=8.0,
    ...                     edge_px=5.0)
    array([ True,  True, False, False])
    """
    if background.ndim != 2:
        raise InvalidInputError(f"background must be 2-D, got shape {background.shape}")
    radius_px, edge_px = float(radius_px), float(edge_px)
    for name, v in (("radius_px", radius_px), ("edge_px", edge_px)):
        if not (np.isfinite(v) and v >= 0):
            raise InvalidInputError(f"{name} must be a non-negative number, got {v!r}")
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise InvalidInputError(f"x and y must be 1-D arrays of equal length, got {x.shape} and {y.shape}")
    bg = np.ascontiguousarray(background, dtype=np.bool_)
    # The background's integral image: a feature whose square around the disc holds no background is kept without
    # scanning the disc (most are), so the cost does not grow with the disc's area.
    counts = cv2.integral(bg.view(np.uint8))
    return _clear_of(x, y, bg, counts, radius_px, edge_px)


@njit(nogil=True)
def _clear_of(x, y, bg, counts, radius, edge):  # pragma: no cover - compiled
    h, w = bg.shape
    r2 = radius * radius
    keep = np.ones(x.size, np.bool_)
    for k in range(x.size):
        px = x[k]
        py = y[k]
        if not (px > edge and py > edge and px < w - 1 - edge and py < h - 1 - edge):
            keep[k] = False  # the image edge (its outer rows and columns) is within edge px
            continue
        r0 = max(int(np.ceil(py - radius)), 0)
        r1 = min(int(np.floor(py + radius)), h - 1)
        c0 = max(int(np.ceil(px - radius)), 0)
        c1 = min(int(np.floor(px + radius)), w - 1)
        if counts[r1 + 1, c1 + 1] - counts[r0, c1 + 1] - counts[r1 + 1, c0] + counts[r0, c0] == 0:
            continue
        for r in range(r0, r1 + 1):
            dy2 = (r - py) ** 2
            half = np.sqrt(max(r2 - dy2, 0.0))
            for c in range(max(int(np.ceil(px - half)), 0), min(int(np.floor(px + half)), w - 1) + 1):
                if bg[r, c]:
                    keep[k] = False
                    break
            if not keep[k]:
                break
    return keep
