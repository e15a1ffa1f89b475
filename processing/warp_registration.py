"""Lucas-Kanade registration kernel of a window under a second-order warp (beyond the seed, seed 7.2.2).

Compiled loops for :class:`~skinstretch.processing.displacement_refinement.SubpixelRefiner`: the second-order warp
measures a span's motion (``register_span``). Hand
written: OpenCV's ``calcOpticalFlowPyrLK`` registers translations only, and ``findTransformECC`` one warp of a whole
image at a time (no per-point windows, no second-order warp, no statistic of the fit).
"""

from __future__ import annotations

import numpy as np

from skinstretch.processing.jit import njit

#: The kernels below sum over windows of up to 63 x 63 pixels in any order (``reassoc``: vectorised sums, rounding
#: differences ~1e-15 relative) and keep IEEE NaN and infinity semantics (a failed fit stays NaN, then rejected).
FASTMATH = {"reassoc", "contract"}


@njit(nogil=True)
def shifted_window(b, c, r, half, dx, dy):
    """The window of side 2 half + 1 around pixel (c, r) shifted by (dx, dy), for bilinear sampling of ``b``: its
    integer offset (ix, iy), fractions (fx, fy) (the same for every pixel of the window), and whether every
    sample's 2 x 2 neighbourhood lies in ``b``."""
    h, w = b.shape
    ix = int(np.floor(dx))
    iy = int(np.floor(dy))
    inside = c - half + ix >= 0 and r - half + iy >= 0 and c + half + ix + 1 < w and r + half + iy + 1 < h
    return ix, iy, dx - ix, dy - iy, inside


@njit(nogil=True, fastmath=FASTMATH)
def _bilinear(b, qx, qy):
    """``b`` at (qx, qy) by bilinear interpolation (float32 weights), for a point its callers keep inside ``b``.
    A plain call that LLVM inlines (Numba's ``inline="always"`` here kept the callers' loops from vectorising)."""
    h, w = b.shape
    one = np.float32(1.0)
    x0 = min(int(qx), w - 2)
    y0 = min(int(qy), h - 2)
    fx = np.float32(qx - x0)
    fy = np.float32(qy - y0)
    return ((b[y0, x0] * (one - fx) + b[y0, x0 + 1] * fx) * (one - fy)
            + (b[y0 + 1, x0] * (one - fx) + b[y0 + 1, x0 + 1] * fx) * fy)


#: Exponents (i, j) of the monomials s^i t^j of :func:`second_order_kernel`'s warp: 1, s, t, s^2, s t, t^2.
_SECOND_ORDER_TERMS = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))

#: The 12 coefficients reordered affine first (x: 1, s, t; y: 1, s, t), then second-order: the Hessian's Cholesky
#: factor in this order holds the affine block's factor and the factor of the second-order block's Schur complement.
_ORDER = np.array([0, 1, 2, 6, 7, 8, 3, 4, 5, 9, 10, 11])


