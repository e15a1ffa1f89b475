"""Which prism surface a clip was filmed on (flat, ridge or valley), read from the frames alone.

A ridge or a valley of the contact surface leaves a band that stays fixed on the glass while the skin slides over
it (:mod:`skinstretch.processing.glass_shading`): its slopes are lit less (seed 6.3.2) and where the skin cannot
follow the shape it loses contact; both take contrast from the fingerprint seen there. Averaged over the clip, the
contrast of the moving texture (its local standard deviation over ~0.5 mm, about one ridge period) is smooth on a
flat surface and shows that band as a straight trough across the whole field on a shaped one:

* **shaped or flat**: the profile of the mean contrast across the image (median along the other axis) is read for
  the deepest trough, i.e. the largest relative drop below the lower of the two highest points on either side
  (a flat surface's contrast falls off only towards the edge of the contact: no trough). A trough that takes at
  least :data:`MIN_BAND_DEPTH` of the contrast, found at the same place in each of four strips along the band (it
  is straight, as a ruled surface's is; a finger's own features are not), is a shaped surface.
* **ridge or valley**: a shaped surface is level in the middle of the band, between its two slopes (the two outer
  minima of the trough). On a ridge the skin is pressed onto that level crest and keeps its contrast there; it
  does not reach the bottom of a valley and loses it (seed Figure 95). The band's middle keeping at least
  :data:`MIN_CREST_LEVEL` of the contrast outside the band is a ridge, less a valley.

On the simulated scenes (flatL/S, ridgeL/S, valleyL/S, slipfront: 40-frame clips, seeds 1-3, also transposed
and their first 10 frames; flat1, flat2, stretch, reversal, slipsweep: seed 4; 6-frame clips, seeds 11-12): every
one is read right; flat troughs are at most 0.05 deep, ridge and valley troughs 0.40-0.58; a ridge's middle keeps
0.85-0.96 of the contrast, a valley's 0.60-0.67. The band is read from the contrast pattern alone, so a few frames
suffice. The rule cannot tell a valley that the skin fills completely (no contact lost at its bottom) from a ridge;
a band that takes less than a fifth of the contrast reads as flat (the analysis then leaves the glass shading in,
as it does on a flat surface).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError

__all__ = ["SurfaceEvidence", "ContrastAccumulator", "detect_surface", "MIN_BAND_DEPTH", "MIN_CREST_LEVEL"]

#: Smallest relative contrast drop of a glass-fixed band read as a shaped surface.
MIN_BAND_DEPTH = 0.2
#: Smallest contrast kept in the middle of the band (relative to outside it) read as a ridge's crest.
MIN_CREST_LEVEL = 0.78
_WINDOW_MM = 0.5  # local contrast window: about one ridge period
_SMOOTH_MM = 0.1  # profile smoothing
_STRIPS = 4


@dataclass(frozen=True)
class SurfaceEvidence:
    """What :func:`detect_surface` decided and why.

    Attributes
    ----------
    kind : {"flat", "ridge", "valley"}
        The surface read from the frames.
    axis : {"x", "y"}
        The image axis the contrast profile runs along (across the band; for a flat surface, the axis of its
        deepest, too shallow, trough).
    band_depth : float
        Relative contrast drop of the deepest trough of the profile (0: none, 1: all contrast lost).
    band_at_px : float
        Where that trough is along ``axis`` (pixels).
    strip_depth : float
        The smallest depth at that place in the four strips along the band (a straight band: close to
        ``band_depth``).
    crest_level : float or None
        Contrast kept in the middle of the band relative to outside it (shaped surfaces only).
    frames : int
        Frames averaged.
    """

    kind: str
    axis: str
    band_depth: float
    band_at_px: float
    strip_depth: float
    crest_level: float | None
    frames: int

    def describe(self) -> str:
        """One line: what was found."""
        where = f"a glass-fixed band across image {self.axis} at {self.band_at_px:.0f} px"
        if self.kind == "flat":
            return (f"flat: no glass-fixed band (deepest contrast trough {self.band_depth:.2f} < {MIN_BAND_DEPTH}, "
                    f"{self.frames} frames)")
        crest = f"its middle keeps {self.crest_level:.2f} of the contrast"
        rule = ">=" if self.kind == "ridge" else "<"
        return (f"{self.kind}: {where} takes {self.band_depth:.2f} of the contrast, {crest} ({rule} "
                f"{MIN_CREST_LEVEL}: {'a crest in contact' if self.kind == 'ridge' else 'a bottom out of contact'}; "
                f"{self.frames} frames)")

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


class ContrastAccumulator:
    """The mean local contrast of frames added one at a time (the streaming half of :func:`detect_surface`).

    Parameters
    ----------
    px_per_mm : float
        Pixel scale: the contrast window is ~0.5 mm, the profile smoothing 0.1 mm.
    """

    def __init__(self, *, px_per_mm: float) -> None:
        if not (np.isfinite(px_per_mm) and px_per_mm > 0):
            raise InvalidInputError(f"px_per_mm must be a positive number, got {px_per_mm!r}")
        self.px_per_mm = float(px_per_mm)
        self._window = max(3, int(round(_WINDOW_MM * self.px_per_mm)) | 1)
        self._sum: np.ndarray | None = None
        self.frames = 0

    def add(self, frame: np.ndarray) -> None:
        """Add one 2-D grey frame (any real dtype; all frames of one shape)."""
        f = np.asarray(frame)
        if f.ndim != 2:
            raise InvalidInputError(f"frame must be a 2-D grey image, got shape {f.shape}")
        f = f.astype(np.float32)
        k = (self._window, self._window)
        m = cv2.blur(f, k)
        contrast = np.sqrt(np.maximum(cv2.blur(f * f, k) - m * m, 0.0))
        if self._sum is None:
            self._sum = contrast.astype(np.float64)
        elif self._sum.shape != contrast.shape:
            raise InvalidInputError(f"frame is {contrast.shape}, the frames before it {self._sum.shape}")
        else:
            self._sum += contrast
        self.frames += 1

    def result(self) -> SurfaceEvidence:
        """The decision from the frames added so far.

        Raises
        ------
        InsufficientDataError
            Fewer than 2 frames, frames smaller than 2 mm each way, or frames without texture.
        """
        if self._sum is None or self.frames < 2:
            raise InsufficientDataError(f"surface detection needs at least 2 frames, got {self.frames}")
        mean = (self._sum / self.frames).astype(np.float32)
        if min(mean.shape) < 4 * self._window:
            raise InsufficientDataError(
                f"surface detection needs frames of at least {4 * _WINDOW_MM:g} mm ({4 * self._window} px) each way, "
                f"got {mean.shape[1]}x{mean.shape[0]} px"
            )
        if not float(mean.max()) > 0:
            raise InsufficientDataError("surface detection: the frames hold no texture (uniform images)")
        sigma = _SMOOTH_MM * self.px_per_mm
        best = max((_across(mean if axis == "y" else mean.T, sigma) + (axis,) for axis in ("y", "x")),
                   key=lambda t: t[0])
        depth, at, strip, crest, axis = best
        if depth < MIN_BAND_DEPTH or strip < 0.5 * depth:
            kind, crest = "flat", None
        else:
            kind = "ridge" if crest >= MIN_CREST_LEVEL else "valley"
        return SurfaceEvidence(kind=kind, axis=axis, band_depth=float(depth), band_at_px=float(at),
                               strip_depth=float(strip), crest_level=crest, frames=self.frames)


def detect_surface(frames, *, px_per_mm: float) -> SurfaceEvidence:
    """Read the prism surface (flat, ridge or valley) of a clip from its frames (see the module doc).

    Parameters
    ----------
    frames : sequence of 2-D arrays, or an (N, H, W) array
        The clip (grey), at least 2 frames in which the skin slides.
    px_per_mm : float
        Pixel scale.

    Examples
    --------
    >>> stripes = lambda k: 128 + 60 * np.sin(np.arange(200) / 4.0 + k)[None, :].repeat(200, 0)
    >>> band = 1 - 0.6 * np.exp(-0.5 * ((np.arange(200) - 100) / 15.0) ** 2)[:, None]
    >>> clip = [128 + (stripes(k) - 128) * band for k in range(6)]
    >>> detect_surface(clip, px_per_mm=40).kind
    'valley'
    """
    acc = ContrastAccumulator(px_per_mm=px_per_mm)
    for f in frames:
        acc.add(f)
    return acc.result()


def _troughs(profile: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's drop below the lower of the highest points on either side of it, and that level."""
    level = np.minimum(np.maximum.accumulate(profile), np.maximum.accumulate(profile[::-1])[::-1])
    return level - profile, level


