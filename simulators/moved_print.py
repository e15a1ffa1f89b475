"""A real print moved by an exactly known field, imaged as a lab would make its own test clip.

No scene simulator: the shipped 500-dpi print (:mod:`skinstretch.simulators.prints`) is resampled to the clip's
pixel scale, laid on a uniform background (white, black or grey) where it has no ridges (its segmentation,
:func:`~skinstretch.simulators.print_texture.load_print`), and frame k samples that picture through the exact
inverse of the field at every pixel (cubic spline, :func:`scipy.ndimage.map_coordinates`; ``cv2.remap`` would round
every source position to 1/32 px). Then the camera-fixed imaging condition: vignetting, Gaussian blur, Gaussian
noise, rounding to 8 bits. Frame 0 is the picture itself.

The field (:class:`ExactField`) maps a point X of frame 0 to frame k as
``x = c + R(k theta) [[1 + k sx, k shear], [0, 1 + k sy]] (B_k(X) - c) + k v``, about the frame's centre c:
a slide v (px a frame), a stretch (a fraction a frame along x and y), a simple shear, a rotation, and an optional
travelling band ``B_k`` (a Gaussian band of stretch along x whose centre moves at a constant speed: material the
band has passed is shifted by ``peak sigma sqrt(2 pi)``). Its inverse is closed-form except through the band,
where Newton's method solves it to 1e-10 px; :meth:`ExactField.between` gives the true displacement of any point of
frame a to frame b, the interface :class:`skinstretch.experiments.evaluation.tracking.TruthField` has.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field
from scipy import ndimage as ndi
from scipy.special import erf

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import (FiniteFloat, NonNegativeFloat, NonNegativeInt, PositiveFloat,
                                                        PositiveInt, Probability, validated_dataclass)

__all__ = ["TravellingBand", "PrintMotion", "ExactField", "ClipConditions", "PrintClip", "MovingPicture",
           "render_print_clip", "BACKGROUND_LEVELS", "PRINT_DPI_PX_PER_MM"]

#: Pixel scale of the shipped 500-dpi prints.
PRINT_DPI_PX_PER_MM = 500.0 / 25.4
#: Grey level of each background.
BACKGROUND_LEVELS = {"white": 235.0, "black": 15.0, "grey": 128.0}
_MID, _HALF_SWING = 128.0, 100.0  # full contrast: ridges 28, valleys 228 (or the reverse)
_NEWTON_TOL_PX = 1e-10


@validated_dataclass
class TravellingBand:
    """A band of stretch along x, Gaussian across (``sigma_mm``), ``peak_strain`` at its centre (a fraction), centred
    ``start_mm`` right of the frame's centre in frame 0 and moving ``speed_mm`` a frame along x."""

    peak_strain: Annotated[float, Field(gt=-0.5, lt=0.5)]  # the inverse's Newton steps converge
    sigma_mm: PositiveFloat
    start_mm: FiniteFloat
    speed_mm: FiniteFloat


@validated_dataclass
class PrintMotion:
    """What moves the print, per frame: slide (px), stretch along x and y and shear (fractions), rotation (rad,
    counter-clockwise on the image), and an optional travelling band."""

    slide_px: tuple[FiniteFloat, FiniteFloat] = (0.0, 0.0)
    stretch: tuple[FiniteFloat, FiniteFloat] = (0.0, 0.0)
    shear: FiniteFloat = 0.0
    rotation_rad: FiniteFloat = 0.0
    band: TravellingBand | None = None


