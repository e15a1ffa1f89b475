"""2-D Delaunay triangulation, compiled: the sweep-hull algorithm of mapbox/delaunator (v5), ported to numba.

The strain stage triangulates the matched features of every frame pair (seed 5.3.1): ~350 triangulations of
~250 points for a 180-frame session at spans 1 and 11. ``scipy.spatial.Delaunay`` (Qhull) takes ~0.4 ms each and
holds the GIL; this takes ~0.05 ms, with the same triangles for points in general position (tested against
Qhull). Orientation tests use Shewchuk's error bound with an exact fallback, so the hull is built from exact
signs; the in-circle test is the plain floating-point one, as in delaunator.

delaunator is (c) Vladimir Agafonkin and contributors, ISC licence: permission to use, copy, modify and/or
distribute with or without fee, provided the copyright notice and this permission notice appear in all copies.
THE SOFTWARE IS PROVIDED "AS IS" AND THE AUTHOR DISCLAIMS ALL WARRANTIES.
"""

from __future__ import annotations

import math

import numpy as np

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.jit import njit

__all__ = ["delaunay_triangles", "triangulate_points"]

_EPSILON = 2.0**-52
_SPLITTER = 134217729.0  # 2^27 + 1
_CCW_ERRBOUND_A = (3.0 + 16.0 * _EPSILON) * _EPSILON


def delaunay_triangles(points: np.ndarray) -> np.ndarray:
    """Triangles (k, 3) int64 of the Delaunay triangulation of ``points`` (n, 2), as indices into ``points``.

    Points must be finite and distinct (an exact duplicate is skipped, as if absent).

    Raises
    ------
    InsufficientDataError
        Fewer than 3 points, or all of them on one line (no triangle).

    Examples
    --------
    >>> import numpy as np
    >>> t = delaunay_triangles(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.1]]))
    >>> sorted(sorted(r) for r in t.tolist())
    [[0, 1, 2], [1, 2, 3]]
    """
    p = np.ascontiguousarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise InvalidInputError(f"points must have shape (n, 2), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InvalidInputError("points must be finite")
    if p.shape[0] < 3:
        raise InsufficientDataError(f"{p.shape[0]} points, need at least 3 to triangulate")
    tri = triangulate_points(p)
    if tri.shape[0] == 0:
        raise InsufficientDataError(f"the {p.shape[0]} points are collinear: no triangle")
    return tri


def triangulate_points(points: np.ndarray) -> np.ndarray:
    """:func:`delaunay_triangles` without its checks, for callers whose (n, 2) float64 points are known finite and
    distinct: (0, 3) when there is no triangle (collinear, fewer than 3 points)."""
    if points.shape[0] < 3:
        return np.zeros((0, 3), np.int64)
    return _triangulate(np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1]))


# -- exact orientation -------------------------------------------------------------------------------------------


@njit(nogil=True, inline="always")
def _two_product(a, b):  # pragma: no cover - compiled
    x = a * b
    c = _SPLITTER * a
    ahi = c - (c - a)
    alo = a - ahi
    c = _SPLITTER * b
    bhi = c - (c - b)
    blo = b - bhi
    y = alo * blo - (((x - ahi * bhi) - alo * bhi) - ahi * blo)
    return x, y


@njit(nogil=True)
def _orient_exact(ax, ay, bx, by, cx, cy):  # pragma: no cover - compiled
    """Sign of ax*by - ay*bx + ay*cx - ax*cy + bx*cy - by*cx, exactly: the six products as two-term expansions,
    summed into a non-overlapping expansion (Shewchuk's grow-expansion); its largest term has the sign."""
    terms = np.empty(12)
    terms[0], terms[1] = _two_product(ax, by)
    terms[2], terms[3] = _two_product(-ay, bx)
    terms[4], terms[5] = _two_product(ay, cx)
    terms[6], terms[7] = _two_product(-ax, cy)
    terms[8], terms[9] = _two_product(bx, cy)
    terms[10], terms[11] = _two_product(-by, cx)
    e = np.zeros(13)
    m = 0
    for t in range(12):
        q = terms[t]
        k = 0
        for i in range(m):  # grow-expansion: add q to e[0..m), keeping every partial error term
            s = q + e[i]
            bv = s - q
            err = (q - (s - bv)) + (e[i] - bv)
            q = s
            if err != 0.0:
                e[k] = err
                k += 1
        e[k] = q
        m = k + 1
    for i in range(m - 1, -1, -1):
        if e[i] != 0.0:
            return e[i]
    return 0.0


