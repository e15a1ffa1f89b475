"""The compiled kernels of the dense flow (:mod:`skinstretch.processing.flow`), numba, nogil: the second image
warped by a grid field and the window sums of the brightness-constancy terms at the nodes in one pass, the
over-relaxed (SOR) solve of the coupled system, the bias of its membrane estimated with that solve, and points
followed through consecutive fields.

Hand-written: the window sums at a sparse node grid in one pass, and the block SOR of a 2-vector field with a
membrane on its deviation from a prior, have no library equivalent (OpenCV's box filters give every pixel, scipy's
solvers do not take the per-node 2x2 blocks without assembling a sparse matrix per iteration). Warping inside the
pass leaves out the image-sized remap coordinates, warped and padded images that ``cv2.remap`` needs.
"""

from __future__ import annotations

import numpy as np

from skinstretch.processing.jit import njit


def sor(u0, prior, gxx, gxy, gyy, rx, ry, contact, lam, sweeps, omega):
    """Block successive over-relaxation of the coupled system at contact nodes: per node, the 2x2 data term
    ``G`` plus ``lam`` times the number of contact neighbours, right-hand side ``r + lam * (sum of the
    neighbours' deviation from the prior + n * own prior)``, solved with the neighbours' latest values and
    over-relaxed by ``omega``. Nodes out of contact keep ``u0``. (Plain Jacobi needs hundreds of sweeps to carry
    the along-ridge component across the grid; SOR reaches the same solution in a few dozen.)"""
    lam_map = np.full(contact.shape, float(lam))
    none = np.zeros(contact.shape)
    return sor_tensor(u0, prior, gxx, gxy, gyy, rx, ry, contact, lam_map, lam_map, none, none, sweeps, omega)


@njit(nogil=True)
def sor_tensor(u0, prior, gxx, gxy, gyy, rx, ry, contact, wx, wy, wd1, wd2, sweeps, omega):
    """:func:`sor` with a membrane weight per node and edge direction, for an anisotropic membrane: the weights of
    a node's edges along x (``wx``), along y (``wy``) and along the diagonals (``wd1``: to (i + 1, j + 1) and
    (i - 1, j - 1); ``wd2``: to (i + 1, j - 1) and (i - 1, j + 1)); an edge weighs the mean of its two nodes'
    weights (the energy stays symmetric). Without diagonal weights only the four axis neighbours are visited. A
    membrane ``grad(u)^T D grad(u)`` with a 2x2 tensor ``D`` per node is ``wx = Dxx - |Dxy|``,
    ``wy = Dyy - |Dxy|``, ``wd1 = max(Dxy, 0)``, ``wd2 = max(-Dxy, 0)`` (see :func:`membrane_edge_weights`)."""
    gy_n, gx_n = contact.shape
    u = u0.copy()
    di = (-1, 1, 0, 0, 1, -1, 1, -1)  # up, down, left, right, then the diagonals
    dj = (0, 0, -1, 1, 1, -1, -1, 1)
    n_dirs = 8 if (np.any(wd1 != 0.0) or np.any(wd2 != 0.0)) else 4
    # What stays fixed over the sweeps, per contact node: its edges' weights (0: no edge), the right-hand side
    # without the neighbours' current values, and its 2 x 2 system.
    weight = np.zeros((gy_n, gx_n, n_dirs))
    bx = np.zeros((gy_n, gx_n))
    by = np.zeros((gy_n, gx_n))
    ax = np.zeros((gy_n, gx_n))
    ay = np.zeros((gy_n, gx_n))
    inv_det = np.ones((gy_n, gx_n))  # 1 / det: a multiplication in the sweeps, whose nodes wait on each other
    for i in range(gy_n):
        for j in range(gx_n):
            if not contact[i, j]:
                continue
            sx = 0.0
            sy = 0.0
            total = 0.0
            for k in range(n_dirs):
                ii = i + di[k]
                jj = j + dj[k]
                if ii < 0 or ii >= gy_n or jj < 0 or jj >= gx_n or not contact[ii, jj]:
                    continue
                if k < 2:
                    we = 0.5 * (wy[i, j] + wy[ii, jj])
                elif k < 4:
                    we = 0.5 * (wx[i, j] + wx[ii, jj])
                elif k < 6:
                    we = 0.5 * (wd1[i, j] + wd1[ii, jj])
                else:
                    we = 0.5 * (wd2[i, j] + wd2[ii, jj])
                if we <= 0.0:
                    continue
                weight[i, j, k] = we
                sx += we * (prior[i, j, 0] - prior[ii, jj, 0])
                sy += we * (prior[i, j, 1] - prior[ii, jj, 1])
                total += we
            bx[i, j] = rx[i, j] + sx
            by[i, j] = ry[i, j] + sy
            ax[i, j] = gxx[i, j] + total
            ay[i, j] = gyy[i, j] + total
            d = ax[i, j] * ay[i, j] - gxy[i, j] * gxy[i, j]
            inv_det[i, j] = 1.0 / (1e-12 if abs(d) < 1e-12 else d)  # NaN stays NaN
    for _ in range(sweeps):
        for i in range(gy_n):
            for j in range(gx_n):
                if not contact[i, j]:
                    continue
                px = bx[i, j]
                py = by[i, j]
                for k in range(n_dirs):
                    we = weight[i, j, k]
                    if we == 0.0:
                        continue
                    px += we * u[i + di[k], j + dj[k], 0]
                    py += we * u[i + di[k], j + dj[k], 1]
                c = gxy[i, j]
                ux = (ay[i, j] * px - c * py) * inv_det[i, j]
                uy = (ax[i, j] * py - c * px) * inv_det[i, j]
                u[i, j, 0] += omega * (ux - u[i, j, 0])
                u[i, j, 1] += omega * (uy - u[i, j, 1])
    return u


