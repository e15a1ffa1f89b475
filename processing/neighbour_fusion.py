"""Fusing each point's registered displacement with its neighbours' (beyond the seed).

A window of parallel ridges determines the displacement across them well and along them poorly (the aperture
problem): on real prints the feature method's frame-to-frame error along the ridges is about twice that across
(known gaps, "Thin margins on real prints"). Each point's measurement comes with its covariance ``C_i = s^2 T^-1``
(:meth:`skinstretch.processing.displacement_refinement.SubpixelRefiner.displacement_covariance`), long along the
ridges. Its neighbours predict its displacement by a local affine fit of theirs (generalised least squares, each
weighted by the inverse of its covariance plus a model term, and by a Gaussian of its distance), with the
prediction's own covariance; the fused displacement is the inverse-covariance-weighted mean of the measurement and
that prediction. Across the ridges the measurement keeps most of its weight; along them the neighbours, whose
ridges run in other directions further off, supply what the window cannot see: the role the membrane plays in the
dense flow (:mod:`skinstretch.processing.flow`), on scattered points. The model term ``model_sigma_px`` is how far
the skin's true motion may depart from the local affine at a point: the prediction is never trusted more than
that. It grows where the neighbours do not fit the affine within their covariances, and where the point's own
window gradient departs from theirs (a slip band: a pull towards the affine that is small each frame would add up
along a trajectory crossing it).

Hand-written (numba): a weighted affine fit per point over a variable neighbour list with per-point 2 x 2
weights is not in scipy or scikit-image.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit

#: Weight of a point's gradient mismatch (its own window's displacement gradient against its neighbours' affine)
#: in the model term, times the neighbours' typical squared distance. It loosens the pull where the skin does not
#: move affinely (a slip band): without it the pull, small each frame, added up along a trajectory crossing the
#: band (held-out real prints, slip front on 102_1: 11-frame edge strain 0.125 % unfused, 0.21 % fused without the
#: gate, 0.144 % at 0.25, 0.131 % at 1, where the displacement gain was mostly gone: 0.0452 -> 0.0407 -> 0.0431 px
#: on the slide of the same print).
_GRADIENT_WEIGHT = 0.25


def fuse_with_neighbours(
    points: np.ndarray,
    displacement: np.ndarray,
    covariance: np.ndarray,
    *,
    gradient: np.ndarray | None = None,
    radius_px: float,
    model_sigma_px: float,
    min_neighbours: int = 4,
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's displacement fused with the local affine prediction of its neighbours within ``radius_px``
    (Gaussian weights of standard deviation ``radius_px / 2``); see the module doc.

    Parameters
    ----------
    points, displacement : (n, 2) arrays, px
    covariance : (n, 2, 2) array, px^2
        Of each displacement; a point whose covariance is not finite is neither fused nor used as a neighbour.
    gradient : (n, 2, 2) array, optional
        The displacement gradient measured in each point's own window (``gradient[i, j, l] = d u_j / d x_l``; NaN:
        unknown). Where it departs from the neighbours' affine, the model term grows with the difference (see
        :data:`_GRADIENT_WEIGHT`).
    radius_px, model_sigma_px : float
    min_neighbours : int
        Fewer usable neighbours (at least 3 for the affine) leave the point as it is.

    Returns
    -------
    (fused (n, 2), changed (n,) bool)
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    displacement = np.ascontiguousarray(displacement, dtype=np.float64).reshape(-1, 2)
    covariance = np.ascontiguousarray(covariance, dtype=np.float64).reshape(-1, 2, 2)
    n = points.shape[0]
    if displacement.shape[0] != n or covariance.shape[0] != n:
        raise InvalidInputError(f"points ({n}), displacement ({displacement.shape[0]}) and covariance "
                                f"({covariance.shape[0]}) must have one row per point")
    if not (radius_px > 0 and model_sigma_px > 0 and min_neighbours >= 3):
        raise InvalidInputError("radius_px and model_sigma_px must be positive and min_neighbours >= 3, got "
                                f"{radius_px!r}, {model_sigma_px!r}, {min_neighbours!r}")
    usable = np.all(np.isfinite(covariance), axis=(1, 2)) & np.all(np.isfinite(displacement), axis=1)
    if n < min_neighbours + 1 or usable.sum() < min_neighbours + 1:
        return displacement.copy(), np.zeros(n, bool)
    pairs = cKDTree(points).query_pairs(float(radius_px), output_type="ndarray")  # i < j, each once
    both = np.concatenate([pairs, pairs[:, ::-1]])
    both = both[np.argsort(both[:, 0], kind="stable")]
    indptr = np.searchsorted(both[:, 0], np.arange(n + 1))
    indices = np.ascontiguousarray(both[:, 1], dtype=np.int64)
    grad = np.full((n, 2, 2), np.nan)
    if gradient is not None:
        grad = np.ascontiguousarray(gradient, dtype=np.float64).reshape(-1, 2, 2)
        if grad.shape[0] != n:
            raise InvalidInputError(f"gradient has {grad.shape[0]} rows for {n} points")
    return _fuse_kernel(points, displacement, covariance, grad, usable, indptr, indices, float(radius_px) / 2.0,
                        float(model_sigma_px) ** 2, int(min_neighbours))


@njit(nogil=True)
def _neighbour_weight(points, cov, i, j, sigma, model_var):
    """Neighbour j of point i: its offset (ox, oy), distance weight wt, and weight matrix (w00, w01, w11), the
    inverse of its covariance plus the model term times wt; wt = 0 where that covariance is not positive."""
    ox = points[j, 0] - points[i, 0]
    oy = points[j, 1] - points[i, 1]
    a, b, c = cov[j, 0, 0] + model_var, cov[j, 0, 1], cov[j, 1, 1] + model_var
    det = a * c - b * b
    if not det > 0.0:
        return ox, oy, 0.0, 0.0, 0.0, 0.0
    wt = np.exp(-0.5 * (ox * ox + oy * oy) / (sigma * sigma))
    return ox, oy, wt, wt * c / det, -wt * b / det, wt * a / det


@njit(nogil=True)
def _fuse_kernel(points, disp, cov, grad, usable, indptr, indices, sigma, model_var, min_neighbours):
    n = points.shape[0]
    out = disp.copy()
    changed = np.zeros(n, np.bool_)
    m = np.zeros((6, 6))
    v = np.zeros(6)
    most = 0
    for i in range(n):
        most = max(most, indptr[i + 1] - indptr[i])
    # the usable neighbours of the current point: index, offset, distance weight, weight matrix
    nb_j = np.zeros(most, np.int64)
    nb_w = np.zeros((most, 6))
    for i in range(n):
        if not usable[i]:
            continue
        m[:] = 0.0
        v[:] = 0.0
        used = 0
        for t in range(indptr[i], indptr[i + 1]):
            j = indices[t]
            if j == i or not usable[j]:
                continue
            ox, oy, wt, w00, w01, w11 = _neighbour_weight(points, cov, i, j, sigma, model_var)
            if not wt > 0.0:
                continue
            nb_j[used] = j
            nb_w[used, 0], nb_w[used, 1], nb_w[used, 2] = ox, oy, wt
            nb_w[used, 3], nb_w[used, 4], nb_w[used, 5] = w00, w01, w11
            # rows of the design: u = (ux0 + gxx ox + gxy oy, uy0 + gyx ox + gyy oy), unknowns
            # (ux0, uy0, gxx, gxy, gyx, gyy)
            bx = (1.0, 0.0, ox, oy, 0.0, 0.0)
            by = (0.0, 1.0, 0.0, 0.0, ox, oy)
            dx, dy = disp[j, 0], disp[j, 1]
            for p in range(6):
                wxp = w00 * bx[p] + w01 * by[p]
                wyp = w01 * bx[p] + w11 * by[p]
                v[p] += wxp * dx + wyp * dy
                for q in range(6):
                    m[p, q] += wxp * bx[q] + wyp * by[q]
            used += 1
        if used < min_neighbours:
            continue
        scale = 0.0
        for p in range(6):
            scale = max(scale, m[p, p])
        for p in range(6):
            m[p, p] += 1e-9 * scale  # neighbours on a line leave the gradient across it free: a huge, finite variance
        minv = np.linalg.inv(m)
        pred = minv @ v
        if not (np.all(np.isfinite(pred)) and minv[0, 0] > 0.0 and minv[1, 1] > 0.0):
            continue
        # How well the neighbours fit the affine, in their own covariances: the mean of r^T W r over them is 2
        # where the affine holds; where it does not (a slip band), the prediction's covariance grows by as much.
        chi = 0.0
        wsum = 0.0
        for k in range(used):
            j = nb_j[k]
            ox, oy, wt, w00, w01, w11 = nb_w[k, 0], nb_w[k, 1], nb_w[k, 2], nb_w[k, 3], nb_w[k, 4], nb_w[k, 5]
            rx = disp[j, 0] - (pred[0] + pred[2] * ox + pred[3] * oy)
            ry = disp[j, 1] - (pred[1] + pred[4] * ox + pred[5] * oy)
            chi += w00 * rx * rx + 2.0 * w01 * rx * ry + w11 * ry * ry
            wsum += wt
        inflate = max(1.0, chi / (2.0 * wsum)) if wsum > 0.0 else 1.0
        # The point's own window gradient against the neighbours' affine: where the skin does not move affinely
        # (a slip band) they differ, and over the neighbours' typical distance that is what the prediction misses.
        mv = model_var
        if np.isfinite(grad[i, 0, 0]):
            g2 = ((grad[i, 0, 0] - pred[2]) ** 2 + (grad[i, 0, 1] - pred[3]) ** 2 + (grad[i, 1, 0] - pred[4]) ** 2
                  + (grad[i, 1, 1] - pred[5]) ** 2)
            mv += _GRADIENT_WEIGHT * g2 * sigma * sigma
        # The prediction's covariance (its fit's, plus the model term) and the point's own: inverse-variance mean.
        pa, pb, pc = inflate * (minv[0, 0] + mv), inflate * minv[0, 1], inflate * (minv[1, 1] + mv)
        pdet = pa * pc - pb * pb
        ma, mb, mc = cov[i, 0, 0], cov[i, 0, 1], cov[i, 1, 1]
        mdet = ma * mc - mb * mb
        if not (pdet > 0.0 and mdet > 0.0):
            continue
        # information matrices
        ia, ib, ic = mc / mdet, -mb / mdet, ma / mdet
        ja, jb, jc = pc / pdet, -pb / pdet, pa / pdet
        sa, sb, sc = ia + ja, ib + jb, ic + jc
        rx = ia * disp[i, 0] + ib * disp[i, 1] + ja * pred[0] + jb * pred[1]
        ry = ib * disp[i, 0] + ic * disp[i, 1] + jb * pred[0] + jc * pred[1]
        sdet = sa * sc - sb * sb
        if not sdet > 0.0:
            continue
        out[i, 0] = (sc * rx - sb * ry) / sdet
        out[i, 1] = (sa * ry - sb * rx) / sdet
        changed[i] = True
    return out, changed
