"""Sub-pixel feature positions (beyond the seed, which stops at whole pixels: seed 6.1 and 7.2.2).

Pores: a bright blob on a dark ridge. Its position is the centre of mass of the grey-level *excess over the local
binarization threshold* in a small window, iterated so the window re-centres on the blob. Subtracting the threshold
removes the bias the seed's eq. 4.3 has when the blob sits on a brightness gradient (the plain grey-level centre of
a blob is pulled toward the brighter side of the window).

Minutiae: a valley ending or bifurcation is located on the skeleton, whose position depends on binarization and
thinning. The refinement moves it to the centre of mass of the valley excess intensity in a small disc around it
(the valley's medial axis across; along the valley the disc is symmetric only at its tip), which removes the
pixel quantisation and most of the thinning jitter. See :func:`refine_minutiae`.
"""

from __future__ import annotations

import numba
import numpy as np

from processing.errors import InvalidInputError

__all__ = ["refine_pores", "refine_minutiae"]


@numba.njit(cache=True, nogil=True)
def _excess_centroids(img, thr, xs, ys, radius, iterations):  # pragma: no cover - compiled
    h, w = img.shape
    n = xs.size
    ox = xs.copy()
    oy = ys.copy()
    ok = np.ones(n, np.bool_)
    r = int(np.ceil(radius))
    r2 = radius * radius
    for k in range(n):
        cx = xs[k]
        cy = ys[k]
        for _ in range(iterations):
            ic = int(np.rint(cx))
            ir = int(np.rint(cy))
            sw = 0.0
            sx = 0.0
            sy = 0.0
            for rr in range(max(ir - r, 0), min(ir + r + 1, h)):
                for cc in range(max(ic - r, 0), min(ic + r + 1, w)):
                    dx = cc - cx
                    dy = rr - cy
                    if dx * dx + dy * dy > r2:
                        continue
                    v = img[rr, cc] - thr[rr, cc]
                    if v > 0:
                        sw += v
                        sx += v * cc
                        sy += v * rr
            if sw <= 0:
                ok[k] = False
                break
            nx = sx / sw
            ny = sy / sw
            # Never wander further than the window radius from the detected position.
            if (nx - xs[k]) ** 2 + (ny - ys[k]) ** 2 > r2:
                ok[k] = False
                break
            cx = nx
            cy = ny
        if ok[k]:
            ox[k] = cx
            oy[k] = cy
    return ox, oy, ok


def _check(image: np.ndarray, threshold: np.ndarray, x, y, radius_px: float):
    if image.ndim != 2 or threshold.shape != image.shape:
        raise InvalidInputError(f"image {image.shape} and threshold {threshold.shape} must be equal 2-D shapes")
    if not radius_px > 0:
        raise InvalidInputError(f"radius_px must be positive, got {radius_px!r}")
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise InvalidInputError(f"x and y must be 1-D arrays of equal length, got {x.shape} and {y.shape}")
    return image.astype(np.float32, copy=False), threshold.astype(np.float32, copy=False), x, y


def refine_pores(
    image: np.ndarray,
    *,
    threshold: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    radius_px: float,
    iterations: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel pore centres: centre of mass of ``max(image - threshold, 0)`` in a disc of ``radius_px``.

    Parameters
    ----------
    image : (H, W) float32
        The smoothed frame.
    threshold : (H, W) float32
        The binarization threshold map (scaled local average).
    x, y : (P,) float
        Initial positions (pixels).
    radius_px : float
        Disc radius, about half the largest pore diameter.
    iterations : int
        Re-centring iterations.

    Returns
    -------
    x, y : (P,) float64
        Refined positions; unchanged where refinement failed.
    refined : (P,) bool
        Whether each position was refined (False: no excess intensity, or the centre drifted out of the disc).

    Examples
    --------
    >>> import numpy as np
    >>> yy, xx = np.mgrid[0:21, 0:21]
    >>> img = (100 * np.exp(-((xx - 10.3) ** 2 + (yy - 9.6) ** 2) / 4.0)).astype(np.float32)
    >>> rx, ry, ok = refine_pores(img, threshold=np.full_like(img, 5.0), x=np.array([10.0]), y=np.array([10.0]),
    ...                           radius_px=5)
    >>> round(float(rx[0]), 1), round(float(ry[0]), 1), bool(ok[0])
    (10.3, 9.6, True)
    """
    img, thr, x, y = _check(image, threshold, x, y, radius_px)
    if not (isinstance(iterations, (int, np.integer)) and iterations >= 1):
        raise InvalidInputError(f"iterations must be a positive integer, got {iterations!r}")
    return _excess_centroids(img, thr, x, y, float(radius_px), int(iterations))


def refine_minutiae(
    image: np.ndarray,
    *,
    threshold: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    radius_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel minutia positions: one-step centre of mass of the valley excess intensity in a disc.

    A single step (no re-centring) so the point stays at the minutia instead of sliding down the valley; see the
    module docstring. Returns refined x, y and a mask of the refined entries (the others are unchanged).
    """
    img, thr, x, y = _check(image, threshold, x, y, radius_px)
    return _excess_centroids(img, thr, x, y, float(radius_px), 1)