def _smoothed(profile: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(profile[None].astype(np.float32), (0, 0), sigma).ravel()


def _across(contrast: np.ndarray, sigma: float) -> tuple[float, float, float, float | None]:
    """Deepest trough of the row profile of ``contrast`` (bands along x): depth, row, smallest depth there in the
    strips, and the contrast kept in the band's middle."""
    width = contrast.shape[1]
    cols = [int(width * (0.1 + 0.8 * i / _STRIPS)) for i in range(_STRIPS + 1)]
    profile = _smoothed(np.median(contrast[:, cols[0]:cols[-1]], axis=1), sigma)
    drop, level = _troughs(profile)
    relative = drop / np.maximum(level, 1e-6)
    at = int(np.argmax(relative))
    depth = float(relative[at])
    strips = []
    for a, b in zip(cols[:-1], cols[1:]):
        s = _smoothed(np.median(contrast[:, a:b], axis=1), sigma)
        s_drop, s_level = _troughs(s)
        # a straight band is in every strip at about the same place (within the profile smoothing)
        near = slice(max(0, at - int(3 * sigma)), at + int(3 * sigma) + 1)
        strips.append(float(np.max(s_drop[near] / np.maximum(s_level[near], 1e-6))))
    # the band's slopes: the outermost minima at least half as deep as the deepest; its middle lies between them
    basin = relative > 0.02  # the trough around the deepest point: every sample below the level on both sides
    lo = at - int(np.argmin(basin[at::-1])) + 1 if not basin[: at + 1].all() else 0
    hi = at + int(np.argmin(basin[at:])) if not basin[at:].all() else profile.size
    inner = profile[1:-1]
    is_min = np.zeros(profile.size, bool)
    is_min[1:-1] = (inner <= profile[:-2]) & (inner <= profile[2:])
    minima = lo + np.flatnonzero(is_min[lo:hi] & (relative[lo:hi] >= 0.5 * depth))
    crest = None
    if depth > 0 and minima.size:
        middle = 0.5 * (float(minima[0]) + float(minima[-1]))
        crest = float(np.interp(middle, np.arange(profile.size), profile) / max(float(level[at]), 1e-6))
    return depth, float(at), min(strips), crest
