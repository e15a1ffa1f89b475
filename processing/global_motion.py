"""Sturdier feature matching than the seed's (seed 6.2, 7.2: matching fails when the fingertip changes speed or
direction, because predictions come only from each feature's previous displacement).

Two ingredients, used by :class:`skinstretch.processing.tracking.FeatureTracker` when given:

* :class:`GlobalMotionEstimator` measures the coarse motion between consecutive frames by phase correlation of the
  whole (downsampled) images. It does not depend on the previous displacement, so a reversal or a jump in speed
  is predicted correctly.
* :func:`affine_motion` measures the affine motion between two (downsampled) whole images by ECC, the dense
  flow's start.
* :func:`local_predictions` predicts each feature's displacement from the median displacement of its matched
  neighbours (local structure): after a first matching pass this replaces the single global shift, so features
  in a region that sticks while the rest slides are predicted correctly too.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit


@dataclass(frozen=True)
class GlobalMotion:
    """Coarse motion between two frames: shift (dx, dy) px of the second frame's content, and its reliability."""

    shift: np.ndarray  # (2,) float64
    response: float  # phase-correlation peak height in [0, 1]; low = unreliable (no contact, no texture)
    reliable: bool


class GlobalMotionEstimator:
    """Whole-image translation between consecutive frames by phase correlation (windowed, downsampled).

    Parameters
    ----------
    downsample : int
        Integer reduction before correlation (2 keeps the ~27 px ridge period of the full field resolvable).
    min_response : float
        Peak height below which the estimate is flagged unreliable.

    Examples
    --------
    >>> import numpy as np, cv2
    >>> rng = np.random.default_rng(1)
    >>> a = cv2.GaussianBlur((rng.random((200, 240)) * 255).astype(np.float32), (0, 0), 3)
    >>> b = np.roll(a, (4, -8), axis=(0, 1))
    >>> m = GlobalMotionEstimator().estimate(a, b)
    >>> bool(np.abs(m.shift - [-8, 4]).max() < 1.0), m.reliable  # coarse: a prediction, refined later
    (True, True)
    """

    def __init__(self, *, downsample: int = 2, min_response: float = 0.05) -> None:
        if int(downsample) < 1:
            raise InvalidInputError(f"downsample must be >= 1, got {downsample!r}")
        self.downsample = int(downsample)
        self.min_response = float(min_response)
        self._window: np.ndarray | None = None

    def prepare(self, image: np.ndarray) -> np.ndarray:
        """The image as :meth:`estimate_prepared` wants it (downsampled, zero mean); thread-safe, once per frame."""
        image = np.asarray(image)
        if image.ndim != 2:
            raise InvalidInputError(f"image must be 2-D, got shape {image.shape}")
        img = image.astype(np.float32)
        if self.downsample > 1:
            h, w = img.shape
            img = cv2.resize(img, (w // self.downsample, h // self.downsample), interpolation=cv2.INTER_AREA)
        return img - float(img.mean())

    def estimate(self, prev_image: np.ndarray, curr_image: np.ndarray) -> GlobalMotion:
        return self.estimate_prepared(self.prepare(prev_image), self.prepare(curr_image))

    def estimate_prepared(self, a: np.ndarray, b: np.ndarray) -> GlobalMotion:
        """:meth:`estimate` on two images already through :meth:`prepare`."""
        if a.shape != b.shape:
            raise InvalidInputError(f"images differ in shape: {a.shape} vs {b.shape} (after preparation)")
        if self._window is None or self._window.shape != a.shape:
            self._window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
        if float(a.std()) < 1e-3 or float(b.std()) < 1e-3:
            return GlobalMotion(np.zeros(2), 0.0, False)
        (dx, dy), response = cv2.phaseCorrelate(a, b, self._window)
        shift = np.array([dx, dy], dtype=np.float64) * self.downsample
        ok = bool(np.all(np.isfinite(shift))) and response >= self.min_response
        return GlobalMotion(shift if ok else np.zeros(2), float(response), ok)


def local_predictions(
    points: np.ndarray,
    matched_points: np.ndarray,
    matched_displacements: np.ndarray,
    *,
    neighbours: int = 6,
    fallback: np.ndarray | None = None,
) -> np.ndarray:
    """Predict the displacement at ``points`` as the median of the ``neighbours`` nearest matched displacements.

    Parameters
    ----------
    points : (n, 2) array
        Where to predict (x, y px).
    matched_points, matched_displacements : (m, 2) arrays
        Positions and displacements of features already matched (e.g. by a first pass).
    neighbours : int
        How many nearest matched features vote (the median rejects a wrong match among them).
    fallback : (2,) array, optional
        Used when fewer than 3 matched features exist (default zero).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    matched_points = np.asarray(matched_points, dtype=np.float64).reshape(-1, 2)
    matched_displacements = np.asarray(matched_displacements, dtype=np.float64).reshape(-1, 2)
    if matched_points.shape != matched_displacements.shape:
        raise InvalidInputError(
            f"matched_points {matched_points.shape} and matched_displacements {matched_displacements.shape} differ"
        )
    if neighbours < 1:
        raise InvalidInputError(f"neighbours must be >= 1, got {neighbours!r}")
    fb = np.zeros(2) if fallback is None else np.asarray(fallback, dtype=np.float64).reshape(2)
    m = matched_points.shape[0]
    if m < 3 or points.shape[0] == 0:
        return np.tile(fb, (points.shape[0], 1))
    k = min(neighbours, m)
    return _knn_median(points, matched_points, matched_displacements, k)


def local_gradients(points: np.ndarray, displacements: np.ndarray, *, neighbours: int = 10,
                    at: np.ndarray | None = None) -> np.ndarray:
    """The displacement gradient at each of ``points`` from an affine least-squares fit of its ``neighbours``
    nearest points' ``displacements`` (itself included): ``out[i, j, l] = d u_j / d x_l``, (n, 2, 2). Zero where
    the fit is degenerate (fewer than 3 points, collinear neighbours). ``at`` (indices into ``points``): only at
    those points, (len(at), 2, 2), fitted to all of them."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    displacements = np.asarray(displacements, dtype=np.float64).reshape(-1, 2)
    if points.shape != displacements.shape:
        raise InvalidInputError(f"points {points.shape} and displacements {displacements.shape} differ")
    where = points if at is None else points[np.asarray(at, dtype=np.int64).reshape(-1)]
    n = where.shape[0]
    out = np.zeros((n, 2, 2))
    if points.shape[0] < 3 or n == 0:
        return out
    k = min(int(neighbours), points.shape[0])
    _, idx = cKDTree(points).query(where, k=k)
    idx = idx.reshape(n, k)
    rel = points[idx] - where[:, None, :]  # (n, k, 2)
    a = np.concatenate([np.ones((n, k, 1)), rel], axis=2)  # (n, k, 3): u = u0 + G rel
    ata = np.einsum("nki,nkj->nij", a, a)
    atb = np.einsum("nki,nkj->nij", a, displacements[idx])  # (n, 3, 2)
    det = np.linalg.det(ata)
    scale = np.einsum("nkj,nkj->n", rel, rel) / k
    ok = det > 1e-9 * np.maximum(scale, 1e-12) ** 2
    if ok.any():
        coef = np.linalg.solve(ata[ok], atb[ok])  # (m, 3, 2): rows u0, d/dx, d/dy; columns u_x, u_y
        out[ok] = np.transpose(coef[:, 1:, :], (0, 2, 1))
    return out


@njit(nogil=True)
def _knn_median(points, matched_points, matched_displacements, k):
    """Per point, the median (per axis, as np.median) of the displacements of its k nearest matched points.
    The matched points are scanned outward in x from the point's own x, stopping once the x gap alone exceeds
    the k-th best distance so far."""
    n = points.shape[0]
    m = matched_points.shape[0]
    order = np.argsort(matched_points[:, 0])
    xs = matched_points[order, 0]
    ys = matched_points[order, 1]
    out = np.empty((n, 2))
    best_d = np.empty(k)
    best_i = np.empty(k, np.int64)
    vals = np.empty(k)
    for a in range(n):
        px = points[a, 0]
        py = points[a, 1]
        found = 0
        hi = np.searchsorted(xs, px)
        lo = hi - 1
        while lo >= 0 or hi < m:
            # the nearer side in x next
            if hi >= m or (lo >= 0 and px - xs[lo] <= xs[hi] - px):
                t = lo
                lo -= 1
            else:
                t = hi
                hi += 1
            dx = xs[t] - px
            if found == k and dx * dx > best_d[k - 1]:
                break  # every point left is further in x alone
            dy = ys[t] - py
            d = dx * dx + dy * dy
            if found == k and d >= best_d[k - 1]:
                continue
            # insertion into the sorted list of the k best so far
            j = found if found < k else k - 1
            while j > 0 and best_d[j - 1] > d:
                best_d[j] = best_d[j - 1]
                best_i[j] = best_i[j - 1]
                j -= 1
            best_d[j] = d
            best_i[j] = order[t]
            if found < k:
                found += 1
        for c in range(2):
            for j in range(k):  # insertion sort: k is small
                v = matched_displacements[best_i[j], c]
                q = j
                while q > 0 and vals[q - 1] > v:
                    vals[q] = vals[q - 1]
                    q -= 1
                vals[q] = v
            if k % 2:
                out[a, c] = vals[k // 2]
            else:
                out[a, c] = (vals[k // 2 - 1] + vals[k // 2]) / 2.0
    return out


def affine_motion(a: np.ndarray, b: np.ndarray, shift: np.ndarray) -> np.ndarray | None:
    """Affine motion between two (downsampled) images by ECC, started from a translation; None if it fails.

    Returns the 2x3 matrix mapping frame-a points to frame-b points (at the resolution of ``a``)."""
    warp = np.array([[1, 0, shift[0]], [0, 1, shift[1]]], dtype=np.float32)
    try:
        # ECC's warp maps template (a) coordinates into the input image (b).
        _, warp = cv2.findTransformECC(
            a, b, warp, cv2.MOTION_AFFINE, (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4), None, 3
        )
    except cv2.error:
        return None
    if not np.all(np.isfinite(warp)) or np.abs(warp[:, :2] - np.eye(2)).max() > 0.3:
        return None
    return warp.astype(np.float64)