@njit(nogil=True, fastmath=FASTMATH)
def second_order_kernel(a, b, gx, gy, points, disp, half, steps):
    """Per point, the second-order warp x -> x + d + sum_k (cx_k, cy_k) m_k(s, t) that registers the window of
    ``a`` around p onto ``b``: m = (1, s, t, s^2, s t, t^2) of the window's normalised coordinates
    (s, t) = (x - p) / half, each within [-1, 1] so that the 12 x 12 system is well scaled. Up to ``steps``
    Gauss-Newton steps with the gradient of ``a`` (a fixed Hessian: the Jacobian is the first image's), from no change,
    each after the first accelerated by a secant (Anderson, depth 1) combination with the step before, stopping
    once a step moves no pixel by more than 1e-4 px.

    Rows (n, 13): 0-1 the translation (delta_x, delta_y) of the centre; 2-5 the displacement gradient
    (G00, G01, G10, G11) there, px/px, ``G[j, l] = d u_j / d x_l``; 6-7 the translation of the affine model, the
    second-order terms dropped (its least-squares solution at the same linearisation,
    ``c_1 + H_11^-1 H_12 c_2``); 8 the Wald statistic of the six second-order terms, ``c_2^T (H^-1)_22^-1 c_2 / s^2``;
    9-10 and 11-12 the predicted variances (px^2) of the translation x and y, ``s^2 (H^-1)_jj``, of the second-order
    and of the affine model; ``s^2`` the residual variance after the fit times ``(1 + r_x)(1 + r_y) / ((1 - r_x)(1 - r_y))``, r the
    residual's correlation between horizontally and vertically neighbouring pixels (what interpolation and
    texture leave is smooth: fewer independent samples than pixels; about 1 for camera noise). Large: the window's
    displacement is curved. ok False where the system is singular (the correlation matrix of its 12 columns has a
    determinant below 1e-12: no texture, or ridges all one way) or the warp could take the window beyond ``b``
    (bounded by the sum of its coefficients' magnitudes). Sums along a row are float32 (SIMD-wide), over the window float64."""
    h, w = a.shape
    n = points.shape[0]
    out = np.zeros((n, 13))
    ok = np.zeros(n, np.bool_)
    side = 2 * half + 1
    inv = 1.0 / half
    hess = np.zeros((12, 12))
    chol = np.zeros((12, 12))
    rhs = np.zeros(12)
    mom = np.zeros((3, 5, 5))
    row = np.zeros((3, 5))
    res = np.zeros((side, side), np.float32)
    ss = np.empty(side)
    ss32 = np.empty(side, np.float32)
    pw = np.empty((4, side), np.float32)  # s, s^2, s^3, s^4 of each column
    for i in range(n):
        px, py = points[i, 0], points[i, 1]
        c, r = int(np.round(px)), int(np.round(py))
        if c - half < 0 or r - half < 0 or c + half >= w or r + half >= h:
            continue
        s0 = (c - half - px) * inv
        t0 = (r - half - py) * inv
        for k in range(side):
            ss[k] = s0 + k * inv
            ss32[k] = np.float32(ss[k])
            pw[0, k] = ss32[k]
            pw[1, k] = np.float32(ss[k] ** 2)
            pw[2, k] = np.float32(ss[k] ** 3)
            pw[3, k] = np.float32(ss[k] ** 4)
        # moments sum P s^e t^f (e + f <= 4) of P = gx^2, gx gy, gy^2, row by row
        mom[:] = 0.0
        for y in range(r - half, r + half + 1):
            t = t0 + (y - r + half) * inv
            gxr = gx[y, c - half:c + half + 1]
            gyr = gy[y, c - half:c + half + 1]
            z = np.float32(0.0)
            a0 = a1 = a2 = a3 = a4 = b0 = b1 = b2 = b3 = b4 = d0 = d1 = d2 = d3 = d4 = z
            for k in range(side):
                ax = gxr[k]
                ay = gyr[k]
                p0, p1, p2 = ax * ax, ax * ay, ay * ay
                s1 = pw[0, k]
                s2 = pw[1, k]
                s3 = pw[2, k]
                s4 = pw[3, k]
                a0 += p0
                a1 += p0 * s1
                a2 += p0 * s2
                a3 += p0 * s3
                a4 += p0 * s4
                b0 += p1
                b1 += p1 * s1
                b2 += p1 * s2
                b3 += p1 * s3
                b4 += p1 * s4
                d0 += p2
                d1 += p2 * s1
                d2 += p2 * s2
                d3 += p2 * s3
                d4 += p2 * s4
            row[0, 0], row[0, 1], row[0, 2], row[0, 3], row[0, 4] = a0, a1, a2, a3, a4
            row[1, 0], row[1, 1], row[1, 2], row[1, 3], row[1, 4] = b0, b1, b2, b3, b4
            row[2, 0], row[2, 1], row[2, 2], row[2, 3], row[2, 4] = d0, d1, d2, d3, d4
            tp = 1.0
            for f in range(5):
                for e in range(5 - f):
                    for m in range(3):
                        mom[m, e, f] += row[m, e] * tp
                tp *= t
        for u in range(6):
            for v in range(6):
                e = _SECOND_ORDER_TERMS[u][0] + _SECOND_ORDER_TERMS[v][0]
                f = _SECOND_ORDER_TERMS[u][1] + _SECOND_ORDER_TERMS[v][1]
                hess[u, v] = mom[0, e, f]
                hess[u, 6 + v] = mom[1, e, f]
                hess[6 + u, v] = mom[1, e, f]
                hess[6 + u, 6 + v] = mom[2, e, f]
        if not hess[0, 0] + hess[6, 6] > 0.0:
            continue
        if not _cholesky_permuted(hess, chol):
            continue
        q = np.zeros(12)
        last_q = np.zeros(12)
        last_step = np.zeros(12)
        inside = True
        taken = 0
        dx, dy = disp[i, 0], disp[i, 1]
        while True:
            # The warp moves no sample of the window by more than the sum of |coefficients| beyond the centre's
            # translation (|m_k| <= 1): the window stays inside b if that box does (checked once, not per pixel).
            reach_x = abs(q[1]) + abs(q[2]) + abs(q[3]) + abs(q[4]) + abs(q[5])
            reach_y = abs(q[7]) + abs(q[8]) + abs(q[9]) + abs(q[10]) + abs(q[11])
            cx = c + dx + q[0]
            cy = r + dy + q[6]
            if not (cx - half - reach_x >= 0.0 and cy - half - reach_y >= 0.0
                    and cx + half + reach_x < w - 1 and cy + half + reach_y < h - 1):
                inside = False
                break
            if taken == steps:
                break
            # the right-hand side at the current warp (no stores in the pixel loop: it vectorises)
            for k in range(12):
                rhs[k] = 0.0
            for y in range(r - half, r + half + 1):
                t = t0 + (y - r + half) * inv
                ex0, ex1, ex2, ey0, ey1, ey2 = _second_order_residual_row(a, b, gx, gy, q, c, half, y, t, dx, dy, ss,
                                                                          ss32, res[0], False)
                _add_row_terms(rhs, 0, float(ex0), float(ex1), float(ex2), t)
                _add_row_terms(rhs, 6, float(ey0), float(ey1), float(ey2), t)
            step = _chol_solve(chol, rhs)
            moved = np.sum(np.abs(step))
            if taken > 0:
                # Anderson (secant) acceleration of the fixed-Hessian iteration, which contracts slowly
                df = step - last_step
                dd = np.dot(df, df)
                gamma = np.dot(df, step) / dd if dd > 0.0 else 0.0
                new_q = q + step - gamma * ((q - last_q) + df)
            else:
                new_q = q + step
            last_q = q
            last_step = step
            q = new_q
            taken += 1
            # |m_k| <= 1 in the window: the sum bounds how far any pixel moved
            if moved < 1e-4:
                taken = steps  # one more bounds check, then the residual below
        if not inside or not np.all(np.isfinite(q)):
            continue
        # the residual at the final warp, for its variance and its correlation between neighbouring pixels
        for y in range(r - half, r + half + 1):
            _second_order_residual_row(a, b, gx, gy, q, c, half, y, t0 + (y - r + half) * inv, dx, dy, ss, ss32,
                                       res[y - r + half], True)
        sse = 0.0
        lag_x = 0.0
        lag_y = 0.0
        for y in range(side):
            z = np.float32(0.0)
            e2 = lx = ly = z
            for k in range(side):
                e2 += res[y, k] * res[y, k]
            for k in range(1, side):
                lx += res[y, k] * res[y, k - 1]
            if y > 0:
                for k in range(side):
                    ly += res[y, k] * res[y - 1, k]
            sse += float(e2)
            lag_x += float(lx)
            lag_y += float(ly)
        # residual variance, inflated by the residual's correlation between neighbouring pixels
        rho_x = min(max(lag_x / sse, 0.0), 0.95) if sse > 0.0 else 0.0
        rho_y = min(max(lag_y / sse, 0.0), 0.95) if sse > 0.0 else 0.0
        var = sse / (side * side - 12) * (1.0 + rho_x) / (1.0 - rho_x) * (1.0 + rho_y) / (1.0 - rho_y)
        wald, affine_x, affine_y, v2x, v2y, v1x, v1y = _fit_statistics(chol, q)
        out[i, 0], out[i, 1] = q[0], q[6]
        out[i, 2], out[i, 3], out[i, 4], out[i, 5] = q[1] * inv, q[2] * inv, q[7] * inv, q[8] * inv
        out[i, 6], out[i, 7] = affine_x, affine_y
        out[i, 8] = wald / var if var > 0.0 else np.inf
        out[i, 9], out[i, 10] = var * v2x, var * v2y
        out[i, 11], out[i, 12] = var * v1x, var * v1y
        ok[i] = True
    return out, ok


