"""Pre-processing of FTIR fingerprint frames (seed 3.5, 4.1-4.4): smoothing, light, local average, contact
(the background), binarization.

Polarity: ridges in contact are DARK, valleys, pores and the uncovered prism (the background) are BRIGHT. The
binary image of :func:`binarize` has the valleys and pores as foreground (255), because the seed's skeleton is the
valley skeleton.

The local statistics (the seed's local average of 4.2 and local variance of 4.3, and the light of 3.5) are taken at
the scale of one ridge period on a grid of cells an eighth of a period wide: Gaussian filters of a few cells, then
brought back to full resolution bilinearly. Like the seed's Appendix B running sums, they cost the same whatever
the window, and the local variance is known everywhere, not on the seed's grid of a hundred squares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from skinstretch.processing.errors import InvalidInputError

__all__ = [
    "check_frame", "smooth", "binarize", "RidgeStatistics", "ridge_statistics", "contact_map", "flatten_light",
]


def check_frame(frame: np.ndarray, *, name: str = "frame", min_size: int = 1) -> np.ndarray:
    """Return ``frame`` if it is a 2-D uint8 image at least ``min_size`` pixels on each side, else raise."""
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim != 2:
        got = f"{getattr(frame, 'dtype', type(frame).__name__)} {getattr(frame, 'shape', '')}"
        raise InvalidInputError(f"{name} must be a 2-D uint8 image, got {got}")
    if min(frame.shape) < min_size:
        raise InvalidInputError(f"{name} of shape {frame.shape} is smaller than the {min_size}-px window it needs")
    return frame


def _odd_window(width_px: int, name: str) -> int:
    if not isinstance(width_px, (int, np.integer)) or width_px < 1 or width_px % 2 == 0:
        raise InvalidInputError(f"{name} must be a positive odd number of pixels, got {width_px!r}")
    return int(width_px)


def smooth(frame: np.ndarray, *, sigma_px: float, kernel_px: int) -> np.ndarray:
    """Gaussian low-pass filter (seed 4.1, eq. 4.1: sigma 1 px, kernel 3 px at the seed's scale).

    Parameters
    ----------
    frame : (H, W) uint8
    sigma_px : float
        Standard deviation of the Gaussian, pixels (> 0).
    kernel_px : int
        Odd kernel width, pixels.

    Returns
    -------
    (H, W) float32
        The smoothed image. Float keeps the sub-grey-level information the sub-pixel steps use.

    Examples
    --------
    >>> import numpy as np
    >>> float(smooth(np.full((5, 5), 7, np.uint8), sigma_px=1.0, kernel_px=3)[2, 2])
    7.0
    """
    check_frame(frame, min_size=kernel_px)
    if not np.isfinite(sigma_px) or sigma_px <= 0:
        raise InvalidInputError(f"sigma_px must be positive, got {sigma_px!r}")
    k = _odd_window(kernel_px, "kernel_px")
    # The separable Gaussian straight from uint8 to float32: the kernel of cv2.GaussianBlur, ~7x less CPU than
    # GaussianBlur on a float copy of the frame (results differ by float rounding only, < 1e-4 grey levels).
    g = cv2.getGaussianKernel(k, float(sigma_px), cv2.CV_32F)
    return cv2.sepFilter2D(frame, cv2.CV_32F, g, g, borderType=cv2.BORDER_REFLECT)


def binarize(
    smoothed: np.ndarray,
    *,
    local_average: np.ndarray,
    scale: float = 1.0,
    background: np.ndarray | None = None,
) -> np.ndarray:
    """Valleys and pores as foreground: pixels brighter than ``scale`` times the local average (seed 4.4).

    Parameters
    ----------
    smoothed : (H, W) float32
    local_average : (H, W) float32
        The local mean map (seed 4.2, ~2 mm window) used as a pixel-wise threshold.
    scale : float
        The seed's user-defined factor applied to the local average (1 = the plain local mean).
    background : (H, W) bool, optional
        Background pixels are set to black (seed 4.3), so no valley is found there.

    Returns
    -------
    (H, W) uint8
        255 on valleys and pores, 0 on ridges and background.
    """
    if smoothed.shape != local_average.shape:
        raise InvalidInputError(f"local_average shape {local_average.shape} differs from the image's {smoothed.shape}")
    if not np.isfinite(scale) or scale <= 0:
        raise InvalidInputError(f"scale must be positive, got {scale!r}")
    thr = local_average if scale == 1.0 else cv2.multiply(local_average, float(scale))
    binary = cv2.compare(smoothed.astype(np.float32, copy=False), thr, cv2.CMP_GT)
    if background is not None:
        if background.shape != smoothed.shape:
            raise InvalidInputError(f"background shape {background.shape} differs from the image's {smoothed.shape}")
        # Through OpenCV (no boolean-mask indexing: that holds the GIL for a whole-frame scan).
        bg = np.ascontiguousarray(background if background.dtype == np.bool_ else background != 0)
        foreground = cv2.compare(bg.view(np.uint8), 0, cv2.CMP_EQ)
        binary = cv2.bitwise_and(binary, foreground)
    return binary


@dataclass(frozen=True)
class RidgeStatistics:
    """Local statistics of a frame at the scale of one ridge period (see :func:`ridge_statistics`).

    Attributes
    ----------
    mean : (H, W) float32
        Local mean, full resolution (the binarization threshold).
    cell_image : (h, w) float32
        The image averaged over each of the ``cell_px`` x ``cell_px`` cells of the grid (not smoothed further).
    cell_mean, cell_std : (h, w) float32
        Local mean and standard deviation on the grid.
    cell_px : int
        Cell size of the grid.
    """

    mean: np.ndarray
    cell_image: np.ndarray
    cell_mean: np.ndarray
    cell_std: np.ndarray
    cell_px: int


def ridge_statistics(smoothed: np.ndarray, *, sigma_px: float, cell_px: int = 4) -> RidgeStatistics:
    """Gaussian-weighted local mean and standard deviation of ``smoothed`` with a standard deviation of half a ridge
    period (the ridge pattern's own frequency is then damped ~140 times, so the mean follows the brightness of the
    skin, not its ridges).

    Beyond the seed (4.2 uses a 2 mm mean): partial contact over a ridge or a valley of the surface and the light
    change the brightness over a few tenths of a millimetre, and a 2 mm mean then puts whole bands of ridges above
    or below the threshold. The statistics vary slowly, so they are computed on a grid of ``cell_px`` pixel cells
    (exact cell means of the image) and the mean is brought back to full resolution bilinearly.

    Parameters
    ----------
    smoothed : (H, W) float32
    sigma_px : float
        Standard deviation of the Gaussian window, full-resolution pixels (> 0).
    cell_px : int
        Cell size of the grid (1 = every pixel).
    """
    if smoothed.ndim != 2:
        raise InvalidInputError(f"smoothed must be a 2-D image, got shape {smoothed.shape}")
    if not (np.isfinite(sigma_px) and sigma_px > 0):
        raise InvalidInputError(f"sigma_px must be positive, got {sigma_px!r}")
    if not isinstance(cell_px, (int, np.integer)) or cell_px < 1:
        raise InvalidInputError(f"cell_px must be a positive integer, got {cell_px!r}")
    h, w = smoothed.shape
    img = smoothed.astype(np.float32, copy=False)
    size = (max(w // cell_px, 1), max(h // cell_px, 1))
    cells = cv2.resize(img, size, interpolation=cv2.INTER_AREA) if cell_px > 1 else img
    sg = float(sigma_px) / cell_px
    k = 2 * int(math.ceil(3.0 * sg)) + 1
    m1 = cv2.GaussianBlur(cells, (k, k), sg, borderType=cv2.BORDER_REFLECT)
    # Twicing (Tukey): the mean of what the first mean left. A Gaussian mean lags where the brightness curves
    # (across a band of partial contact: ~0.16 of the band's depth at its centre with the valleyL surface); the
    # second pass removes that bias to the next order while the ridge frequency stays damped ~70 times.
    m = m1 + cv2.GaussianBlur(cells - m1, (k, k), sg, borderType=cv2.BORDER_REFLECT)
    # The local standard deviation about the first mean (the contact map compares it with the mean).
    var = cv2.subtract(cv2.GaussianBlur(cells * cells, (k, k), sg, borderType=cv2.BORDER_REFLECT), m1 * m1)
    np.maximum(var, 0.0, out=var)
    std = cv2.sqrt(var)
    if cell_px > 1:
        # Cell centres sit at (i + 0.5) * cell - 0.5 in full-resolution pixels: cv2.resize's own convention.
        full = cv2.resize(m, (w, h), interpolation=cv2.INTER_LINEAR)
    else:
        full = m
    return RidgeStatistics(mean=full, cell_image=cells, cell_mean=m, cell_std=std, cell_px=int(cell_px))


#: Where the bright envelope is below this fraction of the frame's (its 90th percentile) the glass is not lit: the
#: light is not divided out there and it is no contact (FTIR: valleys in contact are nearly as bright as the glass).
DARK_ENVELOPE_FRACTION = 0.25


def contact_map(stats: RidgeStatistics, *, shape: tuple[int, int], min_contact: float, min_extent_px: float = 0.0,
                texture_floor: float = 0.1, reference_percentile: float = 90.0) -> tuple[np.ndarray, float]:
    """Where the skin touches the glass: contact fraction from the local contrast, and the background mask.

    FTIR model (seed 3.2): the camera sees ``g (B + c (S - B))``, the bright glass ``B`` blended with the skin's
    ridge/valley pattern ``S`` by the contact fraction ``c`` and multiplied by the light's gain ``g``. The valleys
    are nearly as bright as the bare glass, so the local relative contrast
    ``kappa = (valley - ridge) / valley`` is ``c`` times that of full contact, whatever the gain: it does not
    depend on vignetting, the slope's darkening or the exposure. ``valley`` and ``ridge`` are taken as mean +/-
    sqrt(2) std (a sinusoid's envelope) at the ridge scale, and full contact's ``kappa`` is the frame's
    ``reference_percentile``-th percentile over the textured cells (``kappa > texture_floor``; the bare glass
    gives ~0.05). Cells with ``c < min_contact`` are background, except an island of them inside the image
    narrower than ``min_extent_px`` on both axes: bare glass is the outside of the fingertip, or a band of the
    surface that the skin does not reach, and either reaches far; a small island is skin whose pattern has few
    ridges there (a wide valley round a minutia, in partial contact), and calling it background would delete the
    minutia that makes it.

    Returns
    -------
    background : (H, W) bool
        True where the contact fraction is below ``min_contact`` (the cells' contrast upsampled bilinearly).
    reference : float
        Full contact's relative contrast in this frame (``nan`` when no cell is textured: all background).
    """
    m, s = stats.cell_mean, stats.cell_std
    env = cv2.scaleAdd(s, math.sqrt(2.0), m)
    kappa = cv2.divide(s, np.maximum(env, 1.0), scale=2.0 * math.sqrt(2.0))
    # A dark surround (a black background, a print smaller than the frame) is not lit skin, whatever its noise's
    # relative contrast: FTIR's valleys in contact are nearly as bright as the glass.
    kappa[env < DARK_ENVELOPE_FRACTION * float(np.percentile(env, 90))] = 0.0
    textured = kappa[kappa > texture_floor]
    h, w = shape
    if textured.size == 0:
        return np.ones((h, w), dtype=bool), float("nan")
    reference = float(np.percentile(textured, reference_percentile))
    threshold = min_contact * reference
    islands = None
    if min_extent_px > 0:
        cell = (h / kappa.shape[0] + w / kappa.shape[1]) / 2
        low = cv2.compare(kappa, threshold, cv2.CMP_LT)
        n, labels, box, _ = cv2.connectedComponentsWithStats(low, connectivity=4)
        bh, bw = kappa.shape
        x0, y0, bx, by = box[:, 0], box[:, 1], box[:, 2], box[:, 3]
        small = (np.maximum(bx, by) * cell < min_extent_px) & (x0 > 0) & (y0 > 0) & (x0 + bx < bw) & (y0 + by < bh)
        small[0] = False  # label 0: the contact
        if small.any():
            islands = cv2.dilate(small[labels].view(np.uint8), np.ones((3, 3), np.uint8))  # and their rim cells
    if kappa.shape != (h, w):
        # Thresholded after a bilinear upsampling: the outline moves smoothly with the image instead of by whole
        # cells (a cell flipping moved the fingertip's outline, and the features near it, by a few pixels).
        kappa = cv2.resize(kappa, (w, h), interpolation=cv2.INTER_LINEAR)
    background = cv2.compare(kappa, threshold, cv2.CMP_LT)
    if islands is not None:
        if islands.shape != (h, w):
            islands = cv2.resize(islands, (w, h), interpolation=cv2.INTER_NEAREST)
        background[islands > 0] = 0
    return background.view(bool), reference


def flatten_light(smoothed: np.ndarray, *, cell_px: int, window_px: float, sigma_px: float) -> np.ndarray:
    """``smoothed`` divided by the light that falls on it, estimated from the frame alone (seed 3.5 per frame).

    The valleys and pores are almost as bright as the bare glass whatever the contact (FTIR, seed 3.2), so the
    upper envelope of the frame (its local maximum over ``window_px``, about a ridge period, smoothed by a Gaussian
    of ``sigma_px``) is the light times a constant. Dividing by it removes the light's slow changes (vignetting,
    a surface slope's darkening) that tilt a pore's or a minutia's brightness and pull its centre uphill; the
    result is scaled so the envelope becomes 255 (the seed's eq. 3.7 without the clip). Computed on the grid of
    ``cell_px`` cell means.
    """
    h, w = smoothed.shape
    size = (max(w // cell_px, 1), max(h // cell_px, 1))
    cells = cv2.resize(smoothed, size, interpolation=cv2.INTER_AREA) if cell_px > 1 else smoothed
    kd = max(int(round(window_px / cell_px)) | 1, 3)
    env = cv2.dilate(cells, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kd, kd)))
    sg = float(sigma_px) / cell_px
    k = 2 * int(math.ceil(3.0 * sg)) + 1
    env = cv2.GaussianBlur(env, (k, k), sg, borderType=cv2.BORDER_REFLECT)
    # Not lit where darker than a fraction of the frame's light (a black surround): left dark, its noise unamplified.
    floor = max(1.0, DARK_ENVELOPE_FRACTION * float(np.percentile(env, 90)))
    gain = cv2.divide(np.full_like(env, 255.0), np.maximum(env, floor))
    if cell_px > 1:
        gain = cv2.resize(gain, (w, h), interpolation=cv2.INTER_LINEAR)
    return cv2.multiply(smoothed, gain)