@njit(nogil=True, inline="always")
def _orient(ax, ay, bx, by, cx, cy):  # pragma: no cover - compiled
    """Positive when c is to the left... delaunator's orient2d sign convention (robust-predicates' orient2d):
    (ay - cy) (bx - cx) - (ax - cx) (by - cy)."""
    detleft = (ay - cy) * (bx - cx)
    detright = (ax - cx) * (by - cy)
    det = detleft - detright
    bound = _CCW_ERRBOUND_A * abs(detleft + detright)
    if abs(det) >= bound and det != 0.0:
        return det
    # (ay-cy)(bx-cx) - (ax-cx)(by-cy) = -(ax*by - ay*bx + ay*cx - ax*cy + bx*cy - by*cx)
    return -_orient_exact(ax, ay, bx, by, cx, cy)


# -- delaunator --------------------------------------------------------------------------------------------------


@njit(nogil=True, inline="always")
def _pseudo_angle(dx, dy):  # pragma: no cover - compiled
    d = abs(dx) + abs(dy)
    if d == 0.0:
        return 0.25
    p = dx / d
    return (3.0 - p if dy > 0 else 1.0 + p) / 4.0


@njit(nogil=True, inline="always")
def _hash_key(x, y, cx, cy, size):  # pragma: no cover - compiled
    return int(math.floor(_pseudo_angle(x - cx, y - cy) * size)) % size


@njit(nogil=True, inline="always")
def _circumradius(ax, ay, bx, by, cx, cy):  # pragma: no cover - compiled
    dx, dy = bx - ax, by - ay
    ex, ey = cx - ax, cy - ay
    bl = dx * dx + dy * dy
    cl = ex * ex + ey * ey
    den = dx * ey - dy * ex
    if den == 0.0:
        return np.inf
    d = 0.5 / den
    x = (ey * bl - dy * cl) * d
    y = (dx * cl - ex * bl) * d
    return x * x + y * y


@njit(nogil=True, inline="always")
def _in_circle(ax, ay, bx, by, cx, cy, px, py):  # pragma: no cover - compiled
    dx, dy = ax - px, ay - py
    ex, ey = bx - px, by - py
    fx, fy = cx - px, cy - py
    ap = dx * dx + dy * dy
    bp = ex * ex + ey * ey
    cp = fx * fx + fy * fy
    return dx * (ey * cp - bp * fy) - dy * (ex * cp - bp * fx) + ap * (ex * fy - ey * fx) < 0


@njit(nogil=True, inline="always")
def _link(halfedges, a, b):  # pragma: no cover - compiled
    halfedges[a] = b
    if b != -1:
        halfedges[b] = a


@njit(nogil=True)
def _add_triangle(triangles, halfedges, t, i0, i1, i2, a, b, c):  # pragma: no cover - compiled
    """Triangle (i0, i1, i2) at ``t`` with its three half-edges linked to the opposite ones a, b, c (-1: none),
    as delaunator's ``_addTriangle``."""
    triangles[t], triangles[t + 1], triangles[t + 2] = i0, i1, i2
    _link(halfedges, t, a)
    _link(halfedges, t + 1, b)
    _link(halfedges, t + 2, c)


