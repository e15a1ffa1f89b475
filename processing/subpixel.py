"""Sub-pixel feature positions (beyond the seed, which stops at whole pixels: seed 6.1 and 7.2.2).

Pores: a bright blob on a dark ridge. Its position is the centre of mass of the grey-level *excess over the local
binarization threshold* in a small window, iterated so the window re-centres on the blob. Subtracting the threshold
removes the bias the seed's eq. 4.3 has when the blob sits on a brightness gradient (the plain grey-level centre of
a blob is pulled toward the brighter side of the window).

Minutiae: the skeleton's ending or fork depends on binarization and thinning; the refinement finds where the
valley (or the ridge between a fork's arms) actually ends in the grey image. See :func:`refine_minutiae`.
"""

from __future__ import annotations

import numba
import numpy as np

from processing.errors import InvalidInputError

__all__ = ["refine_pores", "refine_minutiae", "refine_bifurcations"]


@numba.njit(cache=True, nogil=True)
def _excess_centroids(img, thr, xs, ys, radius, iterations):  # pragma: no cover - compiled
    h, w = img.shape
    n = xs.size
    ox = xs.copy()
    oy = ys.copy()
    ok = np.ones(n, np.bool_)
    for k in range(n):
        r = int(np.ceil(radius[k]))
        r2 = radius[k] * radius[k]
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


def _check(image: np.ndarray, threshold: np.ndarray, x, y, radius_px):
    if image.ndim != 2 or threshold.shape != image.shape:
        raise InvalidInputError(f"image {image.shape} and threshold {threshold.shape} must be equal 2-D shapes")
    if not np.all(np.asarray(radius_px) > 0):
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
    radius_px,
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
    radius_px : float or (P,) float
        Disc radius per pore: a little more than the blob's radius, so that the window does not reach the
        neighbouring valleys (they are bright too and would pull the centre).
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
    radius = np.ascontiguousarray(np.broadcast_to(np.asarray(radius_px, dtype=np.float64), x.shape))
    return _excess_centroids(img, thr, x, y, radius, int(iterations))


@numba.njit(cache=True, nogil=True, inline="always")
def _bilinear(img, x, y):  # pragma: no cover - compiled
    h, w = img.shape
    if x < 0 or y < 0 or x > w - 1.001 or y > h - 1.001:
        return np.nan
    c = int(x)
    r = int(y)
    fx = x - c
    fy = y - r
    return (
        (1 - fy) * ((1 - fx) * img[r, c] + fx * img[r, c + 1])
        + fy * ((1 - fx) * img[r + 1, c] + fx * img[r + 1, c + 1])
    )


@numba.njit(cache=True, nogil=True)
def _apex(img, x0, y0, wx, wy, sign, t0, t_max, half, step):  # pragma: no cover - compiled
    """Apex of the region ``sign * img > 0`` in direction (wx, wy): for lateral offsets d in [-half, half], walk
    from (x0, y0) + t0 w + d v along w to the region's edge; the apex is the farthest edge point (parabola-refined
    across). Returns (x, y, found)."""
    vx = -wy
    vy = wx
    n_d = int(half / step)
    best_t = -1e9
    best_k = 0
    ts = np.full(2 * n_d + 1, np.nan)
    for kd in range(-n_d, n_d + 1):
        d = kd * step
        sx = x0 + t0 * wx + d * vx
        sy = y0 + t0 * wy + d * vy
        prev = sign * _bilinear(img, sx, sy)
        if not prev > 0:
            continue
        n_t = int((t_max - t0) / step)
        for k in range(1, n_t + 1):
            t = t0 + k * step
            v = sign * _bilinear(img, x0 + t * wx + d * vx, y0 + t * wy + d * vy)
            if not v == v:
                break
            if v <= 0:
                tc = t - step + step * prev / (prev - v)
                ts[kd + n_d] = tc
                if tc > best_t:
                    best_t = tc
                    best_k = kd
                break
            prev = v
    if best_t < -1e8:
        return x0, y0, False
    # Parabola through the best lateral sample and its neighbours, when both exist.
    d_best = best_k * step
    i = best_k + n_d
    if 0 < i < 2 * n_d and ts[i - 1] == ts[i - 1] and ts[i + 1] == ts[i + 1]:
        a = ts[i - 1]
        b = ts[i]
        c = ts[i + 1]
        den = a - 2 * b + c
        if den < 0:
            off = 0.5 * (a - c) / den
            if abs(off) <= 1:
                d_best += off * step
                best_t = b - 0.25 * (a - c) * off
    return x0 + best_t * wx + d_best * vx, y0 + best_t * wy + d_best * vy, True


