"""Which prism surface a clip was filmed on (flat, ridge or valley), read from the frames alone.

A ridge or a valley of the contact surface leaves a band that stays fixed on the glass while the skin slides over
it (:mod:`skinstretch.processing.glass_shading`): its slopes are lit less (seed 6.3.2) and where the skin cannot
follow the shape it loses contact. Averaged over the clip, the contrast of the moving texture (its local standard
deviation over about one ridge period) is smooth on a flat surface and shows that band as a straight trough:

* **shaped or flat**: the profile of the mean contrast across the image is read for its deepest trough; one that
  takes at least :data:`MIN_BAND_DEPTH` of the contrast, at the same place in each of four strips along the band
  (straight, as a ruled surface's is), is a shaped surface.
* **ridge or valley**: on a ridge the skin is pressed onto the level crest and keeps its contrast there; it does
  not reach a valley's bottom (seed Figure 95). The band's middle keeping at least :data:`MIN_CREST_LEVEL` of the
  contrast outside it is a ridge, less a valley.
* **where the contrast is read**: only where there is print or skin (at least :data:`MIN_TEXTURE_LEVEL` of the
  frame's typical contrast, in at least half the frames), less one window along that region's edge.

Every length is in mm. The rule cannot tell a valley the skin fills completely from a ridge; a band taking less
than a fifth of the contrast reads as flat (the analysis then leaves the glass shading in). The scenes it was
checked on: docs/tuning-log.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError

__all__ = ["SurfaceEvidence", "ContrastAccumulator", "detect_surface", "MIN_BAND_DEPTH", "MIN_CREST_LEVEL",
           "MIN_TEXTURE_LEVEL"]

#: Smallest relative contrast drop of a glass-fixed band read as a shaped surface.
MIN_BAND_DEPTH = 0.2
#: Smallest contrast kept in the middle of the band (relative to outside it) read as a ridge's crest.
MIN_CREST_LEVEL = 0.78
#: Smallest contrast, relative to the frame's typical, of a pixel counted as print or skin (a ridge or valley band
#: keeps at least ~0.4 of it; plain background and sensor noise of a few grey levels ~0.1 or less).
MIN_TEXTURE_LEVEL = 0.25
_WINDOW_MM = 0.5  # local contrast window: about one ridge period
_ANY_TEXTURE = 0.1  # "any texture": contrast above this fraction of the frame's 99.5th percentile
_MIN_ROW_SHARE = 0.1  # a profile sample needs textured pixels over this share of the band's length
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
    textured_fraction : float
        Share of the frame where the contrast was read (print or skin in most frames; the rest is background).
    """

    kind: str
    axis: str
    band_depth: float
    band_at_px: float
    strip_depth: float
    crest_level: float | None
    frames: int
    textured_fraction: float = 1.0

    def describe(self) -> str:
        """One line: what was found, and from what."""
        where = f"a glass-fixed band across image {self.axis} at {self.band_at_px:.0f} px"
        source = (f"from the ridge contrast of the {100 * self.textured_fraction:.0f} % of the frame that holds print "
                  f"or skin, {self.frames} frames")
        if self.kind == "flat" and self.band_depth < MIN_BAND_DEPTH:
            return (f"flat: no glass-fixed band (deepest contrast trough {self.band_depth:.2f} < {MIN_BAND_DEPTH}; "
                    f"{source})")
        if self.kind == "flat":
            return (f"flat: the deepest contrast trough ({self.band_depth:.2f} across image {self.axis} at "
                    f"{self.band_at_px:.0f} px) does not run straight across the print ({self.strip_depth:.2f} in one "
                    f"strip of {_STRIPS}; {source})")
        crest = f"its middle keeps {self.crest_level:.2f} of the contrast"
        rule = ">=" if self.kind == "ridge" else "<"
        return (f"{self.kind}: {where} takes {self.band_depth:.2f} of the contrast, {crest} ({rule} "
                f"{MIN_CREST_LEVEL}: {'a crest in contact' if self.kind == 'ridge' else 'a bottom out of contact'}; "
                f"{source})")

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
        self._count: np.ndarray | None = None
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
            self._sum = np.zeros(contrast.shape, np.float64)
            self._count = np.zeros(contrast.shape, np.int32)
        elif self._sum.shape != contrast.shape:
            raise InvalidInputError(f"frame is {contrast.shape}, the frames before it {self._sum.shape}")
        textured = _textured(contrast, self._window)
        self._sum[textured] += contrast[textured]
        self._count += textured
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
        if min(self._sum.shape) < 4 * self._window:
            raise InsufficientDataError(
                f"surface detection needs frames of at least {4 * _WINDOW_MM:g} mm ({4 * self._window} px) each way, "
                f"got {self._sum.shape[1]}x{self._sum.shape[0]} px"
            )
        kept = self._count >= 0.5 * self.frames  # print or skin in most frames
        if not kept.any():
            raise InsufficientDataError("surface detection: the frames hold no texture (uniform images)")
        mean = np.where(kept, self._sum / np.maximum(self._count, 1), np.nan).astype(np.float32)
        sigma = _SMOOTH_MM * self.px_per_mm
        found = [r + (axis,) for axis in ("y", "x") if (r := _across(mean if axis == "y" else mean.T, sigma))]
        if not found:
            raise InsufficientDataError(
                f"surface detection: print or skin in only {100 * kept.mean():.0f} % of the frame, too little to read "
                "a contrast profile across it")
        depth, at, strip, crest, axis = max(found, key=lambda t: t[0])
        if depth < MIN_BAND_DEPTH or strip < 0.5 * depth:
            kind, crest = "flat", None
        else:
            kind = "ridge" if crest >= MIN_CREST_LEVEL else "valley"
        return SurfaceEvidence(kind=kind, axis=axis, band_depth=float(depth), band_at_px=float(at),
                               strip_depth=float(strip), crest_level=crest, frames=self.frames,
                               textured_fraction=float(kept.mean()))


