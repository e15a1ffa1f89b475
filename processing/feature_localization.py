"""Sub-pixel feature positions (beyond the seed, which stops at whole pixels: seed 6.1 and 7.2.2).

Pores: a bright blob on a dark ridge. Its position is the centre of mass of the grey-level *excess over the local
binarization threshold* in a small window, iterated so the window re-centres on the blob. Subtracting the threshold
removes the bias the seed's eq. 4.3 has when the blob sits on a brightness gradient (the plain grey-level centre of
a blob is pulled toward the brighter side of the window).

Minutiae: the skeleton's ending or fork depends on binarization and thinning; the refinement finds the same
landmark from the grey image, where it moves smoothly with the print. A minutia is where the valleys' medial axis
(the ideal skeleton, seed 4.6) ends or forks: a valley ending at the centre of curvature of the valley's tip
(:func:`locate_minutiae_tips` finds the tip, :func:`tip_curvature_centres` its centre), a valley bifurcation at
the centre of the largest disc in the valleys' crotch (:func:`locate_forks`).
"""

from __future__ import annotations

import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit
from skinstretch.processing.ridge_flow import RidgeFlow, flow_normal_at

__all__ = ["refine_pores", "locate_pores_on_ridges", "locate_forks", "locate_minutiae_tips", "tip_curvature_centres"]


@njit(nogil=True)
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
    image, threshold : (H, W) float32
        The smoothed frame; the binarization threshold map (scaled local average).
    x, y : (P,) float
        Initial positions (pixels).
    radius_px : float or (P,) float
        Disc radius per pore: a little more than the blob's, short of the neighbouring (bright) valleys.
    iterations : int
        Re-centring iterations.

    Returns ``x, y`` ((P,) float64, unchanged where refinement failed) and ``refined`` ((P,) bool: False where there
    was no excess intensity, or the centre drifted out of the disc).

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


@njit(nogil=True, inline="always")
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


@njit(nogil=True)
def _ridge_pores(img, xs, ys, fc2, fs2, fcell, half_period, along, iterations):  # pragma: no cover - compiled
    """See :func:`locate_pores_on_ridges`."""
    n = xs.size
    ox = xs.copy()
    oy = ys.copy()
    ok = np.zeros(n, np.bool_)
    for k in range(n):
        c2, s2 = flow_normal_at(fc2, fs2, fcell, xs[k], ys[k])
        if c2 == 0 and s2 == 0:
            continue
        phi = 0.5 * np.arctan2(s2, c2)
        nx = np.cos(phi)
        ny = np.sin(phi)
        tx = -ny
        ty = nx
        cx = xs[k]
        cy = ys[k]
        good = True
        for _ in range(iterations):
            # Across: the dark ridge's centre on profiles along the normal, beside the pore on both sides.
            before = _across_peak(img, cx - along * tx, cy - along * ty, nx, ny, -1.0, half_period)
            after = _across_peak(img, cx + along * tx, cy + along * ty, nx, ny, -1.0, half_period)
            if not (before == before and after == after):
                good = False
                break
            cx += 0.5 * (before + after) * nx
            cy += 0.5 * (before + after) * ny
            # Along: the pore's bright excess on the ridge's centre line.
            shift = _across_peak(img, cx, cy, tx, ty, 1.0, along)
            if not shift == shift:
                good = False
                break
            cx += shift * tx
            cy += shift * ty
            if (cx - xs[k]) ** 2 + (cy - ys[k]) ** 2 > half_period * half_period:
                good = False
                break
        if good:
            ox[k] = cx
            oy[k] = cy
            ok[k] = True
    return ox, oy, ok


