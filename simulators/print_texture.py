"""A real fingerprint image as the skin's texture: loading, polarity, segmentation, resampling to the rig.

A scene with ``texture`` renders a user's own print instead of the synthetic one: contact, deformation, optics
and noise are the scene's, and the displacement and strain truth is as exact as with a synthetic print (it comes
from the deformation model, not from the texture). The features of a real print are not known, so such a scene
has no feature truth: ``skinstretch evaluate`` scores displacement, trajectories and strain and says that features
are not scored.

How an image becomes skin texture (:func:`prepare_print`)
---------------------------------------------------------
1. **Grey levels.** 8- or 16-bit, grey or colour (OpenCV's BGR order; converted to luminance); an alpha channel
   marks where the print is (transparent = no print).
2. **Where the print is.** Fingerprint segmentation by local contrast: the grey-level standard deviation over a
   Gaussian window (sigma 0.3 mm, of the opaque pixels only: a transparent border is no contrast) above 0.3 times
   the print's contrast (its 95th percentile over the pixels with some texture, above a tenth of the image's 99.5th
   percentile, so that a small print on a large blank page is measured against itself), cleaned (opening, holes
   filled, the largest region and any region at least a tenth of it kept), eroded by the window's reach (0.4 mm) and
   0.3 mm more (a print's ragged border, where ridges break up, is not kept) and given a soft 0.1 mm edge. This
   *coverage* multiplies the contact: skin outside the print renders as out of contact (bright glass, no ridges) and
   the truth marks it invalid there. A print smaller than the contact therefore shows a bright hole or border that
   moves with the skin; the renderer logs how much of the contact in view the print covers.
3. **Polarity.** The scene renders FTIR polarity: ridges in contact dark, valleys bright (FACTS). Ink prints and
   live scans have the same polarity (dark ridges on a bright background). ``auto`` reads it from the background
   around the print, which has the valleys' level (paper, or glass the skin does not touch): nearer the print's
   bright end (90th percentile) than its dark end (10th) means dark ridges (kept), else bright ridges (inverted);
   the print's median would not do (the thin, broken ridges of a faint print leave it at the background's level).
   When the print fills the image (no background to compare with), ``auto`` assumes dark ridges and logs it;
   ``dark_ridges`` or ``bright_ridges`` says it explicitly.
4. **Contrast.** Uneven inking or pressure is levelled: the grey levels are standardised by their local mean and
   standard deviation (Gaussian, sigma 1 mm, within the print) and mapped to [0, 1] (0 = ridge, 1 = valley) with
   the 1st and 99th percentiles of the print at the ends.
5. **Resolution.** The print's ridge period is estimated from its spectrum and logged; a period outside
   0.3-0.7 mm (FACTS: 0.43 mm median, IQR 0.39-0.46) is warned about: the ``dpi`` is probably wrong. The print is
   resampled to the renderer's master grid (the rig's ~62 px/mm times its oversampling) by bicubic
   interpolation (a 500 dpi print is upsampled ~6x; a print finer than the master grid is low-pass filtered first).
   A 500 dpi print does not resolve pores, so the texture has none.

Hand-written: no library segments fingerprint images or maps them to a rendering grid in skin coordinates.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from scipy import ndimage as ndi

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.texture_gate import PLAUSIBLE_RIDGE_PERIOD_MM, ridge_period_mm
from skinstretch.simulators.deformation import rotation_matrix

log = logging.getLogger(__name__)

Polarity = Literal["auto", "dark_ridges", "bright_ridges"]

_SEGMENT_SIGMA_MM = 0.3
_SEGMENT_THRESHOLD = 0.3
_TEXTURED = 0.1  # pixels with "some texture": contrast above this fraction of the image's (99.5th percentile)
_BORDER_EROSION_MM = 0.3
_COVERAGE_EDGE_MM = 0.1
_LEVEL_SIGMA_MM = 1.0


@dataclass(frozen=True)
class PrintImage:
    """A real print made ready to render (see the module doc).

    Attributes
    ----------
    brightness : (H, W) float32
        0 at a ridge, 1 at a valley (FTIR polarity), on the image's own pixel grid.
    coverage : (H, W) float32
        1 where the print is, 0 where it is not, soft at the edge.
    px_per_mm : float
        Resolution of the image (dpi / 25.4).
    polarity : str
        The polarity of the image as given: "dark_ridges" or "bright_ridges" (inverted to FTIR).
    ridge_period_mm : float
        Ridge period estimated from the spectrum (NaN if there is no clear peak).
    name, sha256 : str
        Where it came from, and the hash of the file (or array) it was made from.
    """

    brightness: np.ndarray
    coverage: np.ndarray
    px_per_mm: float
    polarity: str
    ridge_period_mm: float
    name: str
    sha256: str

    @property
    def centre_px(self) -> tuple[float, float]:
        """(x, y) of the coverage's centroid, image pixels."""
        w = self.coverage.astype(np.float64)
        total = w.sum()
        rows, cols = np.indices(w.shape)
        return float((cols * w).sum() / total), float((rows * w).sum() / total)

    @property
    def area_mm2(self) -> float:
        """Area the print covers."""
        return float(self.coverage.sum()) / self.px_per_mm**2