@njit(nogil=True)
def _add_row_terms(rhs, o, e0, e1, e2, t):
    """Adds a row's sums ``e0, e1, e2`` (of ``g e s^0, s^1, s^2``) to the six terms of ``rhs`` from ``o`` on, in the
    order of ``_SECOND_ORDER_TERMS`` (1, s, t, s^2, s t, t^2), ``t`` the row's coordinate."""
    rhs[o] += e0
    rhs[o + 1] += e1
    rhs[o + 2] += e0 * t
    rhs[o + 3] += e2
    rhs[o + 4] += e1 * t
    rhs[o + 5] += e0 * t * t


@njit(nogil=True, fastmath=FASTMATH, inline="always")
def _second_order_residual_row(a, b, gx, gy, q, c, half, y, t, dx, dy, ss, ss32, out, store):
    """The residual ``e = a(x) - b(x + d + warp)`` along row ``y`` of the window around column ``c`` (bilinear;
    ``t`` the row's normalised coordinate, ``ss`` the columns', ``ss32`` the same in float32), for
    :func:`second_order_kernel`, whose bounds check keeps every sample inside ``b``: its sums of ``gx e``,
    ``gx e s``, ``gx e s^2`` and the same with ``gy`` (float32), and with ``store`` the residual itself in ``out``
    (inlined where it is called with a constant ``store``, so the branch folds away and the loop without the store
    vectorises: called as a function it ran 2.3x slower)."""
    # along the row the sample is at (x + bx0 + bx1 s + qx3 s^2, by0 + by1 s + qy3 s^2)
    bx0 = c - half + dx + q[0] + q[2] * t + q[5] * t * t
    bx1 = q[1] + q[4] * t
    by0 = y + dy + q[6] + q[8] * t + q[11] * t * t
    by1 = q[7] + q[10] * t
    qx3, qy3 = q[3], q[9]
    ar = a[y, c - half:c + half + 1]
    gxr = gx[y, c - half:c + half + 1]
    gyr = gy[y, c - half:c + half + 1]
    z = np.float32(0.0)
    ex0 = ex1 = ex2 = ey0 = ey1 = ey2 = z
    for k in range(2 * half + 1):
        sk = ss[k]
        qx = k + bx0 + (bx1 + qx3 * sk) * sk
        qy = by0 + (by1 + qy3 * sk) * sk
        err = ar[k] - _bilinear(b, qx, qy)
        if store:
            out[k] = err
        ex = gxr[k] * err
        ey = gyr[k] * err
        s32 = ss32[k]
        ex0 += ex
        ex1 += ex * s32
        ex2 += ex * s32 * s32
        ey0 += ey
        ey1 += ey * s32
        ey2 += ey * s32 * s32
    return ex0, ex1, ex2, ey0, ey1, ey2