def membrane_bias(field, membrane, contact, node_x, node_y, gxx, gxy, gyy, *, sweeps, omega):
    """Per node, px (larger axis): the bias of a membrane smoothing ``S`` (weight ``membrane``, a number or one per
    node, on the deviation from the field's affine fit; data terms ``gxx, gxy, gyy``), estimated from the solved
    ``field`` ``u_hat = S u``: ``(S - I) u = (S - I) u_hat - (S - I)^2 u_hat + ...``, its first two terms (Tukey's
    twicing and one step more), each smoothing ``sweeps`` SOR sweeps. A field the membrane already left smooth moves
    little (its noise is not counted twice); a band of strain narrower than the windows, which the membrane
    flattens, gives about half its bias (the series converges slowly there). 0 out of ``contact``."""
    u = np.ascontiguousarray(field, dtype=np.float64)
    if int(contact.sum()) < 3:
        return np.zeros(contact.shape)
    coef, *_ = np.linalg.lstsq(np.column_stack([node_x[contact], node_y[contact], np.ones(int(contact.sum()))]),
                               u[contact], rcond=None)
    prior = np.stack([node_x, node_y, np.ones_like(node_x)], axis=-1) @ coef
    lam = np.ascontiguousarray(np.broadcast_to(np.asarray(membrane, dtype=np.float64), contact.shape))
    none = np.zeros(contact.shape)

    def smoothed(v, around):  # the data term pulls each node to v
        rx, ry = gxx * v[..., 0] + gxy * v[..., 1], gxy * v[..., 0] + gyy * v[..., 1]
        return sor_tensor(v, around, gxx, gxy, gyy, rx, ry, contact, lam, lam, none, none, sweeps, omega)

    d1 = np.where(contact[..., None], smoothed(u, prior) - u, 0.0)  # D u_hat, D = S - I
    d2 = smoothed(d1, np.zeros_like(d1)) - d1  # D^2 u_hat
    return np.where(contact, np.abs(d1 - d2).max(axis=-1), 0.0)


def membrane_edge_weights(dxx, dxy, dyy):
    """Edge weights (``wx, wy, wd1, wd2`` of :func:`sor_tensor`) of the membrane ``grad(u)^T D grad(u)`` on a
    square grid with diagonals, for a tensor ``D`` per node (arrays). Exact when ``|Dxy| <= min(Dxx, Dyy)``;
    beyond, the axis weights are clipped at zero (the nearest non-negative stencil)."""
    a = np.abs(dxy)
    return (np.maximum(dxx - a, 0.0), np.maximum(dyy - a, 0.0), np.maximum(dxy, 0.0), np.maximum(-dxy, 0.0))


