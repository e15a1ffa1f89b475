"""Blob-based pore detection (seed 4.5).

Any 4-connected blob of the binary (valley/pore) image smaller than ~0.25 mm across is a pore. Its position is the
grey-level centre of mass of its pixels (seed eq. 4.3); the blob is then removed from the binary image so that
thinning only sees valleys (the seed reduces it to one pixel at its centre, which thinning would classify as a pore
again; keeping the pores in a list is equivalent and keeps their sub-pixel positions).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from processing.errors import InvalidInputError

__all__ = ["BlobPores", "detect_blob_pores"]


@dataclass(frozen=True)
class BlobPores:
    """Pores found as small blobs.

    Attributes
    ----------
    x, y : (P,) float64
        Grey-level centre of mass (seed eq. 4.3), pixels.
    diameter_px : (P,) float64
        Largest bounding-box side of the blob, pixels.
    area_px : (P,) int64
        Number of pixels of the blob.
    binary_without_pores : (H, W) uint8
        The binary image with the pore blobs removed (what thinning receives).
    """

    x: np.ndarray
    y: np.ndarray
    diameter_px: np.ndarray
    area_px: np.ndarray
    binary_without_pores: np.ndarray


@numba.njit(cache=True, nogil=True)
def _blob_moments(labels, weights, is_pore, remove, out):  # pragma: no cover - compiled
    """Weighted moments of the pore blobs, and ``out`` (a copy of the binary image) cleared on removed blobs."""
    n_labels = is_pore.size
    sw = np.zeros(n_labels)
    sx = np.zeros(n_labels)
    sy = np.zeros(n_labels)
    h, w = labels.shape
    for r in range(h):
        for c in range(w):
            lab = labels[r, c]
            if lab > 0 and remove[lab]:
                out[r, c] = 0
                if is_pore[lab]:
                    v = weights[r, c]
                    sw[lab] += v
                    sx[lab] += v * c
                    sy[lab] += v * r
    return sw, sx, sy


def detect_blob_pores(
    binary: np.ndarray,
    *,
    grey: np.ndarray,
    max_diameter_px: float,
    min_area_px: int = 1,
) -> BlobPores:
    """Find the pores of seed 4.5 in a binary valley/pore image.

    Parameters
    ----------
    binary : (H, W) uint8
        Foreground (valleys and pores) = non-zero.
    grey : (H, W) float32 or uint8
        Grey-level weights of eq. 4.3 (the seed uses the foreground grey image; the smoothed frame minus the
        binarization threshold gives a less biased centre, see :mod:`processing.subpixel`).
    max_diameter_px : float
        A blob is a pore when its bounding box is narrower than this on both axes (seed: 0.25 mm).
    min_area_px : int
        Blobs smaller than this are noise and are dropped (removed from the binary image, not reported).

    Returns
    -------
    BlobPores

    Examples
    --------
    >>> import numpy as np
    >>> b = np.zeros((20, 20), np.uint8); b[5:8, 10:13] = 255
    >>> p = detect_blob_pores(b, grey=b.astype(np.float32), max_diameter_px=5)
    >>> (float(p.x[0]), float(p.y[0]))
    (11.0, 6.0)
    """
    if binary.ndim != 2 or binary.dtype != np.uint8:
        raise InvalidInputError(f"binary must be a 2-D uint8 image, got {binary.dtype} {binary.shape}")
    if grey.shape != binary.shape:
        raise InvalidInputError(f"grey shape {grey.shape} differs from binary shape {binary.shape}")
    if not max_diameter_px > 0:
        raise InvalidInputError(f"max_diameter_px must be positive, got {max_diameter_px!r}")
    _, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=4, ltype=cv2.CV_32S)
    wh = np.maximum(stats[:, cv2.CC_STAT_WIDTH], stats[:, cv2.CC_STAT_HEIGHT])
    area = stats[:, cv2.CC_STAT_AREA]
    small = wh < max_diameter_px
    small[0] = False
    noise = small & (area < min_area_px)
    is_pore = small & ~noise
    weights = grey.astype(np.float32, copy=False)
    without = binary.copy()
    sw, sx, sy = _blob_moments(labels, weights, is_pore, small, without)
    idx = np.flatnonzero(is_pore)
    sw_p = sw[idx]
    good = sw_p > 0
    # A pore whose weights sum to zero has no defined centre: fall back to its bounding-box centre.
    bx = stats[idx, cv2.CC_STAT_LEFT] + (stats[idx, cv2.CC_STAT_WIDTH] - 1) / 2.0
    by = stats[idx, cv2.CC_STAT_TOP] + (stats[idx, cv2.CC_STAT_HEIGHT] - 1) / 2.0
    safe = np.where(good, sw_p, 1.0)
    x = np.where(good, sx[idx] / safe, bx)
    y = np.where(good, sy[idx] / safe, by)
    return BlobPores(
        x=x.astype(np.float64),
        y=y.astype(np.float64),
        diameter_px=wh[idx].astype(np.float64),
        area_px=area[idx].astype(np.int64),
        binary_without_pores=without,
    )