def load_print(image: str | os.PathLike, *, dpi: float | None = None, polarity: Polarity = "auto") -> PrintImage:
    """A print from a built-in name (:data:`skinstretch.simulators.prints.PRINT_NAMES`) or an image file.

    ``dpi`` defaults to the built-in print's, and must be given for a file (the image's own metadata is not
    trusted: scanners often write 72 or 96).
    """
    from skinstretch.simulators.prints import PRINT_NAMES, PRINTS, print_path  # noqa: PLC0415

    key = str(image)
    if key in PRINTS:
        path, default_dpi = print_path(key), PRINTS[key][1]
        name = key
    else:
        path, default_dpi, name = Path(image), None, Path(image).name
        if path.is_dir():
            raise InvalidInputError(f"{path}: is a folder; give a print image file (PNG, TIFF, JPEG, ...)")
        if not path.is_file():
            raise InvalidInputError(f"{path}: no such print image, and not a built-in print "
                                    f"(known: {', '.join(PRINT_NAMES)})")
    dpi = default_dpi if dpi is None else dpi
    if dpi is None:
        raise InvalidInputError(f"{path}: give the print's resolution (dpi), e.g. 500")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise InvalidInputError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not raw:
        raise InvalidInputError(f"{path}: the file is empty, not an image")
    try:
        pixels = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        pixels = None
    if pixels is None or pixels.size == 0:
        raise InvalidInputError(f"{path}: not an image OpenCV can read")
    return prepare_print(pixels, dpi=dpi, polarity=polarity, name=name, sha256=hashlib.sha256(raw).hexdigest())


def prepare_print(
    pixels: np.ndarray, *, dpi: float, polarity: Polarity = "auto", name: str = "array", sha256: str | None = None
) -> PrintImage:
    """Make an image array (grey, BGR or BGRA; uint8, uint16 or float in [0, 1]) ready to render (module doc)."""
    if not (np.isfinite(dpi) and 100 <= dpi <= 10000):
        raise InvalidInputError(f"dpi must be in [100, 10000], got {dpi!r}")
    if polarity not in ("auto", "dark_ridges", "bright_ridges"):
        raise InvalidInputError(f"polarity must be auto, dark_ridges or bright_ridges, got {polarity!r}")
    a = np.asarray(pixels)
    if sha256 is None:
        sha256 = hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()
    grey, alpha = _grey_and_alpha(a)
    if min(grey.shape) < 16:
        raise InvalidInputError(f"print image {name} is too small ({grey.shape[1]} x {grey.shape[0]} px)")
    ppm = float(dpi) / 25.4
    mask = _segment(grey, alpha, ppm)
    if mask.sum() < (1.0 * ppm) ** 2:
        raise InvalidInputError(f"print image {name}: no fingerprint found (no region of ridges of 1 mm^2 or more)")
    opaque = alpha > 0.5
    around = ~ndi.binary_dilation(mask, iterations=max(1, int(round(0.5 * ppm)))) & opaque
    # The contrast window reaches ~1.3 sigma beyond the print (where the threshold is met), then the ragged border.
    erosion_mm = _BORDER_EROSION_MM + 1.3 * _SEGMENT_SIGMA_MM
    inside = ndi.binary_erosion(mask, iterations=max(1, int(round(erosion_mm * ppm))))
    if not inside.any():
        inside = mask
    if polarity == "auto":
        if around.sum() >= 0.02 * opaque.sum():
            # The background is the level of the valleys (paper, or glass the skin does not touch), one end of the
            # print's grey levels, whatever share of the print the ridges take (thin broken ridges of a faint print
            # leave its median at the background's level).
            background = np.median(grey[around])
            dark_end, bright_end = np.percentile(grey[mask], [10, 90])
            polarity = "dark_ridges" if bright_end - background < background - dark_end else "bright_ridges"
        else:
            log.info("%s: the print fills the image (no background to compare with): assuming dark ridges, the "
                     "ink and live-scan convention; give the polarity to override", name)
            polarity = "dark_ridges"
    if polarity == "bright_ridges":
        grey = 1.0 - grey
    brightness = _levelled(grey, inside, ppm)
    coverage = ndi.gaussian_filter(inside.astype(np.float32), _COVERAGE_EDGE_MM * ppm / 2.0)
    coverage = np.clip((coverage - 0.5) * 2.0 + 0.5, 0.0, 1.0) * alpha
    period = ridge_period_mm(brightness, px_per_mm=ppm, window=ndi.gaussian_filter(inside.astype(np.float64), 2.0))
    lo, hi = PLAUSIBLE_RIDGE_PERIOD_MM
    if not lo <= period <= hi:
        log.warning("%s: ridge period %.2f mm at %g dpi, far from a fingertip's 0.43 mm: is the dpi right?",
                    name, period, dpi)
    else:
        log.info("%s: %g dpi, %s, %.0f mm^2 of print, ridge period %.2f mm", name, dpi, polarity,
                 float(coverage.sum()) / ppm**2, period)
    return PrintImage(brightness.astype(np.float32), coverage.astype(np.float32), ppm, polarity, period, name, sha256)


