"""Is there fingerprint texture in contact in this frame? A gate both motion methods pass every frame through.

A frame without a print in contact (camera noise, a blank or black frame, a saturated one, a print out of focus)
must be flagged with a named reason, and no motion or strain may be measured from it: noise registers against
noise as happily as a print against a print.

The test is physical. In FTIR a print in contact is a field of dark ridges, nearly parallel over a millimetre,
with a period of about 0.43 mm. So, per block of 3.5 ridge periods (~1.5 mm), on the frame reduced until a period
spans 6-12 px:

* **orientation coherence** of the ridge band (structure tensor, ``(l1 - l2) / (l1 + l2)``): ridges keep one
  orientation over a block, band-limited isotropic noise does not;
* **ridge-band energy**: a difference of Gaussians tuned to the ridge period keeps the ridge band, where a print
  puts a large share of its detail energy; a straight edge or an out-of-focus print almost none;
* **amplitude**: the ridge band must stand above the camera's noise.

A block is *textured* when all three hold; a frame passes when its textured blocks cover at least
``min_textured_mm2``. Otherwise the reason is ``out_of_focus`` when the blocks that show any structure hold most
of their energy below the ridge band, else ``no_texture``. Exposure comes first: ``all_black`` and ``saturated``,
as the feature extraction defines them (seed 4 frame checks). The measured figures: docs/tuning-log.md.

Hand-written because no library offers a fingerprint-quality measure on the seed's FTIR images (NIST NFIQ is a
C program scoring ink prints for matching, not motion); the measures themselves are OpenCV filters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from pydantic import Field

from skinstretch.processing.argument_checks import positive_number
from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import FiniteFloat, PositiveFloat, validated_dataclass

__all__ = ["TextureGateParams", "TextureVerdict", "EXPOSURE_REASONS", "TEXTURE_REASONS", "PLAUSIBLE_RIDGE_PERIOD_MM",
           "ridge_period_mm", "exposure_reason",
           "texture_verdict"]

#: Reasons of the exposure checks (tested first), then of the texture test.
EXPOSURE_REASONS = ("all_black", "saturated")
TEXTURE_REASONS = ("out_of_focus", "no_texture")


@validated_dataclass
class TextureGateParams:
    """Options of the texture gate, in mm and grey levels (see the module docstring for where each comes from).

    Parameters
    ----------
    ridge_period_mm : float
        Ridge period the band is tuned to (0.43 mm median; the band is ~1.5 octaves wide, so 0.3-0.6 mm pass).
    block_periods : float
        Side of a block in ridge periods (3.5: noise coherence <= 0.42; 2.5 let noise reach 0.62).
    min_coherence : float
        Orientation coherence a textured block must reach (prints 0.85 at the 5th percentile, noise <= 0.42).
    min_band_fraction : float
        Share of the block's detail energy in the ridge band (prints 0.21 at the 5th percentile; edges and blur
        less).
    min_band_rms : float
        Ridge-band amplitude, grey levels (camera noise leaves ~0.2, ridges tens).
    min_textured_mm2 : float
        Textured area a frame needs to pass.
    structure_rms : float
        Detail amplitude (grey levels) below which a block counts as flat when naming the reason (only an
        exactly uniform block is below 0.1: camera noise alone gives ~0.4 at the working resolution).
    black_level, saturated_fraction : float
        Exposure checks, as :class:`skinstretch.processing.extraction.ExtractionParams` defines them.
    """

    ridge_period_mm: PositiveFloat = 0.43
    block_periods: PositiveFloat = 3.5
    min_coherence: FiniteFloat = Field(default=0.6, gt=0, lt=1)
    min_band_fraction: FiniteFloat = Field(default=0.12, gt=0, lt=1)
    min_band_rms: PositiveFloat = 2.0
    min_textured_mm2: PositiveFloat = 4.0
    structure_rms: PositiveFloat = 0.1
    black_level: FiniteFloat = Field(default=20.0, ge=0, le=255)
    saturated_fraction: FiniteFloat = Field(default=0.5, gt=0, le=1)


_DEFAULT_PARAMS = TextureGateParams()


@dataclass(frozen=True)
class TextureVerdict:
    """What the gate found in one frame. ``reason`` is "" when the frame has fingerprint texture in contact."""

    reason: str
    textured_mm2: float  # area of the textured blocks
    blocks: int  # blocks examined (0 when an exposure check decided)
    textured_blocks: int

    @property
    def ok(self) -> bool:
        return not self.reason


def exposure_reason(frame: np.ndarray, *, black_level: float = 20.0, saturated_fraction: float = 0.5) -> str:
    """``"all_black"``, ``"saturated"`` or ``""``: the exposure checks of a 2-D uint8 frame."""
    brightest = cv2.minMaxLoc(frame)[1]
    if brightest < black_level:
        return "all_black"
    if brightest == 255 and cv2.countNonZero(cv2.compare(frame, 255, cv2.CMP_EQ)) > saturated_fraction * frame.size:
        return "saturated"
    return ""


def texture_verdict(frame: np.ndarray, *, px_per_mm: float, params: TextureGateParams | None = None) -> TextureVerdict:
    """Check one 2-D uint8 grey frame for fingerprint texture in contact (see the module docstring).

    Examples
    --------
    >>> import numpy as np
    >>> noise = np.random.default_rng(0).integers(0, 256, (240, 320)).astype(np.uint8)
    >>> texture_verdict(noise, px_per_mm=62.0).reason
    'no_texture'
    >>> y, x = np.mgrid[0:240, 0:320]
    >>> ridges = (128 + 60 * np.cos(2 * np.pi * (0.8 * x + 0.6 * y) / (0.43 * 62.0))).astype(np.uint8)
    >>> texture_verdict(ridges, px_per_mm=62.0).ok
    True
    """
    p = _DEFAULT_PARAMS if params is None else params
    px_per_mm = positive_number(px_per_mm, "px_per_mm")
    frame = np.asarray(frame)
    if frame.ndim != 2 or frame.dtype != np.uint8:
        raise InvalidInputError(f"frame must be a 2-D uint8 image, got {frame.dtype} {frame.shape}")
    reason = exposure_reason(frame, black_level=p.black_level, saturated_fraction=p.saturated_fraction)
    if reason:
        return TextureVerdict(reason, 0.0, 0, 0)
    m = _block_measures(frame, px_per_mm=px_per_mm, params=p)
    textured = ((m.coherence >= p.min_coherence) & (m.band_fraction >= p.min_band_fraction)
                & (m.e_band >= p.min_band_rms**2))
    n_textured = int(textured.sum())
    area = n_textured * m.block_mm2
    if area >= p.min_textured_mm2:
        return TextureVerdict("", area, int(textured.size), n_textured)
    structured = m.total >= p.structure_rms**2
    reason = "no_texture"
    if np.any(structured) and np.median(m.e_low[structured] / m.total[structured]) > 0.5:
        reason = "out_of_focus"  # structure, but below the ridge band: the blur took the ridges away
    return TextureVerdict(reason, area, int(textured.size), n_textured)


@dataclass(frozen=True)
class _BlockMeasures:
    """Per block: energies (mean squares, grey levels^2) of the three bands, ridge-band coherence, block area."""

    e_high: np.ndarray
    e_band: np.ndarray
    e_low: np.ndarray
    coherence: np.ndarray
    block_mm2: float

    @property
    def total(self) -> np.ndarray:
        return self.e_high + self.e_band + self.e_low

    @property
    def band_fraction(self) -> np.ndarray:
        total = self.total
        return np.divide(self.e_band, total, out=np.zeros_like(total), where=total > 0)


def _block_measures(frame: np.ndarray, *, px_per_mm: float, params: TextureGateParams) -> _BlockMeasures:
    """The gate's measures on blocks of ``params.block_periods`` ridge periods of a 2-D uint8 frame."""
    period = params.ridge_period_mm * px_per_mm
    scale = 1.0
    image = frame
    # Work where a ridge period spans 6-12 px: finer sampling only costs time (pyrDown low-passes before it drops).
    while period / 2 >= 6 and min(image.shape) >= 64:
        image = cv2.pyrDown(image)
        period /= 2
        scale *= 2
    image = image.astype(np.float32)
    block = max(4, int(round(params.block_periods * period)))
    h, w = image.shape
    nby, nbx = h // block, w // block
    if nby < 1 or nbx < 1:
        side = block * scale
        raise InvalidInputError(
            f"frames of {frame.shape[1]}x{frame.shape[0]} px are too small to analyse: the texture check needs at "
            f"least {side:.0f}x{side:.0f} px ({params.block_periods:g} ridge periods at {px_per_mm:g} px/mm; smaller "
            "than one gate block)"
        )
    # A difference of Gaussians sigma / 2 sigma peaks at frequency 0.153 / sigma: sigma = 0.153 period.
    s1 = 0.153 * period
    s2 = 2 * s1
    s3 = period  # below the band: shading, contact edges, a defocused print
    g1 = cv2.GaussianBlur(image, (0, 0), s1)
    g2 = cv2.GaussianBlur(g1, (0, 0), math.sqrt(s2 * s2 - s1 * s1))
    g3 = cv2.GaussianBlur(g2, (0, 0), math.sqrt(s3 * s3 - s2 * s2))
    high, band, low = image - g1, g1 - g2, g2 - g3
    gx = cv2.Sobel(band, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(band, cv2.CV_32F, 0, 1, ksize=3)
    crop = (slice(0, nby * block), slice(0, nbx * block))

    def block_mean(a: np.ndarray) -> np.ndarray:  # area averaging over whole blocks is their exact mean
        return cv2.resize(np.ascontiguousarray(a[crop]), (nbx, nby), interpolation=cv2.INTER_AREA).astype(np.float64)

    jxx, jyy, jxy = block_mean(gx * gx), block_mean(gy * gy), block_mean(gx * gy)
    trace = jxx + jyy
    anisotropy = np.sqrt((jxx - jyy) ** 2 + 4 * jxy**2)
    coherence = np.divide(anisotropy, trace, out=np.zeros_like(trace), where=trace > 0)
    e_high, e_band, e_low = block_mean(high * high), block_mean(band * band), block_mean(low * low)
    return _BlockMeasures(e_high, e_band, e_low, coherence, (block * scale / px_per_mm) ** 2)


#: Ridge periods (mm) a fingertip's print plausibly has (median 0.43 mm, IQR 0.39-0.46 mm: module doc); outside
#: them the image's scale (dpi, px/mm) is more likely wrong than the finger.
PLAUSIBLE_RIDGE_PERIOD_MM = (0.3, 0.7)


def ridge_period_mm(image: np.ndarray, *, px_per_mm: float, window: np.ndarray | None = None) -> float:
    """The ridge period of a print image (mm): the radial peak, between 0.17 and 1.25 mm, of its power spectrum,
    each annulus' power weighted by its frequency.

    The weighting: a print's background (mottle, smudges, a latent print's surface, shading, the contact's edge)
    has a natural image's 1/f^2 spectrum, whose power per annulus falls as 1/f and outweighed the ridges' ring in a
    blotchy print (the WSQ test print of the ``wsq`` package read as 1.14 mm instead of 0.40 mm); weighted, it is
    flat and the ring stands out. ``window`` (the image's shape, weights in [0, 1]) tapers the image where the
    print is (default: a Hann window over the whole image); the mean is taken where it exceeds 0.5. NaN when the
    image is too small for the band or flat.
    """
    positive_number(px_per_mm, "px_per_mm")
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise InvalidInputError(f"image must be 2-D, got shape {img.shape}")
    if window is None:
        window = np.outer(np.hanning(img.shape[0]), np.hanning(img.shape[1]))
    inside = window > 0.5
    if not inside.any():
        return float("nan")
    v = (img - img[inside].mean()) * window
    p = np.abs(np.fft.fftshift(np.fft.fft2(v))) ** 2
    h, w = v.shape
    fy, fx = np.meshgrid((np.arange(h) - h // 2) / h, (np.arange(w) - w // 2) / w, indexing="ij")
    f = np.hypot(fx, fy) * px_per_mm  # cycles per mm
    band = (f > 0.8) & (f < 6.0)  # periods 0.17-1.25 mm
    if not band.any():
        return float("nan")
    edges = np.linspace(0.8, 6.0, 105)
    power, _ = np.histogram(f[band], bins=edges, weights=(p * f)[band])
    if not power.max() > 0:  # a flat image
        return float("nan")
    return float(1.0 / (0.5 * (edges[:-1] + edges[1:]))[int(np.argmax(power))])