@njit(nogil=True)
def _reflect101(i, n):
    """Index ``i`` mirrored into ``0..n - 1`` without repeating the edge (OpenCV's BORDER_REFLECT_101)."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * (n - 1) - i
    return i


@njit(nogil=True)
def _reflect(i, n):
    """Index ``i`` mirrored into ``0..n - 1`` repeating the edge (OpenCV's BORDER_REFLECT, as ``cv2.remap``'s)."""
    while i < 0 or i >= n:
        i = -i - 1 if i < 0 else 2 * n - i - 1
    return i


@njit(nogil=True)
def warped_moments(a, b, field, gx0, gy0, step_x, step_y, rows, cols, half, i0, i1, j0, j1):
    """The data terms of the nodes ``i0..i1 - 1`` x ``j0..j1 - 1`` (a box of the node grid at pixel ``rows`` x
    ``cols``, window 2 half + 1), ``b`` warped by the grid ``field`` on the fly: (7, rows, cols) window sums of
    Ix^2, IxIy, Iy^2, IxIt, IyIt, It^2 and |It|, zero outside the box.

    ``b`` is sampled (bilinear, mirrored at its edges) at each pixel plus the field (bilinear between nodes and
    extrapolated linearly beyond them: the outer nodes' windows reach past the grid, where a field held constant
    biases a stretch); It is that minus ``a``; (Ix, Iy) the 3x3 Sobel gradient of their mean (grey levels per pixel).
    Pixels beyond the image are mirrored (BORDER_REFLECT_101) for ``a`` and the warped ``b`` alike. One pass down
    the box's rows keeps running column sums and stores them at each node row's window edges; only the columns the
    box's windows cover are warped. The same sums as warping the whole image, padding it and summing every window,
    without the image-sized intermediates."""
    h, w = a.shape
    gyn, gxn = field.shape[0], field.shape[1]
    out = np.zeros((7, rows.size, cols.size))
    if i1 <= i0 or j1 <= j0:
        return out
    xlo = cols[j0] - half - 1
    xhi = cols[j1 - 1] + half + 1
    ylo = rows[i0] - half
    yhi = rows[i1 - 1] + half
    nx = xhi - xlo + 1
    # per column of the box (with its one-pixel margin): the image column it mirrors and its place between nodes
    xs = np.empty(nx, np.int64)
    jn = np.empty(nx, np.int64)
    tx = np.empty(nx)
    for k in range(nx):
        x = _reflect101(xlo + k, w)
        xs[k] = x
        fx = (x - gx0) / step_x  # beyond the outer nodes: extrapolated linearly
        jj = min(max(int(np.floor(fx)), 0), gxn - 2)
        jn[k] = jj
        tx[k] = fx - jj
    row_u = np.empty(gxn)
    row_v = np.empty(gxn)
    s = np.empty((3, nx))  # (a + warped b) / 2 ... of rows y - 1, y, y + 1 (ring)
    d = np.empty((3, nx))  # warped b - a of the same rows
    nr = i1 - i0
    win = np.zeros((nr, 7, nx))  # per node row: the column sums over its window (the sums after it minus before)
    acc = np.zeros((7, nx))
    k_lo = 0
    k_hi = 0
    for y in range(ylo - 1, yhi + 2):
        slot = (y - ylo + 1) % 3
        yr = _reflect101(y, h)
        fy = (yr - gy0) / step_y
        ii = min(max(int(np.floor(fy)), 0), gyn - 2)
        ty = fy - ii
        for j in range(gxn):
            row_u[j] = field[ii, j, 0] * (1 - ty) + field[ii + 1, j, 0] * ty
            row_v[j] = field[ii, j, 1] * (1 - ty) + field[ii + 1, j, 1] * ty
        for k in range(nx):
            x = xs[k]
            jj = jn[k]
            t = tx[k]
            qx = x + row_u[jj] * (1 - t) + row_u[jj + 1] * t
            qy = yr + row_v[jj] * (1 - t) + row_v[jj + 1] * t
            fx0 = np.floor(qx)
            fy0 = np.floor(qy)
            wx = qx - fx0
            wy = qy - fy0
            c0 = int(fx0)
            r0 = int(fy0)
            if c0 >= 0 and r0 >= 0 and c0 + 1 < w and r0 + 1 < h:
                c1 = c0 + 1
                r1 = r0 + 1
            else:
                c1 = _reflect(c0 + 1, w)
                r1 = _reflect(r0 + 1, h)
                c0 = _reflect(c0, w)
                r0 = _reflect(r0, h)
            v = ((b[r0, c0] * (1 - wx) + b[r0, c1] * wx) * (1 - wy)
                 + (b[r1, c0] * (1 - wx) + b[r1, c1] * wx) * wy)
            av = a[yr, x]
            s[slot, k] = av + v
            d[slot, k] = v - av
        yc = y - 1  # the row whose gradients are now complete
        if yc < ylo:
            continue
        while k_lo < nr and rows[i0 + k_lo] - half == yc:
            win[k_lo] -= acc
            k_lo += 1
        sm = (slot + 1) % 3  # row yc - 1
        sc = (slot + 2) % 3  # row yc
        sp = slot  # row yc + 1
        for k in range(1, nx - 1):
            gx = ((s[sm, k + 1] - s[sm, k - 1]) + 2.0 * (s[sc, k + 1] - s[sc, k - 1])
                  + (s[sp, k + 1] - s[sp, k - 1])) * 0.0625
            gy = ((s[sp, k - 1] - s[sm, k - 1]) + 2.0 * (s[sp, k] - s[sm, k])
                  + (s[sp, k + 1] - s[sm, k + 1])) * 0.0625
            t = d[sc, k]
            acc[0, k] += gx * gx
            acc[1, k] += gx * gy
            acc[2, k] += gy * gy
            acc[3, k] += gx * t
            acc[4, k] += gy * t
            acc[5, k] += t * t
            acc[6, k] += abs(t)
        while k_hi < nr and rows[i0 + k_hi] + half == yc:
            win[k_hi] += acc
            k_hi += 1
    prefix = np.zeros(nx + 1)
    for i in range(nr):
        for m in range(7):
            run = 0.0
            for k in range(nx):
                run += win[i, m, k]
                prefix[k + 1] = run
            for j in range(j0, j1):
                out[m, i0 + i, j] = prefix[cols[j] + half + 1 - xlo] - prefix[cols[j] - half - xlo]
    return out


@njit(nogil=True)
def compose_steps(points, ok, disp, valid, gx0, gy0, step_x, step_y):
    """Moves ``points`` (n, 2) through the grid fields ``disp`` (k, GY, GX, 2) in turn, each by its bilinear
    displacement there (one field's grid: origin ``gx0, gy0``, spacing ``step_x, step_y``); ``ok`` (n,) turns False
    for a point outside a grid or next to one of its invalid nodes (``valid`` (k, GY, GX)), which then stays put."""
    gyn, gxn = valid.shape[1], valid.shape[2]
    for f in range(disp.shape[0]):
        for p in range(points.shape[0]):
            if not ok[p]:
                continue
            fc = (points[p, 0] - gx0) / step_x
            fr = (points[p, 1] - gy0) / step_y
            if not (fc >= 0.0 and fc <= gxn - 1 and fr >= 0.0 and fr <= gyn - 1):
                ok[p] = False
                continue
            j = min(int(fc), gxn - 2) if gxn > 1 else 0
            i = min(int(fr), gyn - 2) if gyn > 1 else 0
            tx = fc - j
            ty = fr - i
            dx = 0.0
            dy = 0.0
            for di in range(2):
                wy = ty if di else 1.0 - ty
                for dj in range(2):
                    wgt = wy * (tx if dj else 1.0 - tx)
                    if wgt <= 1e-9:
                        continue
                    if not valid[f, i + di, j + dj]:
                        ok[p] = False
                    dx += wgt * disp[f, i + di, j + dj, 0]
                    dy += wgt * disp[f, i + di, j + dj, 1]
            if ok[p]:
                points[p, 0] += dx
                points[p, 1] += dy