def _grey_and_alpha(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grey levels in [0, 1] (float64) and alpha in [0, 1]."""
    if a.dtype == np.uint8:
        f = a.astype(np.float64) / 255.0
    elif a.dtype == np.uint16:
        f = a.astype(np.float64) / 65535.0
    elif np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)):
            raise InvalidInputError("print image has NaN or infinite values")
        f = np.clip(a.astype(np.float64), 0.0, 1.0)
    else:
        raise InvalidInputError(f"print image must be uint8, uint16 or float, got {a.dtype}")
    if f.ndim == 2:
        return f, np.ones_like(f)
    if f.ndim != 3 or f.shape[2] not in (1, 2, 3, 4):
        raise InvalidInputError(f"print image must be (H, W) or (H, W, 1-4 channels), got shape {a.shape}")
    channels = f.shape[2]
    alpha = f[..., -1] if channels in (2, 4) else np.ones(f.shape[:2])
    colour = f[..., : 3 if channels >= 3 else 1]
    grey = colour[..., 0] if colour.shape[2] == 1 else colour @ np.array([0.114, 0.587, 0.299])  # BGR luminance
    return grey, alpha


def _local_std(grey: np.ndarray, sigma: float, weight: np.ndarray) -> np.ndarray:
    """Grey-level standard deviation over a Gaussian window, of the pixels of ``weight`` (1 opaque, 0 transparent:
    the edge of a transparent background is no contrast)."""
    norm = np.maximum(ndi.gaussian_filter(weight, sigma), 1e-6)
    m = ndi.gaussian_filter(grey * weight, sigma) / norm
    m2 = ndi.gaussian_filter(grey * grey * weight, sigma) / norm
    return np.sqrt(np.maximum(m2 - m * m, 0.0)) * (weight > 0.5)


def _segment(grey: np.ndarray, alpha: np.ndarray, ppm: float) -> np.ndarray:
    """Where the print has ridges: local contrast, cleaned (module doc, 2)."""
    spread = _local_std(grey, _SEGMENT_SIGMA_MM * ppm, (alpha > 0.5).astype(np.float64))
    # The reference contrast is the print's, not the background's: the 95th percentile over the pixels with some
    # texture (a small print on a large blank page leaves the image's 95th percentile in the background).
    textured = spread > _TEXTURED * np.percentile(spread, 99.5)
    ref = np.percentile(spread[textured], 95) if textured.any() else 0.0
    if ref <= 1e-6:
        return np.zeros(grey.shape, bool)
    mask = spread > _SEGMENT_THRESHOLD * ref
    r = max(1, int(round(0.2 * ppm)))
    disk = np.hypot(*np.mgrid[-r : r + 1, -r : r + 1]) <= r
    mask = ndi.binary_fill_holes(ndi.binary_opening(mask, structure=disk))
    labels, n = ndi.label(mask)
    if n > 1:
        sizes = ndi.sum(mask, labels, index=np.arange(1, n + 1))
        mask = np.isin(labels, 1 + np.nonzero(sizes >= 0.1 * sizes.max())[0])
    return mask


def _levelled(grey: np.ndarray, inside: np.ndarray, ppm: float) -> np.ndarray:
    """Standardised by local mean and deviation within the print, mapped to [0, 1] by its 1st/99th percentiles."""
    sigma = _LEVEL_SIGMA_MM * ppm
    w = inside.astype(np.float64)
    norm = np.maximum(ndi.gaussian_filter(w, sigma), 1e-6)
    mean = ndi.gaussian_filter(grey * w, sigma) / norm
    var = ndi.gaussian_filter((grey - mean) ** 2 * w, sigma) / norm
    z = (grey - mean) / np.sqrt(np.maximum(var, 1e-8))
    lo, hi = np.percentile(z[inside], [1, 99])
    return np.clip((z - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


class RealPrintTexture:
    """A :class:`PrintImage` laid on the skin: its centre at ``center_mm`` (skin coordinates), turned by
    ``rotation_deg`` counter-clockwise on the image. It renders like a synthetic
    :class:`~skinstretch.simulators.fingerprint.Fingerprint` and has no feature truth."""

    def __init__(self, image: PrintImage, *, center_mm: tuple[float, float], rotation_deg: float = 0.0) -> None:
        self.image = image
        self.center_mm = (float(center_mm[0]), float(center_mm[1]))
        self.rotation_deg = float(rotation_deg)
        self._rot = rotation_matrix(self.rotation_deg)
        self._centre_px = image.centre_px

    def _print_px(self, X: np.ndarray) -> np.ndarray:
        """Print-image (x, y) px of skin points X (..., 2) mm."""
        rel = (np.asarray(X, dtype=np.float64) - self.center_mm) @ self._rot  # R^T applied to row vectors
        return rel * self.image.px_per_mm + self._centre_px

    def _grid_maps(self, u0, s0, step_mm, shape) -> tuple[np.ndarray, np.ndarray]:
        ny, nx = shape
        uu, ss = np.meshgrid(u0 + step_mm * np.arange(nx), s0 + step_mm * np.arange(ny))
        p = self._print_px(np.stack([uu, ss], -1))
        return p[..., 0].astype(np.float32), p[..., 1].astype(np.float32)

    def render(self, *, u0: float, s0: float, step_mm: float, shape: tuple[int, int]) -> np.ndarray:
        """Brightness (0 ridge, 1 valley) on a regular skin grid, float32; pixel ``(i, j)`` is the skin point
        ``(u0 + j * step_mm, s0 + i * step_mm)``. Beyond the image it is mirrored (the coverage is 0 there)."""
        src = self.image.brightness
        ratio = step_mm * self.image.px_per_mm  # print pixels per grid pixel
        if ratio > 1.0:  # coarser than the print: low-pass first (no aliasing)
            src = cv2.GaussianBlur(src, (0, 0), 0.5 * ratio)
        mx, my = self._grid_maps(u0, s0, step_mm, shape)
        out = cv2.remap(src, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101)
        return np.clip(out, 0.0, 1.0).astype(np.float32)

    def render_coverage(self, *, u0: float, s0: float, step_mm: float, shape: tuple[int, int]) -> np.ndarray:
        """Coverage (1 where the print is) on the same grid as :meth:`render`, float32; 0 beyond the image."""
        mx, my = self._grid_maps(u0, s0, step_mm, shape)
        out = cv2.remap(self.image.coverage, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return np.clip(out, 0.0, 1.0).astype(np.float32)

    def coverage_at(self, X: np.ndarray) -> np.ndarray:
        """Coverage at skin points X (..., 2) mm (bilinear, 0 beyond the image)."""
        p = self._print_px(X)
        flat = p.reshape(-1, 2)
        c = ndi.map_coordinates(self.image.coverage, [flat[:, 1], flat[:, 0]], order=1, mode="constant", cval=0.0)
        return c.reshape(p.shape[:-1])

    def features(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """No feature truth for a real print: empty (ids, kinds, skin positions)."""
        return np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros((0, 2))