class ExactField:
    """The field of a :class:`PrintMotion` on a clip of ``shape`` (rows, cols) at ``px_per_mm`` (module doc)."""

    def __init__(self, motion: PrintMotion, *, shape: tuple[int, int], px_per_mm: float) -> None:
        self.motion = motion
        self.centre = np.array([(shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0])
        self.px_per_mm = float(px_per_mm)

    def _matrix(self, k: float) -> np.ndarray:
        m = self.motion
        c, s = math.cos(k * m.rotation_rad), math.sin(k * m.rotation_rad)
        rotation = np.array([[c, s], [-s, c]])  # counter-clockwise on the image (y down)
        return rotation @ np.array([[1.0 + k * m.stretch[0], k * m.shear], [0.0, 1.0 + k * m.stretch[1]]])

    def _band(self, k: float) -> tuple[float, float, float] | None:
        """(peak, sigma px, centre x px) of the band in frame k."""
        b = self.motion.band
        if b is None:
            return None
        at = self.centre[0] + (b.start_mm + k * b.speed_mm) * self.px_per_mm
        return b.peak_strain, b.sigma_mm * self.px_per_mm, at

    @staticmethod
    def _band_shift(x: np.ndarray, peak: float, sigma: float, at: float) -> np.ndarray:
        return peak * sigma * math.sqrt(math.pi / 2.0) * (1.0 + erf((x - at) / (sigma * math.sqrt(2.0))))

    def forward(self, points: np.ndarray, k: float) -> np.ndarray:
        """Where the points (n, 2) (x, y) of frame 0 are in frame k."""
        p = np.array(points, dtype=np.float64).reshape(-1, 2)
        band = self._band(k)
        if band is not None:
            p[:, 0] += self._band_shift(p[:, 0], *band) - self._band_shift(p[:, 0], *self._band(0))
        slide = k * np.asarray(self.motion.slide_px, dtype=np.float64)
        return self.centre + (p - self.centre) @ self._matrix(k).T + slide

    def inverse(self, points: np.ndarray, k: float) -> np.ndarray:
        """Where the points (n, 2) (x, y) of frame k were in frame 0."""
        q = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        slide = k * np.asarray(self.motion.slide_px, dtype=np.float64)
        p = self.centre + np.linalg.solve(self._matrix(k), (q - slide - self.centre).T).T
        band = self._band(k)
        if band is not None:
            p[:, 0] = self._undo_band(p[:, 0], band, self._band(0))
        return p

    def _undo_band(self, y: np.ndarray, now, then) -> np.ndarray:
        """The x solving x + shift_now(x) - shift_then(x) = y (Newton; the map's slope is within 1 +- |peak|)."""
        peak, sigma, _ = now
        x = y.copy()
        for _ in range(100):
            f = x + self._band_shift(x, *now) - self._band_shift(x, *then) - y
            slope = 1.0 + peak * (np.exp(-0.5 * ((x - now[2]) / sigma) ** 2)
                                  - np.exp(-0.5 * ((x - then[2]) / sigma) ** 2))
            step = f / slope
            x -= step
            if np.max(np.abs(step), initial=0.0) < _NEWTON_TOL_PX:
                return x
        raise RuntimeError("the travelling band's inverse did not converge")  # |peak| < 0.5 always converges

    def between(self, points: np.ndarray, frame_a: int, frame_b: int) -> tuple[np.ndarray, np.ndarray]:
        """True displacement (n, 2) from frame a to frame b of the points of frame a, and whether it is known
        (always: the field is defined everywhere), as :class:`~skinstretch.experiments.evaluation.tracking.TruthField`
        gives it."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        d = self.forward(self.inverse(p, frame_a), frame_b) - p
        return d, np.ones(p.shape[0], bool)

    def edge_change(self, pa: np.ndarray, pb: np.ndarray, frame_a: int, frame_b: int) -> np.ndarray:
        """True change of length (a fraction) from frame a to frame b of the segments pa-pb of frame a."""
        da, _ = self.between(pa, frame_a, frame_b)
        db, _ = self.between(pb, frame_a, frame_b)
        pa, pb = np.asarray(pa, np.float64).reshape(-1, 2), np.asarray(pb, np.float64).reshape(-1, 2)
        return np.hypot(*((pb + db) - (pa + da)).T) / np.hypot(*(pb - pa).T) - 1.0


@validated_dataclass
class ClipConditions:
    """How the moved print is imaged.

    Attributes
    ----------
    print_name : str
        A shipped print (500 dpi).
    px_per_mm : float
        The clip's pixel scale (the print is resampled to it).
    background : {"white", "black", "grey"}
        Grey level where the print has no ridges (:data:`BACKGROUND_LEVELS`).
    bright_ridges : bool
        Ridges bright and valleys dark (FTIR's look) instead of dark ridges on a bright print.
    contrast : float
        Ridge swing relative to full (full: ridges 28, valleys 228 or the reverse; 0.35: a third of it, about 128).
    vignetting : float
        Light lost at the frame's corners (0.4: corners at 60 % of the centre), falling off as the radius squared.
    blur_px : float
        Gaussian blur sigma (px), camera-fixed.
    noise_grey : float
        Gaussian noise sigma (grey levels).
    shape : (rows, cols)
    n_frames, seed : int
    """

    print_name: str = "afis_p1_2"
    px_per_mm: PositiveFloat = 30.0
    background: Literal["white", "black", "grey"] = "white"
    bright_ridges: bool = False
    contrast: Annotated[float, Field(gt=0, le=1)] = 1.0
    vignetting: Probability = 0.0
    blur_px: NonNegativeFloat = 0.0
    noise_grey: NonNegativeFloat = 2.0
    shape: tuple[PositiveInt, PositiveInt] = (484, 640)
    n_frames: Annotated[int, Field(ge=2)] = 40
    seed: NonNegativeInt = 0


@dataclass(frozen=True)
class PrintClip:
    """Frames (N, rows, cols) uint8 and the exact field that moved the print between them."""

    frames: np.ndarray
    field: ExactField
    conditions: ClipConditions
    motion: PrintMotion


def _picture(conditions: ClipConditions, margin: int) -> np.ndarray:
    """The print at the clip's scale on its background, centred on frame 0 and ``margin`` px beyond it each way."""
    from skinstretch.simulators.print_texture import load_print  # noqa: PLC0415
    from skinstretch.simulators.prints import PRINTS, print_path  # noqa: PLC0415

    if conditions.print_name not in PRINTS:
        raise InvalidInputError(f"print_name must be one of {sorted(PRINTS)}, got {conditions.print_name!r}")
    grey = cv2.imread(str(print_path(conditions.print_name)), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
    coverage = load_print(conditions.print_name).coverage  # where the print has ridges (soft edge)
    f = conditions.px_per_mm / PRINT_DPI_PX_PER_MM
    interpolation = cv2.INTER_AREA if f < 1 else cv2.INTER_CUBIC
    size = (int(round(grey.shape[1] * f)), int(round(grey.shape[0] * f)))
    grey = np.clip(cv2.resize(grey, size, interpolation=interpolation), 0.0, 1.0)
    coverage = np.clip(cv2.resize(coverage, size, interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
    sign = -1.0 if conditions.bright_ridges else 1.0  # print grey: 0 ink (ridge), 1 paper (valley)
    level = _MID + sign * conditions.contrast * _HALF_SWING * (2.0 * grey - 1.0)
    background = BACKGROUND_LEVELS[conditions.background]
    rows, cols = conditions.shape[0] + 2 * margin, conditions.shape[1] + 2 * margin
    picture = np.full((rows, cols), background, np.float64)
    # the print's coverage centroid on the frame's centre
    w = coverage.astype(np.float64)
    cy, cx = (np.indices(w.shape) * w).reshape(2, -1).sum(1) / w.sum()
    oy, ox = int(round(rows / 2.0 - cy)), int(round(cols / 2.0 - cx))
    ys, xs = slice(max(0, oy), min(rows, oy + w.shape[0])), slice(max(0, ox), min(cols, ox + w.shape[1]))
    src = (slice(ys.start - oy, ys.stop - oy), slice(xs.start - ox, xs.stop - ox))
    picture[ys, xs] = w[src] * level[src] + (1.0 - w[src]) * background
    return picture


class MovingPicture:
    """A picture (rows, cols; frame 0's pixels ``margin`` px in from its edge) seen through ``field``: frame k's pixel
    x shows the picture's cubic spline at the field's inverse of x, exactly (no rounding of the source position)."""

    def __init__(self, picture: np.ndarray, field: ExactField, *, shape: tuple[int, int], margin: int) -> None:
        self.coefficients = ndi.spline_filter(np.asarray(picture, np.float64), order=3)
        self.field, self.margin, self.shape = field, int(margin), tuple(shape)
        yy, xx = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
        self._grid = np.column_stack([xx.ravel(), yy.ravel()])

    def frame(self, k: int) -> np.ndarray:
        """Frame k (float64, the picture's levels)."""
        src = self.field.inverse(self._grid, k) + self.margin
        return ndi.map_coordinates(self.coefficients, [src[:, 1], src[:, 0]], order=3, prefilter=False,
                                   mode="nearest").reshape(self.shape)


def render_print_clip(conditions: ClipConditions, motion: PrintMotion) -> PrintClip:
    """The clip of the print moved by ``motion`` under ``conditions`` (module doc), with its exact field."""
    exact = ExactField(motion, shape=conditions.shape, px_per_mm=conditions.px_per_mm)
    rows, cols = conditions.shape
    margin = max(rows, cols) // 2
    moving = MovingPicture(_picture(conditions, margin), exact, shape=conditions.shape, margin=margin)
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    r2 = ((xx - exact.centre[0]) ** 2 + (yy - exact.centre[1]) ** 2) / float(exact.centre @ exact.centre)
    light = 1.0 - conditions.vignetting * r2
    rng = np.random.default_rng(conditions.seed)
    frames = np.empty((conditions.n_frames, rows, cols), np.uint8)
    for k in range(conditions.n_frames):
        image = moving.frame(k) * light
        if conditions.blur_px > 0:
            image = cv2.GaussianBlur(image, (0, 0), conditions.blur_px)
        if conditions.noise_grey > 0:
            image = image + rng.normal(0.0, conditions.noise_grey, image.shape)
        frames[k] = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    return PrintClip(frames=frames, field=exact, conditions=conditions, motion=motion)