def locate_pores_on_ridges(
    excess: np.ndarray,
    *,
    x: np.ndarray,
    y: np.ndarray,
    flow: RidgeFlow,
    half_period_px: float,
    along_px: float,
    iterations: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel centres of pores that touch a valley, from the ridge they sit on.

    A pore opens on a ridge's centre line (FACTS). When it touches a valley its bright pixels join the valley's
    and no window around it holds the pore alone, so the two coordinates are taken where the valley cannot enter:

    1. across the ridge, the centre of mass of the ridge's darkness (``-excess`` > 0) on two profiles along the
       ridges' normal (``flow``), ``along_px`` before and after the pore along the ridge, within
       ``half_period_px``; the pore is put half-way between the two centres;
    2. along the ridge, the centre of mass of the pore's excess (> 0) on the centre line, within ``along_px``.

    Both are repeated ``iterations`` times. A pore whose profiles find no ridge, or that moves more than
    ``half_period_px``, is left where it was (``refined`` False).

    Parameters
    ----------
    excess : (H, W) float32
        The frame minus the binarization threshold (valleys and pores > 0).
    """
    img, _, x, y = _check(excess, excess, x, y, half_period_px)
    if not isinstance(flow, RidgeFlow):
        raise InvalidInputError(f"flow must be a RidgeFlow, got {type(flow).__name__}")
    if not (np.isfinite(along_px) and along_px > 0):
        raise InvalidInputError(f"along_px must be positive, got {along_px!r}")
    if not (isinstance(iterations, (int, np.integer)) and iterations >= 1):
        raise InvalidInputError(f"iterations must be a positive integer, got {iterations!r}")
    return _ridge_pores(img, x, y, flow.cos2, flow.sin2, flow.cell_px, float(half_period_px), float(along_px),
                        int(iterations))


@njit(nogil=True, inline="always")
def _nearest_sq(bx, by, nb, px, py, floor):  # pragma: no cover - compiled
    """Squared distance from (px, py) to the nearest of the ``nb`` points; any value <= ``floor`` once one is found
    that close (the caller only wants points farther than ``floor`` from all of them)."""
    best = np.inf
    for i in range(nb):
        dx = bx[i] - px
        dy = by[i] - py
        d = dx * dx + dy * dy
        if d < best:
            best = d
            if best <= floor:
                return best
    return best


@njit(nogil=True)
def _inscribed_centres(img, xs, ys, reach, half, slack):  # pragma: no cover - compiled
    """See :func:`locate_forks`: centre of the largest disc inside ``img > 0`` within ``reach`` of each start."""
    h, w = img.shape
    n = xs.size
    ox = xs.copy()
    oy = ys.copy()
    radius = np.full(n, np.nan)
    ok = np.zeros(n, np.bool_)
    side = 2 * half + 1
    cap = 2 * side * side
    bx = np.empty(cap)
    by = np.empty(cap)
    rr = int(np.ceil(reach))
    for k in range(n):
        ic = int(np.rint(xs[k]))
        ir = int(np.rint(ys[k]))
        # The region's outline: where the excess changes sign between two neighbouring pixels, interpolated.
        nb = _outline(img, ic, ir, half, bx, by)
        if nb == 0:
            continue
        # Whole pixels inside the region within reach, then two finer grids around the best.
        best = -1.0
        qx = 0.0
        qy = 0.0
        for r in range(max(ir - rr, 0), min(ir + rr, h - 1) + 1):
            for c in range(max(ic - rr, 0), min(ic + rr, w - 1) + 1):
                if (c - xs[k]) ** 2 + (r - ys[k]) ** 2 > reach * reach or not img[r, c] > 0:
                    continue
                d = _nearest_sq(bx, by, nb, c, r, best)
                if d > best:
                    best = d
                    qx = c
                    qy = r
        if best < 0:
            continue
        for step in (0.25, 0.0625):
            cx = qx
            cy = qy
            for j in range(-4, 5):
                for i in range(-4, 5):
                    px = cx + i * step
                    py = cy + j * step
                    if not _bilinear(img, px, py) > 0:
                        continue
                    d = _nearest_sq(bx, by, nb, px, py, best)
                    if d > best:
                        best = d
                        qx = px
                        qy = py
        # The centre of the places nearly as wide as the widest (within ``slack`` px of its radius), weighted by
        # how much: along a valley whose walls run parallel the widest place is a flat ridge of the distance, and
        # its arg max alone would jump along it with a grey level of noise.
        rmax = np.sqrt(best)
        lo = max(rmax - slack, 0.0)
        sw = 0.0
        sx = 0.0
        sy = 0.0
        m = int(np.ceil(2.0 * slack / 0.25))
        for j in range(-m, m + 1):
            for i in range(-m, m + 1):
                px = qx + i * 0.25
                py = qy + j * 0.25
                if not _bilinear(img, px, py) > 0:
                    continue
                d = np.sqrt(_nearest_sq(bx, by, nb, px, py, lo * lo))
                if d > lo:
                    sw += d - lo
                    sx += (d - lo) * px
                    sy += (d - lo) * py
        ox[k] = sx / sw if sw > 0 else qx
        oy[k] = sy / sw if sw > 0 else qy
        radius[k] = rmax
        ok[k] = True
    return ox, oy, radius, ok


def locate_forks(
    excess: np.ndarray,
    *,
    x: np.ndarray,
    y: np.ndarray,
    reach_px: float,
    max_radius_px: float,
    slack_px: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel valley bifurcations: the centre of the largest disc that fits in the valleys near the fork.

    Where three valleys meet, the widest place of the valley region is the crotch in front of the ridge that ends
    between two of them; its centre is where the medial axis (the ideal skeleton, seed 4.6) of the three valleys
    forks. The region's outline is the excess's zero crossing between neighbouring pixels (linear interpolation,
    so it moves smoothly with the image), and the centre is searched on whole pixels within ``reach_px`` of the
    skeleton's fork, then on grids of 1/4 and 1/16 px around the best. Unlike a mean shift of the valleys'
    brightness, it does not creep toward the brightest of the three valleys where partial contact dims the ridges
    around the fork unevenly.

    Parameters
    ----------
    excess : (H, W) float32
        The frame minus the binarization threshold (valleys > 0).
    x, y : (M,) float
        The skeleton's forks.
    reach_px, max_radius_px : float
        Search radius around each start; largest disc radius looked for (the outline within their sum is used).

    Returns ``x, y`` ((M,) float64, the centres; unchanged where none was found), ``radius`` ((M,) float64, NaN where
    none was found) and ``found`` ((M,) bool).
    """
    img, _, x, y = _check(excess, excess, x, y, reach_px)
    if not (np.isfinite(max_radius_px) and max_radius_px > 0):
        raise InvalidInputError(f"max_radius_px must be positive, got {max_radius_px!r}")
    half = int(np.ceil(reach_px + max_radius_px)) + 1
    return _inscribed_centres(img, x, y, float(reach_px), half, float(slack_px))


@njit(nogil=True)
def _outline(img, ic, ir, half, bx, by):  # pragma: no cover - compiled
    """Sub-pixel points of the outline of ``img > 0`` in the square of ``half`` around (ic, ir) into (bx, by):
    where the sign changes between two neighbouring pixels, linearly interpolated; their number."""
    h, w = img.shape
    r0 = max(ir - half, 0)
    r1 = min(ir + half, h - 1)
    c0 = max(ic - half, 0)
    c1 = min(ic + half, w - 1)
    nb = 0
    for r in range(r0, r1 + 1):
        for c in range(c0, c1):
            a = img[r, c]
            b = img[r, c + 1]
            if (a > 0) != (b > 0):
                bx[nb] = c + a / (a - b)
                by[nb] = r
                nb += 1
    for c in range(c0, c1 + 1):
        for r in range(r0, r1):
            a = img[r, c]
            b = img[r + 1, c]
            if (a > 0) != (b > 0):
                bx[nb] = c
                by[nb] = r + a / (a - b)
                nb += 1
    return nb


@njit(nogil=True)
def _across_peak(img, px, py, vx, vy, sign, half):  # pragma: no cover - compiled
    """Lateral offset (along v) of the centre of mass of ``max(sign * img, 0)`` sampled every 0.5 px within
    [-half, half] of (px, py); NaN when there is none. A centre of mass of the positive part moves smoothly with
    the image (a parabola through bilinear samples would be pulled toward pixel centres)."""
    n = int(half / 0.5)
    sw = 0.0
    sd = 0.0
    for k in range(-n, n + 1):
        v = sign * _bilinear(img, px + 0.5 * k * vx, py + 0.5 * k * vy)
        if not v == v:
            return np.nan
        if v > 0:
            sw += v
            sd += v * 0.5 * k
    if sw <= 0:
        return np.nan
    return sd / sw


#: Lateral weights of the tip profile at offsets -1, -0.5, 0, 0.5, 1 px (a binomial kernel).
_LAT_W = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16.0


@njit(nogil=True)
def _tips(img, xs, ys, ux, uy, sign, t0, t_max, half, n_centres, fit_px):  # pragma: no cover - compiled
    """See :func:`locate_minutiae_tips`. (ux, uy) points toward the tip; sign +1 follows a bright valley, -1 a
    dark ridge."""
    n = xs.size
    ox = xs.copy()
    oy = ys.copy()
    ok = np.zeros(n, np.bool_)
    ts = np.empty(n_centres)
    cs = np.empty(n_centres)
    for k in range(n):
        # 1. The region's centre line behind the tip: lateral centres every 1 px, fitted by a line. Two passes:
        # the second takes its profiles across the first pass's line, so a skeleton direction a few degrees off
        # no longer truncates the profiles asymmetrically.
        sx = xs[k] + t0 * ux[k]
        sy = ys[k] + t0 * uy[k]
        ax = ux[k]
        ay = uy[k]
        good = True
        for _pass in range(2):
            vx = -ay
            vy = ax
            m = 0
            for j in range(n_centres):
                c = _across_peak(img, sx - j * ax, sy - j * ay, vx, vy, sign, half)
                if c == c:
                    ts[m] = -j
                    cs[m] = c
                    m += 1
            if m < 2:
                good = False
                break
            mt = 0.0
            mc = 0.0
            for j in range(m):
                mt += ts[j]
                mc += cs[j]
            mt /= m
            mc /= m
            stt = 0.0
            stc = 0.0
            for j in range(m):
                stt += (ts[j] - mt) ** 2
                stc += (ts[j] - mt) * (cs[j] - mc)
            slope = stc / stt if stt > 0 else 0.0
            if abs(slope) > 1.0:  # more than 45 degrees off the skeleton's axis: not this minutia's valley
                good = False
                break
            # Refined axis: direction a + slope v, through the fitted centre at the start point.
            c0 = mc - slope * mt
            sx += c0 * vx
            sy += c0 * vy
            ax += slope * vx
            ay += slope * vy
            norm = np.sqrt(ax * ax + ay * ay)
            ax /= norm
            ay /= norm
        if not good:
            continue
        bx = -ay
        by = ax
        # 2. Walk the centre line toward the tip; the tip is where the laterally averaged excess crosses zero
        # (the local mean, seed 4.2). The crossing is then re-estimated by a least-squares line through the
        # profile within +-fit_px of it, which averages the noise of ~8 samples instead of interpolating two.
        step = 0.25
        n_t = int((t_max - t0) / step) + int(fit_px / step) + 1
        n_back = int(fit_px / step)
        prof = np.empty(n_back + n_t + 1)
        for i in range(-n_back, n_t + 1):
            t = i * step
            qx = sx + t * ax
            qy = sy + t * ay
            v = 0.0
            for j in range(-2, 3):
                v += _LAT_W[j + 2] * _bilinear(img, qx + 0.5 * j * bx, qy + 0.5 * j * by)
            prof[i + n_back] = sign * v
        if not prof[n_back] > 0:
            continue
        i_c = -1
        for i in range(n_back + 1, n_back + n_t + 1):
            v = prof[i]
            if not v == v:
                break
            if v <= 0:
                i_c = i
                break
        if i_c < 0:
            continue
        if i_c + n_back >= prof.size or not prof[i_c + n_back] == prof[i_c + n_back]:
            tc = (i_c - n_back - 1) * step + step * prof[i_c - 1] / (prof[i_c - 1] - prof[i_c])
        else:
            # Least-squares line v = p + q t over the samples around the crossing; tc = -p / q.
            st = 0.0
            sv = 0.0
            stt = 0.0
            stv = 0.0
            m = 0
            for i in range(i_c - n_back, i_c + n_back):
                t = (i - n_back) * step
                st += t
                sv += prof[i]
                stt += t * t
                stv += t * prof[i]
                m += 1
            den = m * stt - st * st
            q = (m * stv - st * sv) / den
            if not q < 0:
                continue
            pp = (sv - q * st) / m
            tc = -pp / q
        ox[k] = sx + tc * ax
        oy[k] = sy + tc * ay
        ok[k] = True
    return ox, oy, ok


def locate_minutiae_tips(
    excess: np.ndarray,
    *,
    x: np.ndarray,
    y: np.ndarray,
    direction_deg: np.ndarray,
    is_ending: np.ndarray,
    reach_px: float,
    half_width_px: float = 6.0,
    n_centres: int = 15,
    iterations: int = 2,
    back_px: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel minutiae from the grey-level profile along and across their valley (or ridge), not the skeleton.

    A valley ending is where the valley's bright centre line falls to the local mean; a bifurcation is where the dark
    ridge between its two arms does (sign flipped, axis reversed): smooth functions of the image, which move with the
    print instead of jumping with the skeleton's pixels. Across the axis, ``n_centres`` lateral profiles (1 px apart,
    ``half_width_px`` wide) give centres of mass and a least-squares centre line; along it the tip is the excess's zero
    crossing, searched from behind the skeleton position to ``reach_px`` beyond it; ``iterations`` passes, each from
    the previous tip. :func:`tip_curvature_centres` moves a valley ending from its tip to the skeleton's end.

    ``excess``: smoothed frame minus the binarization threshold; ``x, y``: skeleton positions; ``direction_deg``:
    feature-table orientation (NaN: left as is); ``is_ending``. Returns ``x, y`` (float64, unchanged where not refined)
    and ``refined`` (False where the orientation is unknown, no centre line or no crossing was found).

    Examples
    --------
    >>> import numpy as np
    >>> yy, xx = np.mgrid[0:40, 0:60].astype(np.float32)
    >>> valley = np.exp(-((yy - 20.3) ** 2) / 4.0) * (xx <= 30)  # a bright valley: last pixel 30, then ridge
    >>> img = (valley - 0.5).astype(np.float32)
    >>> rx, ry, ok = locate_minutiae_tips(img, x=np.array([29.0]), y=np.array([20.0]), direction_deg=np.array([180.0]),
    ...                                   is_ending=np.array([True]), reach_px=6.0)
    >>> round(float(rx[0]), 1), round(float(ry[0]), 1), bool(ok[0])
    (30.4, 20.3, True)
    """
    img, _, x, y = _check(excess, excess, x, y, reach_px)
    direction = np.asarray(direction_deg, dtype=np.float64)
    is_ending = np.asarray(is_ending, dtype=np.bool_)
    if direction.shape != x.shape or is_ending.shape != x.shape:
        raise InvalidInputError(f"direction_deg and is_ending must have the shape of x {x.shape}")
    if not (np.isfinite(half_width_px) and half_width_px >= 1.0):
        raise InvalidInputError(f"half_width_px must be at least 1 px, got {half_width_px!r}")
    if not (isinstance(n_centres, (int, np.integer)) and n_centres >= 2):
        raise InvalidInputError(f"n_centres must be an integer >= 2, got {n_centres!r}")
    if not (isinstance(iterations, (int, np.integer)) and iterations >= 1):
        raise InvalidInputError(f"iterations must be a positive integer, got {iterations!r}")
    known = np.isfinite(direction)
    a = np.radians(np.where(known, direction, 0.0))
    # Feature-table angles have y up; image rows go down. Endings point into their valley: the tip is the other
    # way; bifurcations point into the ridge between the arms: the fork is the other way too.
    ux = np.ascontiguousarray(-np.cos(a))
    uy = np.ascontiguousarray(np.sin(a))
    rx, ry, ok = x.copy(), y.copy(), np.zeros(x.shape, dtype=bool)
    back = max(reach_px / 3.0, 1.5) if back_px is None else float(back_px)
    for sel, sign, t0 in ((is_ending, 1.0, -back), (~is_ending, -1.0, -reach_px)):
        idx = np.flatnonzero(sel & known)
        if idx.size == 0:
            continue
        sx, sy = x[idx], y[idx]
        found = np.zeros(idx.size, dtype=bool)
        for it in range(iterations):
            ox, oy, o = _tips(img, sx, sy, ux[idx], uy[idx], sign, float(t0), float(reach_px), float(half_width_px),
                              int(n_centres), 1.5)
            if it == 0 and not o.all():
                # The start (t0 behind the skeleton position) may already lie past the crossing: a faint valley
                # whose smoothed excess reaches zero before the skeleton ends. Those start reach_px further back,
                # so that the same crossing is found in every frame instead of none in some.
                r = np.flatnonzero(~o)
                rx2, ry2, o2 = _tips(img, sx[r], sy[r], ux[idx][r], uy[idx][r], sign, float(t0 - reach_px),
                                     float(reach_px), float(half_width_px), int(n_centres), 1.5)
                ox[r], oy[r], o[r] = rx2, ry2, o2
            sx, sy = np.where(o, ox, sx), np.where(o, oy, sy)
            found |= o
        rx[idx], ry[idx], ok[idx] = sx, sy, found
    rx = np.where(ok, rx, x)
    ry = np.where(ok, ry, y)
    return rx, ry, ok


@njit(nogil=True)
def _curvature_centres(img, xs, ys, sigma, max_radius):  # pragma: no cover - compiled
    """See :func:`tip_curvature_centres`."""
    h, w = img.shape
    n = xs.size
    ox = xs.copy()
    oy = ys.copy()
    radius = np.full(n, np.nan)
    ok = np.zeros(n, np.bool_)
    half = int(np.ceil(3.0 * sigma))
    s2 = sigma * sigma
    wx = np.empty(2 * half + 1)
    wy = np.empty(2 * half + 1)
    for k in range(n):
        x = xs[k]
        y = ys[k]
        ic = int(np.rint(x))
        ir = int(np.rint(y))
        if ic - half < 0 or ir - half < 0 or ic + half > w - 1 or ir + half > h - 1:
            continue
        # Derivatives at the sub-pixel point from a quadratic fitted to the pixels within 3 sigma, weighted by a
        # Gaussian of ``sigma`` centred there (exact for a quadratic, whatever the point's sub-pixel phase).
        ata = np.zeros((6, 6))
        atv = np.zeros(6)
        basis = np.empty(6)
        for i in range(2 * half + 1):  # the Gaussian is separable: one exp per row and per column
            wy[i] = np.exp(-((ir - half + i - y) ** 2) / (2.0 * s2))
            wx[i] = np.exp(-((ic - half + i - x) ** 2) / (2.0 * s2))
        for r in range(ir - half, ir + half + 1):
            dy = r - y
            gr = wy[r - ir + half]
            for c in range(ic - half, ic + half + 1):
                dx = c - x
                g = gr * wx[c - ic + half]
                basis[0] = 1.0
                basis[1] = dx
                basis[2] = dy
                basis[3] = 0.5 * dx * dx
                basis[4] = dx * dy
                basis[5] = 0.5 * dy * dy
                v = img[r, c]
                for i in range(6):
                    gb = g * basis[i]
                    atv[i] += gb * v
                    for j in range(i, 6):
                        ata[i, j] += gb * basis[j]
        for i in range(6):
            for j in range(i):
                ata[i, j] = ata[j, i]
        coef = np.linalg.solve(ata, atv)
        gx = coef[1]
        gy = coef[2]
        gxx = coef[3]
        gxy = coef[4]
        gyy = coef[5]
        g2 = gx * gx + gy * gy
        if not g2 > 0:
            continue
        gn = np.sqrt(g2)
        # Curvature of the isophote through (x, y), positive where the bright side is convex (a valley's tip).
        kappa = -(gxx * gy * gy - 2.0 * gxy * gx * gy + gyy * gx * gx) / (g2 * gn)
        if not kappa * max_radius > 1.0:
            continue
        rad = 1.0 / kappa
        ox[k] = x + rad * gx / gn
        oy[k] = y + rad * gy / gn
        radius[k] = rad
        ok[k] = True
    return ox, oy, radius, ok


def tip_curvature_centres(
    excess: np.ndarray,
    *,
    x: np.ndarray,
    y: np.ndarray,
    sigma_px: float,
    max_radius_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Valley endings at the centre of curvature of the valley's outline at its tip.

    The medial axis of a region (its ideal skeleton, seed 4.6) ends at the centre of the circle osculating the outline
    where it is most curved: a round tip of radius r ends the skeleton r behind the tip. The tip
    (:func:`locate_minutiae_tips`) lies on the isophote through it; its curvature comes from a quadratic fitted to
    ``excess`` around the point (Gaussian weights of ``sigma_px``), and the centre is ``1 / kappa`` from the tip along
    the gradient, into the valley. A flatter outline than ``max_radius_px`` (or concave), or a point within
    ``3 sigma_px`` of the image edge, is left as is.

    Returns ``x, y`` (float64, the centres; unchanged where none was found), ``radius`` (NaN where none) and ``found``.

    Examples
    --------
    >>> import numpy as np
    >>> yy, xx = np.mgrid[0:60, 0:60].astype(np.float32)
    >>> dome = np.exp(-((xx - 30.0) ** 2 + (yy - 28.5) ** 2) / 32.0).astype(np.float32) - 0.5  # circular isophotes
    >>> cx, cy, r, ok = tip_curvature_centres(dome, x=np.array([34.71]), y=np.array([28.5]), sigma_px=1.5,
    ...                                       max_radius_px=10.0)
    >>> round(float(cx[0]), 1), round(float(cy[0]), 1), round(float(r[0]), 1), bool(ok[0])
    (30.0, 28.5, 4.7, True)
    """
    img, _, x, y = _check(excess, excess, x, y, max_radius_px)
    if not np.isfinite(max_radius_px):
        raise InvalidInputError(f"max_radius_px must be a positive number, got {max_radius_px!r}")
    if not (np.isfinite(sigma_px) and sigma_px >= 0.5):
        raise InvalidInputError(f"sigma_px must be at least 0.5 px, got {sigma_px!r}")
    return _curvature_centres(img, x, y, float(sigma_px), float(max_radius_px))