@njit(nogil=True)
def _legalize(a, xs, ys, triangles, halfedges, hull_tri, hull_prev, hull_start, stack):  # pragma: no cover
    i = 0
    ar = 0
    while True:
        b = halfedges[a]
        a0 = a - a % 3
        ar = a0 + (a + 2) % 3
        if b == -1:
            if i == 0:
                break
            i -= 1
            a = stack[i]
            continue
        b0 = b - b % 3
        al = a0 + (a + 1) % 3
        bl = b0 + (b + 2) % 3
        p0 = triangles[ar]
        pr = triangles[a]
        pl = triangles[al]
        p1 = triangles[bl]
        if _in_circle(xs[p0], ys[p0], xs[pr], ys[pr], xs[pl], ys[pl], xs[p1], ys[p1]):
            triangles[a] = p1
            triangles[b] = p0
            hbl = halfedges[bl]
            if hbl == -1:  # edge swapped on the hull: fix the hull's reference to that half-edge
                e = hull_start
                while True:
                    if hull_tri[e] == bl:
                        hull_tri[e] = a
                        break
                    e = hull_prev[e]
                    if e == hull_start:
                        break
            _link(halfedges, a, hbl)
            _link(halfedges, b, halfedges[ar])
            _link(halfedges, ar, bl)
            br = b0 + (b + 1) % 3
            if i < stack.size:
                stack[i] = br
                i += 1
        else:
            if i == 0:
                break
            i -= 1
            a = stack[i]
    return ar