@numba.njit(cache=True, nogil=True)
def _refine_minutiae(img, xs, ys, ux, uy, is_end, back, reach, half):  # pragma: no cover - compiled
    n = xs.size
    ox = xs.copy()
    oy = ys.copy()
    ok = np.zeros(n, np.bool_)
    step = 0.25
    for k in range(n):
        if is_end[k]:
            # The bright valley narrows to its tip: start inside the valley, walk toward the tip.
            x, y, found = _apex(img, xs[k], ys[k], ux[k], uy[k], 1.0, -back, reach, half, step)
        else:
            # The dark ridge between the fork's arms narrows to its tip: start inside that ridge, walk back
            # toward the fork.
            x, y, found = _apex(img, xs[k], ys[k], -ux[k], -uy[k], -1.0, -2.0 * reach, reach, half, step)
        if found:
            ox[k] = x
            oy[k] = y
            ok[k] = True
    return ox, oy, ok


def refine_minutiae(
    excess: np.ndarray,
    *,
    x: np.ndarray,
    y: np.ndarray,
    direction_deg: np.ndarray,
    is_ending: np.ndarray,
    reach_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel minutia positions where the valley (or ridge) actually ends in the grey image.

    The skeleton places an ending where thinning stopped eroding and a bifurcation where the thinned branches
    meet; both depend on the valley width and are off the true minutia by a few pixels. In the grey image a
    minutia is where the valley's bright centre line ends (ending) or where the dark ridge between the two
    arms of a fork ends (bifurcation). So:

    Near a minutia every iso-intensity line of the print runs into the minutia point (it is a phase
    singularity), so the valley's bright region (ending) or the ridge's dark region between the arms
    (bifurcation) is a wedge whose apex is the minutia. The refinement finds that apex: from inside the region,
    rays parallel to the minutia axis at lateral offsets every 1/4 px are walked (bilinear interpolation, 1/4 px
    steps) to the threshold crossing (``excess = 0``, linear interpolation); the farthest crossing is the apex,
    refined across by a parabola through its neighbours.

    Parameters
    ----------
    excess : (H, W) float32
        Smoothed frame minus the binarization threshold (positive on valleys and pores).
    x, y : (M,) float
        Skeleton positions.
    direction_deg : (M,) float
        Feature-table orientation (degrees, y up). Endings point into their valley; bifurcations bisect their
        smallest angle, i.e. point between the two arms toward the ridge that ends there.
    is_ending : (M,) bool
    reach_px : float
        How far along the axis (both ways) the crossing is searched.

    Returns
    -------
    x, y : (M,) float64
        Refined positions (unchanged where not refined).
    refined : (M,) bool
        False where the orientation is unknown or no crossing was found.
    """
    img, _, x, y = _check(excess, excess, x, y, reach_px)
    direction = np.asarray(direction_deg, dtype=np.float64)
    is_ending = np.asarray(is_ending, dtype=np.bool_)
    if direction.shape != x.shape or is_ending.shape != x.shape:
        raise InvalidInputError(f"direction_deg and is_ending must have the shape of x {x.shape}")
    known = np.isfinite(direction)
    a = np.radians(np.where(known, direction, 0.0))
    # Feature-table angles have y up; image rows go down.
    ux, uy = np.cos(a), -np.sin(a)
    # Endings point into their valley: the tip is the other way.
    ux = np.where(is_ending, -ux, ux)
    uy = np.where(is_ending, -uy, uy)
    back = max(reach_px / 3.0, 1.5)
    rx, ry, ok = _refine_minutiae(
        img, x, y, np.ascontiguousarray(ux), np.ascontiguousarray(uy), is_ending, back, float(reach_px), float(reach_px)
    )
    ok &= known
    rx = np.where(ok, rx, x)
    ry = np.where(ok, ry, y)
    return rx, ry, ok



def refine_bifurcations(
    image: np.ndarray,
    *,
    threshold: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    radius_px: float,
    iterations: int = 8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel valley bifurcations: a few mean-shift steps on the valley excess intensity from the skeleton fork.

    The centre of mass of ``max(image - threshold, 0)`` in a disc of ``radius_px`` (about half a ridge period)
    around the fork is recomputed ``iterations`` times. The bright mass of the three valleys meeting there pulls
    the point to the same place in every frame, which removes the pixel quantisation and thinning jitter of the
    skeleton fork (on flatL: frame-to-frame jitter 0.60 -> ~0.17 px, bias 3.8 -> ~1.3 px). More iterations let
    the point creep along the widest valley, so the count is kept small.
    """
    return refine_pores(image, threshold=threshold, x=x, y=y, radius_px=radius_px, iterations=iterations)
