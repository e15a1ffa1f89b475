"""The compiled kernels of the dense flow (:mod:`skinstretch.processing.flow`), numba, nogil: the remap
coordinates of a grid field, the window sums of the brightness-constancy terms at the nodes, and the
over-relaxed (SOR) solve of the coupled system.

Hand-written: the window sums at a sparse node grid in one pass, and the block SOR of a 2-vector field with a
membrane on its deviation from a prior, have no library equivalent (OpenCV's box filters give every pixel, scipy's
solvers do not take the per-node 2x2 blocks without assembling a sparse matrix per iteration).
"""

from __future__ import annotations

import numpy as np

from skinstretch.processing.jit import njit


@njit(nogil=True)
def warp_maps(field, gx0, gy0, step_x, step_y, h, w):
    """Remap coordinates (x + u, y + v) of every pixel, (u, v) bilinear between grid nodes and extrapolated linearly
    beyond them (the outer nodes' windows reach past the grid: held constant there, a stretch biased those nodes)."""
    gyn, gxn = field.shape[0], field.shape[1]
    mx = np.empty((h, w), np.float32)
    my = np.empty((h, w), np.float32)
    row_u = np.empty(gxn)
    row_v = np.empty(gxn)
    j0s = np.empty(w, np.int64)
    txs = np.empty(w)
    for x in range(w):
        fx = (x - gx0) / step_x
        j0 = min(max(int(np.floor(fx)), 0), gxn - 2)
        j0s[x] = j0
        txs[x] = fx - j0
    for y in range(h):
        fy = (y - gy0) / step_y
        i0 = min(max(int(np.floor(fy)), 0), gyn - 2)
        ty = fy - i0
        for j in range(gxn):
            row_u[j] = field[i0, j, 0] * (1 - ty) + field[i0 + 1, j, 0] * ty
            row_v[j] = field[i0, j, 1] * (1 - ty) + field[i0 + 1, j, 1] * ty
        for x in range(w):
            j0 = j0s[x]
            tx = txs[x]
            mx[y, x] = x + row_u[j0] * (1 - tx) + row_u[j0 + 1] * tx
            my[y, x] = y + row_v[j0] * (1 - tx) + row_v[j0 + 1] * tx
    return mx, my


@njit(nogil=True)
def window_moments(s, d, rows, cols, half):
    """Window sums at nodes (rows x cols, window 2 half + 1) of Ix^2, IxIy, Iy^2, IxIt, IyIt, with (Ix, Iy) the
    3x3 Sobel gradient of ``s / 2`` (scaled to grey levels per pixel) and It = ``d``; returns (5, rows, cols).

    One pass down the image keeps running column sums and stores them at each node row's window edges (every
    pixel's products are computed once); ``rows`` must be increasing and the windows inside the (padded) image."""
    w = s.shape[1]
    nr, nc = rows.size, cols.size
    lo = np.zeros((nr, 5, w))
    hi = np.zeros((nr, 5, w))
    acc = np.zeros((5, w))
    k_lo = 0
    k_hi = 0
    for y in range(rows[0] - half, rows[nr - 1] + half + 1):
        while k_lo < nr and rows[k_lo] - half == y:
            lo[k_lo] = acc
            k_lo += 1
        for x in range(1, w - 1):
            gx = ((s[y - 1, x + 1] - s[y - 1, x - 1]) + 2.0 * (s[y, x + 1] - s[y, x - 1])
                  + (s[y + 1, x + 1] - s[y + 1, x - 1])) * 0.0625
            gy = ((s[y + 1, x - 1] - s[y - 1, x - 1]) + 2.0 * (s[y + 1, x] - s[y - 1, x])
                  + (s[y + 1, x + 1] - s[y - 1, x + 1])) * 0.0625
            t = d[y, x]
            acc[0, x] += gx * gx
            acc[1, x] += gx * gy
            acc[2, x] += gy * gy
            acc[3, x] += gx * t
            acc[4, x] += gy * t
        while k_hi < nr and rows[k_hi] + half == y:
            hi[k_hi] = acc
            k_hi += 1
    out = np.zeros((5, nr, nc))
    prefix = np.zeros(w + 1)
    for i in range(nr):
        for k in range(5):
            run = 0.0
            for x in range(w):
                run += hi[i, k, x] - lo[i, k, x]
                prefix[x + 1] = run
            for j in range(nc):
                out[k, i, j] = prefix[cols[j] + half + 1] - prefix[cols[j] - half]
    return out


@njit(nogil=True)
def _relax_node(u, i, j, ax, ay, c, px, py, omega):
    """One node's over-relaxed update: solve ``[[ax, c], [c, ay]] x = (px, py)`` and move ``u[i, j]`` by
    ``omega`` towards it."""
    det = ax * ay - c * c
    if abs(det) < 1e-12:
        det = 1e-12
    ux = (ay * px - c * py) / det
    uy = (ax * py - c * px) / det
    u[i, j, 0] += omega * (ux - u[i, j, 0])
    u[i, j, 1] += omega * (uy - u[i, j, 1])


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
    for _ in range(sweeps):
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
                    sx += we * (u[ii, jj, 0] - prior[ii, jj, 0] + prior[i, j, 0])
                    sy += we * (u[ii, jj, 1] - prior[ii, jj, 1] + prior[i, j, 1])
                    total += we
                _relax_node(u, i, j, gxx[i, j] + total, gyy[i, j] + total, gxy[i, j], rx[i, j] + sx, ry[i, j] + sy,
                            omega)
    return u


def membrane_edge_weights(dxx, dxy, dyy):
    """Edge weights (``wx, wy, wd1, wd2`` of :func:`sor_tensor`) of the membrane ``grad(u)^T D grad(u)`` on a
    square grid with diagonals, for a tensor ``D`` per node (arrays). Exact when ``|Dxy| <= min(Dxx, Dyy)``;
    beyond, the axis weights are clipped at zero (the nearest non-negative stencil)."""
    a = np.abs(dxy)
    return (np.maximum(dxx - a, 0.0), np.maximum(dyy - a, 0.0), np.maximum(dxy, 0.0), np.maximum(-dxy, 0.0))