@njit(nogil=True)
def _triangulate(xs, ys):  # pragma: no cover - compiled
    n = xs.size
    max_tri = max(2 * n - 5, 0)
    triangles = np.zeros(max_tri * 3, np.int64)
    halfedges = np.full(max_tri * 3, -1, np.int64)
    hash_size = int(math.ceil(math.sqrt(n)))
    hull_prev = np.zeros(n, np.int64)
    hull_next = np.zeros(n, np.int64)
    hull_tri = np.zeros(n, np.int64)
    hull_hash = np.full(hash_size, -1, np.int64)
    stack = np.zeros(512, np.int64)

    min_x, min_y, max_x, max_y = np.inf, np.inf, -np.inf, -np.inf
    for i in range(n):
        min_x = min(min_x, xs[i])
        min_y = min(min_y, ys[i])
        max_x = max(max_x, xs[i])
        max_y = max(max_y, ys[i])
    cx = (min_x + max_x) / 2
    cy = (min_y + max_y) / 2
    # Seed triangle: the point nearest the centre, its nearest neighbour, and the point making the smallest
    # circumcircle with them.
    i0 = 0
    best = np.inf
    for i in range(n):
        d = (cx - xs[i]) ** 2 + (cy - ys[i]) ** 2
        if d < best:
            i0, best = i, d
    i1 = i0
    best = np.inf
    for i in range(n):
        if i == i0:
            continue
        d = (xs[i0] - xs[i]) ** 2 + (ys[i0] - ys[i]) ** 2
        if d < best and d > 0:
            i1, best = i, d
    i2 = i0
    best = np.inf
    for i in range(n):
        if i == i0 or i == i1:
            continue
        r = _circumradius(xs[i0], ys[i0], xs[i1], ys[i1], xs[i], ys[i])
        if r < best:
            i2, best = i, r
    if best == np.inf or _orient(xs[i0], ys[i0], xs[i1], ys[i1], xs[i2], ys[i2]) == 0.0:
        return np.zeros((0, 3), np.int64)  # all points on a line
    if _orient(xs[i0], ys[i0], xs[i1], ys[i1], xs[i2], ys[i2]) < 0:
        i1, i2 = i2, i1
    # Circumcentre of the seed triangle: points are added in order of distance from it.
    dx, dy = xs[i1] - xs[i0], ys[i1] - ys[i0]
    ex, ey = xs[i2] - xs[i0], ys[i2] - ys[i0]
    bl = dx * dx + dy * dy
    cl = ex * ex + ey * ey
    d = 0.5 / (dx * ey - dy * ex)
    ccx = xs[i0] + (ey * bl - dy * cl) * d
    ccy = ys[i0] + (dx * cl - ex * bl) * d
    dists = np.empty(n)
    for i in range(n):
        dists[i] = (xs[i] - ccx) ** 2 + (ys[i] - ccy) ** 2
    ids = np.argsort(dists, kind="mergesort")

    hull_start = i0
    hull_next[i0] = i1
    hull_prev[i2] = i1
    hull_next[i1] = i2
    hull_prev[i0] = i2
    hull_next[i2] = i0
    hull_prev[i1] = i0
    hull_tri[i0] = 0
    hull_tri[i1] = 1
    hull_tri[i2] = 2
    hull_hash[_hash_key(xs[i0], ys[i0], ccx, ccy, hash_size)] = i0
    hull_hash[_hash_key(xs[i1], ys[i1], ccx, ccy, hash_size)] = i1
    hull_hash[_hash_key(xs[i2], ys[i2], ccx, ccy, hash_size)] = i2

    tlen = 0
    triangles[0], triangles[1], triangles[2] = i0, i1, i2
    tlen = 3

    xp = 0.0
    yp = 0.0
    for k in range(n):
        i = ids[k]
        x = xs[i]
        y = ys[i]
        if k > 0 and abs(x - xp) <= _EPSILON and abs(y - yp) <= _EPSILON:
            continue  # a duplicate of the previous point
        xp = x
        yp = y
        if i == i0 or i == i1 or i == i2:
            continue
        # A visible edge of the hull, found from the hash of the angle around the centre.
        start = 0
        key = _hash_key(x, y, ccx, ccy, hash_size)
        for j in range(hash_size):
            start = hull_hash[(key + j) % hash_size]
            if start != -1 and start != hull_next[start]:
                break
        start = hull_prev[start]
        e = start
        while True:
            q = hull_next[e]
            if _orient(x, y, xs[e], ys[e], xs[q], ys[q]) < 0:
                break
            e = q
            if e == start:
                e = -1
                break
        if e == -1:
            continue  # on the hull's line (nearly a duplicate): skipped, as delaunator does
        # The first triangle from the point, then flips.
        t = tlen
        _add_triangle(triangles, halfedges, t, e, i, hull_next[e], -1, -1, hull_tri[e])
        tlen += 3
        hull_tri[i] = _legalize(t + 2, xs, ys, triangles, halfedges, hull_tri, hull_prev, hull_start, stack)
        hull_tri[e] = t
        # Walk forward through the hull, adding triangles and flipping.
        nxt = hull_next[e]
        while True:
            q = hull_next[nxt]
            if not _orient(x, y, xs[nxt], ys[nxt], xs[q], ys[q]) < 0:
                break
            t = tlen
            _add_triangle(triangles, halfedges, t, nxt, i, q, hull_tri[i], -1, hull_tri[nxt])
            tlen += 3
            hull_tri[i] = _legalize(t + 2, xs, ys, triangles, halfedges, hull_tri, hull_prev, hull_start, stack)
            hull_next[nxt] = nxt  # marks it removed from the hull
            nxt = q
        # Walk backward from the other side.
        if e == start:
            while True:
                q = hull_prev[e]
                if not _orient(x, y, xs[q], ys[q], xs[e], ys[e]) < 0:
                    break
                t = tlen
                _add_triangle(triangles, halfedges, t, q, i, e, -1, hull_tri[e], hull_tri[q])
                tlen += 3
                _legalize(t + 2, xs, ys, triangles, halfedges, hull_tri, hull_prev, hull_start, stack)
                hull_tri[q] = t
                hull_next[e] = e
                e = q
        hull_start = e
        hull_prev[i] = e
        hull_next[e] = i
        hull_prev[nxt] = i
        hull_next[i] = nxt
        hull_hash[_hash_key(x, y, ccx, ccy, hash_size)] = i
        hull_hash[_hash_key(xs[e], ys[e], ccx, ccy, hash_size)] = e
    return triangles[:tlen].reshape(-1, 3).copy()