@njit(nogil=True)
def _cholesky_permuted(hess, chol):
    """The lower Cholesky factor of ``hess`` reordered by ``_ORDER``, into ``chol``; False where the system is
    singular: the correlation matrix of its columns has a determinant below 1e-12, or a pivot is not positive.
    Hand written: numba's ``np.linalg`` calls LAPACK with an allocation per call, a quarter of the kernel's time
    for these 12 x 12 systems."""
    det = 1.0
    for j in range(12):
        for k in range(j + 1):
            acc = hess[_ORDER[j], _ORDER[k]]
            for m in range(k):
                acc -= chol[j, m] * chol[k, m]
            if k == j:
                if not acc > 0.0:
                    return False
                det *= acc / hess[_ORDER[j], _ORDER[j]]
                chol[j, j] = np.sqrt(acc)
            else:
                chol[j, k] = acc / chol[k, k]
    return det >= 1e-12


@njit(nogil=True)
def _chol_solve(chol, rhs):
    """hess^-1 rhs (in the coefficients' own order) from :func:`_cholesky_permuted`'s factor."""
    z = np.empty(12)
    for j in range(12):
        acc = rhs[_ORDER[j]]
        for m in range(j):
            acc -= chol[j, m] * z[m]
        z[j] = acc / chol[j, j]
    x = _back_substitute(chol, z, 12)
    out = np.empty(12)
    for j in range(12):
        out[_ORDER[j]] = x[j]
    return out


@njit(nogil=True)
def _back_substitute(chol, z, n):
    """x with ``L^T x = z``, L the leading n x n block of the lower factor ``chol``."""
    x = np.empty(n)
    for j in range(n - 1, -1, -1):
        acc = z[j]
        for m in range(j + 1, n):
            acc -= chol[m, j] * x[m]
        x[j] = acc / chol[j, j]
    return x


@njit(nogil=True)
def _inverse_diagonal(chol, n, j):
    """``(A^-1)_jj`` of the leading n x n block A of the matrix factored in ``chol``: ``|L^-1 e_j|^2``."""
    z = np.zeros(12)
    acc2 = 0.0
    for r in range(j, n):
        acc = 1.0 if r == j else 0.0
        for m in range(j, r):
            acc -= chol[r, m] * z[m]
        z[r] = acc / chol[r, r]
        acc2 += z[r] * z[r]
    return acc2


@njit(nogil=True)
def _fit_statistics(chol, q):
    """From the reordered factor ``chol`` and the warp ``q``: the Wald form ``c2^T S c2`` of the second-order terms
    (S the Schur complement of the affine block, ``L22 L22^T``), the affine model's translation
    ``c1 + H11^-1 H12 c2`` (x, y), and the translation's inverse-Hessian diagonals, second-order then affine model."""
    # |L22^T c2|^2
    wald = 0.0
    for j in range(6, 12):
        acc = 0.0
        for m in range(j, 12):
            acc += chol[m, j] * q[_ORDER[m]]
        wald += acc * acc
    # H12 = L11 L21^T, so H11^-1 H12 c2 = L11^-T (L21^T c2)
    y = np.empty(6)
    for j in range(6):
        acc = 0.0
        for m in range(6, 12):
            acc += chol[m, j] * q[_ORDER[m]]
        y[j] = acc
    x = _back_substitute(chol, y, 6)
    return (wald, q[0] + x[0], q[6] + x[3], _inverse_diagonal(chol, 12, 0), _inverse_diagonal(chol, 12, 3),
            _inverse_diagonal(chol, 6, 0), _inverse_diagonal(chol, 6, 3))
