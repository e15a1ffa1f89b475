"""The ridge flow of a fingerprint frame: the local direction of its ridges, on a coarse grid.

Beyond the seed: the editing rules of seed 4.8.3-4.8.4 decide whether a short branch of the valley skeleton is a
pore's artefact by its angles with the *valleys at its node*, which the same pore (or a nearby minutia) bends.
The direction of the ridges around it, estimated over a whole ridge period, is what a pore cannot bend: a spur or
bridge made by a pore crosses a ridge, a true valley ending or fork runs along the ridges.

The estimate is the classical structure tensor (Kass & Witkin 1987; Bazen & Gerez 2002 for fingerprints): the
gradient's outer product averaged by a Gaussian of one ridge period, whose dominant eigenvector is the ridges'
normal. It is computed on the grid of cell means of :func:`skinstretch.processing.preprocess.ridge_statistics`
(cells of an eighth of a period: the pattern is still sampled 8 times per period) and averaged on cells a third of
a period wide, so it costs ~0.15 ms a frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.jit import njit

__all__ = ["RidgeFlow", "ridge_flow", "uniform_ridge_flow", "flow_normal_at"]


@dataclass(frozen=True)
class RidgeFlow:
    """The ridges' normal as a doubled angle on a grid of cells.

    Attributes
    ----------
    cos2, sin2 : (h, w) float64
        ``cos 2 phi`` and ``sin 2 phi`` of the normal's angle ``phi`` (x = column, y = row; the ridges run along
        ``phi + 90`` degrees); both 0 where the image has no gradient.
    coherence : (h, w) float64
        ``(l1 - l2) / (l1 + l2)`` of the structure tensor's eigenvalues: 1 for straight parallel ridges, 0 for no
        preferred direction.
    cell_px : int
        Cell size: cell ``(i, j)`` is centred on the full-resolution pixel ``((j + 0.5) cell - 0.5, (i + 0.5) cell
        - 0.5)``.
    """

    cos2: np.ndarray
    sin2: np.ndarray
    coherence: np.ndarray
    cell_px: int

    def normal_angle_deg(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Angle (degrees, in [0, 180)) of the ridges' normal at full-resolution points (nearest cell)."""
        c2, s2 = _nearest(self, np.asarray(x, float), np.asarray(y, float))
        return np.degrees(np.arctan2(s2, c2) / 2) % 180.0


def _nearest(flow: RidgeFlow, x, y):
    h, w = flow.cos2.shape
    j = np.clip(np.floor((x + 0.5) / flow.cell_px).astype(np.int64), 0, w - 1)
    i = np.clip(np.floor((y + 0.5) / flow.cell_px).astype(np.int64), 0, h - 1)
    return flow.cos2[i, j], flow.sin2[i, j]


def ridge_flow(cell_image: np.ndarray, *, cell_px: int, sigma_px: float) -> RidgeFlow:
    """The ridge flow of a frame from its grid of cell means.

    Parameters
    ----------
    cell_image : (h, w) float32
        Mean of the (smoothed) frame over ``cell_px`` x ``cell_px`` cells (``RidgeStatistics.cell_image``).
    cell_px : int
        Cell size of ``cell_image``, full-resolution pixels (the flow's own cells are a whole multiple of it).
    sigma_px : float
        Standard deviation of the Gaussian that averages the structure tensor, full-resolution pixels (about one
        ridge period).
    """
    if cell_image.ndim != 2 or min(cell_image.shape) < 3:
        raise InvalidInputError(f"cell_image must be a 2-D image at least 3x3, got shape {cell_image.shape}")
    if not isinstance(cell_px, (int, np.integer)) or cell_px < 1:
        raise InvalidInputError(f"cell_px must be a positive integer, got {cell_px!r}")
    if not (np.isfinite(sigma_px) and sigma_px > 0):
        raise InvalidInputError(f"sigma_px must be positive, got {sigma_px!r}")
    img = cell_image.astype(np.float32, copy=False)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, borderType=cv2.BORDER_REFLECT)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, borderType=cv2.BORDER_REFLECT)
    # The averaged tensor varies over a ridge period: it is kept on cells about a third of sigma wide (the
    # products' cell means, then a Gaussian of about 3 of those cells).
    factor = max(int(round(float(sigma_px) / int(cell_px) / 3.0)), 1)
    h, w = img.shape
    size = (max(w // factor, 1), max(h // factor, 1))
    sg = float(sigma_px) / (int(cell_px) * factor)
    k = 2 * int(math.ceil(3.0 * sg)) + 1

    def blur(a):
        if factor > 1:
            a = cv2.resize(a, size, interpolation=cv2.INTER_AREA)
        return cv2.GaussianBlur(a, (k, k), sg, borderType=cv2.BORDER_REFLECT)

    gxx, gyy, gxy = blur(gx * gx), blur(gy * gy), blur(gx * gy)
    c = (gxx - gyy).astype(np.float64)
    s = (2.0 * gxy).astype(np.float64)
    norm = np.hypot(c, s)
    total = (gxx + gyy).astype(np.float64)
    safe = np.where(norm > 0, norm, 1.0)
    cos2 = np.where(norm > 0, c / safe, 0.0)
    sin2 = np.where(norm > 0, s / safe, 0.0)
    coherence = np.where(total > 0, norm / np.where(total > 0, total, 1.0), 0.0)
    return RidgeFlow(cos2=np.ascontiguousarray(cos2), sin2=np.ascontiguousarray(sin2),
                     coherence=np.ascontiguousarray(coherence), cell_px=int(cell_px) * factor)


def uniform_ridge_flow(shape: tuple[int, int], *, ridge_angle_deg: float, cell_px: int = 4) -> RidgeFlow:
    """A flow whose ridges run everywhere along ``ridge_angle_deg`` (x = column, y = row), covering an image of
    ``shape`` (H, W): for synthetic skeletons and tests."""
    h, w = shape
    n = (max(-(-h // cell_px), 1), max(-(-w // cell_px), 1))
    phi = math.radians(ridge_angle_deg + 90.0)
    return RidgeFlow(cos2=np.full(n, math.cos(2 * phi)), sin2=np.full(n, math.sin(2 * phi)), coherence=np.ones(n),
                     cell_px=int(cell_px))


@njit(nogil=True)
def flow_normal_at(cos2, sin2, cell, x, y):  # pragma: no cover - compiled
    """(cos 2 phi, sin 2 phi) of the ridges' normal at the full-resolution point (x, y): the nearest cell."""
    h, w = cos2.shape
    j = int(math.floor((x + 0.5) / cell))
    i = int(math.floor((y + 0.5) / cell))
    j = min(max(j, 0), w - 1)
    i = min(max(i, 0), h - 1)
    return cos2[i, j], sin2[i, j]