def _textured(contrast: np.ndarray, window: int) -> np.ndarray:
    """Pixels of print or skin in one frame's contrast image: at least :data:`MIN_TEXTURE_LEVEL` of the typical
    contrast, less one window along the region's edge (where the window straddles it)."""
    sample = contrast[::4, ::4]
    some = sample[sample > _ANY_TEXTURE * np.percentile(sample, 99.5)]
    if not some.size:
        return np.zeros(contrast.shape, bool)
    region = (contrast >= MIN_TEXTURE_LEVEL * float(np.median(some))).astype(np.uint8)
    # the image's own edge is no edge of the region (cv2.erode leaves the border alone by default)
    return cv2.erode(region, cv2.getStructuringElement(cv2.MORPH_RECT, (2 * window + 1, 2 * window + 1))) > 0


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


def _profile(contrast: np.ndarray, a: int, b: int, min_count: int) -> np.ndarray:
    """Median of each row of ``contrast[:, a:b]`` over its textured (finite) pixels; NaN where fewer than
    ``min_count``."""
    part = contrast[:, a:b]
    count = np.isfinite(part).sum(axis=1)
    out = np.full(part.shape[0], np.nan, np.float32)
    rows = count >= max(1, min_count)
    if rows.any():
        out[rows] = np.nanmedian(part[rows], axis=1)
    return out


def _bridged(profile: np.ndarray) -> tuple[np.ndarray, int] | None:
    """The profile from its first to its last sample, inner gaps bridged linearly, and where it starts; None when it
    holds fewer than 3 samples."""
    ok = np.flatnonzero(np.isfinite(profile))
    if ok.size < 3:
        return None
    first, last = int(ok[0]), int(ok[-1])
    rows = np.arange(first, last + 1)
    return np.interp(rows, ok, profile[ok]).astype(np.float32), first


def _across(contrast: np.ndarray, sigma: float) -> tuple[float, float, float, float | None] | None:
    """Deepest trough of the row profile of ``contrast`` (NaN where not textured; bands along x): depth, row,
    smallest depth there in the strips that hold texture, and the contrast kept in the band's middle. None when
    the profile is too short to read."""
    width = contrast.shape[1]
    cols = [int(width * (0.1 + 0.8 * i / _STRIPS)) for i in range(_STRIPS + 1)]
    whole = _bridged(_profile(contrast, cols[0], cols[-1], int(_MIN_ROW_SHARE * (cols[-1] - cols[0]))))
    if whole is None or whole[0].size < 8 * sigma:
        return None
    raw, first = whole
    profile = _smoothed(raw, sigma)
    drop, level = _troughs(profile)
    relative = drop / np.maximum(level, 1e-6)
    at = int(np.argmax(relative))
    depth = float(relative[at])
    strips = []
    for a, b in zip(cols[:-1], cols[1:]):
        strip = _bridged(_profile(contrast, a, b, int(_MIN_ROW_SHARE * (b - a))))
        if strip is None:
            continue
        s = np.full(profile.size, np.nan, np.float32)
        lo_row, hi_row = max(first, strip[1]), min(first + profile.size, strip[1] + strip[0].size)
        if hi_row - lo_row < 8 * sigma:
            continue
        s[lo_row - first : hi_row - first] = _smoothed(strip[0], sigma)[lo_row - strip[1] : hi_row - strip[1]]
        # a straight band is in every strip at about the same place (within the profile smoothing)
        near = slice(max(0, at - int(3 * sigma)), at + int(3 * sigma) + 1)
        if not np.isfinite(s[near]).all():
            continue  # this strip holds no print there
        valid = np.isfinite(s)
        s_drop, s_level = np.full(s.size, np.nan), np.full(s.size, np.nan)
        s_drop[valid], s_level[valid] = _troughs(s[valid])
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
    # a band must show in at least two strips; fewer holding print there cannot tell a straight band
    strip_depth = min(strips) if len(strips) >= 2 else 0.0
    return depth, float(at + first), strip_depth, crest
