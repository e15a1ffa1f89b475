"""Blob-based pore detection (seed 4.5).

Any 4-connected blob of the binary (valley/pore) image smaller than ~0.25 mm across is a pore. Its position is the
grey-level centre of mass of its pixels (seed eq. 4.3); the blob is then removed from the binary image so that
thinning only sees valleys (the seed reduces it to one pixel at its centre, which thinning would classify as a pore
again; keeping the pores in a list is equivalent and keeps their sub-pixel positions).

Hand-written labelling (:func:`_small_blobs`) rather than ``cv2.connectedComponentsWithStats``: one compiled pass
labels, measures, weighs and erases the small blobs, where OpenCV's labels would need three more full-image passes
(grey moments, the size test, the erasing) for the same result.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit

__all__ = ["BlobPores", "detect_blob_pores", "fill_specks"]


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


@njit(nogil=True, inline="always")
def _root(parent, i):  # pragma: no cover - compiled
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(nogil=True)
def _small_blobs(binary, weights, max_diameter, min_area):  # pragma: no cover - compiled
    """4-connected blobs of ``binary`` narrower than ``max_diameter`` (bounding box, both axes): removed from a copy
    of the image; those of at least ``min_area`` pixels reported with their weighted centre of mass.

    Run-based labelling: the horizontal runs of each row are joined (union-find, the lower run index is the root)
    to the runs of the row above that share a column. Blobs come out in the raster order of their first pixel (the
    order of cv2.connectedComponents' labels) and their moments are summed in raster order.
    """
    h, w = binary.shape
    # At most (w + 1) // 2 runs per row; allocated once (arrays re-bound inside the loops would cost reference
    # counting on every iteration).
    cap = h * ((w + 1) // 2)
    run_r = np.empty(cap, np.int32)
    run_a = np.empty(cap, np.int32)
    run_b = np.empty(cap, np.int32)  # exclusive end
    parent = np.empty(cap, np.int64)
    n = 0
    prev_lo = 0
    prev_hi = 0
    for r in range(h):
        row_lo = n
        c = 0
        k = prev_lo
        while c < w:
            if binary[r, c] == 0:
                c += 1
                continue
            a = c
            while c < w and binary[r, c] != 0:
                c += 1
            run_r[n] = r
            run_a[n] = a
            run_b[n] = c
            parent[n] = n
            # Runs of the row above overlapping [a, c): skip those ending before a, join those starting before c.
            while k < prev_hi and run_b[k] <= a:
                k += 1
            kk = k
            while kk < prev_hi and run_a[kk] < c:
                ra = _root(parent, kk)
                rb = _root(parent, n)
                if ra < rb:
                    parent[rb] = ra
                elif rb < ra:
                    parent[ra] = rb
                kk += 1
            if kk > k:
                k = kk - 1  # the last overlapping run may also touch the next run of this row
            n += 1
        prev_lo = row_lo
        prev_hi = n
    # Bounding box and area per root (a root is its blob's first run, so its row is the top row).
    rmax = np.empty(n, np.int32)
    cmin = np.empty(n, np.int32)
    cmax = np.empty(n, np.int32)
    area = np.zeros(n, np.int64)
    root = np.empty(n, np.int64)
    for i in range(n):
        q = _root(parent, i)
        root[i] = q
        if q == i:
            rmax[i] = run_r[i]
            cmin[i] = run_a[i]
            cmax[i] = run_b[i] - 1
        else:
            rmax[q] = run_r[i]
            cmin[q] = min(cmin[q], run_a[i])
            cmax[q] = max(cmax[q], run_b[i] - 1)
        area[q] += run_b[i] - run_a[i]
    out = binary.copy()
    sw = np.zeros(n)
    sx = np.zeros(n)
    sy = np.zeros(n)
    n_res = 0
    for i in range(n):
        q = root[i]
        wh = max(rmax[q] - run_r[q] + 1, cmax[q] - cmin[q] + 1)
        if wh >= max_diameter:
            continue
        r = run_r[i]
        keep = area[q] >= min_area
        for c in range(run_a[i], run_b[i]):
            out[r, c] = 0
            if keep:
                v = weights[r, c]
                sw[q] += v
                sx[q] += v * c
                sy[q] += v * r
        if keep and q == i:
            n_res += 1
    res_x = np.empty(n_res)
    res_y = np.empty(n_res)
    res_d = np.empty(n_res)
    res_a = np.empty(n_res, np.int64)
    k = 0
    for q in range(n):
        if root[q] != q or area[q] < min_area:
            continue
        wh = max(rmax[q] - run_r[q] + 1, cmax[q] - cmin[q] + 1)
        if wh >= max_diameter:
            continue
        if sw[q] > 0:
            res_x[k] = sx[q] / sw[q]
            res_y[k] = sy[q] / sw[q]
        else:
            # Weights summing to zero leave no defined centre: the bounding-box centre.
            res_x[k] = cmin[q] + (cmax[q] - cmin[q]) / 2.0
            res_y[k] = run_r[q] + (rmax[q] - run_r[q]) / 2.0
        res_d[k] = wh
        res_a[k] = area[q]
        k += 1
    return res_x, res_y, res_d, res_a, out


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
        binarization threshold gives a less biased centre, see :mod:`skinstretch.processing.feature_localization`).
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
    weights = np.ascontiguousarray(grey, dtype=np.float32)
    x, y, diameter, area, without = _small_blobs(
        np.ascontiguousarray(binary), weights, float(max_diameter_px), int(min_area_px)
    )
    return BlobPores(x=x, y=y, diameter_px=diameter, area_px=area, binary_without_pores=without)


def fill_specks(binary: np.ndarray, *, max_diameter_px: float) -> np.ndarray:
    """``binary`` with its 4-connected background (0) blobs narrower than ``max_diameter_px`` filled (255).

    The dark counterpart of the noise blobs :func:`detect_blob_pores` drops: a speck of a few pixels inside a valley.
    """
    if binary.ndim != 2 or binary.dtype != np.uint8:
        raise InvalidInputError(f"binary must be a 2-D uint8 image, got {binary.dtype} {binary.shape}")
    if not max_diameter_px > 0:
        raise InvalidInputError(f"max_diameter_px must be positive, got {max_diameter_px!r}")
    inverse = cv2.bitwise_not(binary)
    # No blob is reported (the minimum area is never reached), so the weights are never read.
    unread = np.empty(binary.shape, np.float32)
    _, _, _, _, without = _small_blobs(inverse, unread, float(max_diameter_px), np.iinfo(np.int64).max)
    return cv2.bitwise_not(without)
