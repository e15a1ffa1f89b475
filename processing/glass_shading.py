"""Glass-fixed shading: brightness patterns that stay on the prism while the skin slides over it.

Over a ridge or a valley the contact is partial and the slopes are lit differently (seed 6.3.2, 6.3.3, Figure
95), so the image of the skin is ``I(p) = o(p) + g(p) T(p - u)``: a texture ``T`` that moves with the skin seen
through an offset ``o`` and a gain ``g`` that do not move. Any motion estimate (feature positions, optical flow)
is pulled towards zero where ``o`` and ``g`` vary, because part of what it sees stands still. On the simulated
``valleyL`` both of our methods under-read the skin's movement across the valley by up to 0.1-0.2 px per frame,
several times the per-frame change of stretch that the seed's Figure 94 looks for.

When the skin has slid by several ridge periods over the sequence, every pixel has seen the texture at every
phase, so the per-pixel temporal mean of the sequence estimates ``o + g mean(T)`` and the spread about it
``g std(T)`` (both pooled over pixels that share the shading: a ridge's or valley's run along the shape);
:func:`remove_glass_shading` maps each frame to ``level + contrast (I - mean) / std``, which leaves the moving
texture with the same contrast everywhere. This generalises the seed's illumination map (3.5, ``255 / max_t I``: a
gain only) to an offset and a gain. It needs the whole sequence, like the seed's map.

If the skin did not move enough, the statistics would hold the texture itself and the mapping would erase it:
:func:`glass_shading` checks that the temporal spread is comparable to the texture's spatial contrast and raises
:class:`~skinstretch.processing.errors.InsufficientDataError` otherwise.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.jit import njit

__all__ = ["GlassShading", "glass_shading", "remove_glass_shading"]


@dataclass(frozen=True)
class GlassShading:
    """Per-pixel statistics of one sequence (float32 maps of the frame's shape) and the output levels.

    ``offset`` is the temporal mean, ``gain`` is ``contrast / max(std, floor)``; a frame maps to
    ``level + gain * (frame - offset)``. ``motion_ratio`` is the temporal spread over the texture's spatial
    contrast (about 1 when the skin slid far enough, near 0 when it stood still).
    """

    offset: np.ndarray
    gain: np.ndarray
    level: float
    motion_ratio: float


def glass_shading(
    frames: Sequence[np.ndarray] | np.ndarray,
    *,
    use: Sequence[int] | None = None,
    smooth_px: float | tuple[float, float] = 1.5,
    along_shape_px: float | None = None,
    level: float = 160.0,
    contrast: float = 45.0,
    floor_fraction: float = 0.25,
    min_motion_ratio: float = 0.8,
) -> GlassShading:
    """Estimate the glass-fixed offset and gain of a sequence of uint8 frames (see the module doc).

    Parameters
    ----------
    frames, use : sequence of (H, W) uint8 arrays or an (N, H, W) uint8 array; sequence of int, optional
        The whole sequence; the frames to take the statistics from (at least 2; default all).
    smooth_px : float or (float, float)
        Gaussian smoothing (px; one value or (along x, along y)) of the mean and standard deviation maps.
    along_shape_px : float, optional
        Smooth along the shape by this much (across it by ``smooth_px``); the shape's axis is the image axis whose
        profile holds more of the sequence mean's variance.
    level, contrast : float
        Output grey level of the glass-fixed mean and output contrast of one standard deviation.
    floor_fraction : float
        The standard deviation is floored at this fraction of its 90th percentile (glass the skin never covered).
    min_motion_ratio : float
        Smallest accepted ratio of the median temporal standard deviation to the median spatial contrast in the skin.

    Raises
    ------
    InvalidInputError
        Frames that are not 2-D uint8 arrays of one shape, or bad parameters.
    InsufficientDataError
        Fewer than 2 frames, or a sequence in which the skin did not move enough.
    """
    use = np.arange(len(frames), dtype=np.int64) if use is None else np.asarray(use, dtype=np.int64).reshape(-1)
    if use.size and (use.min() < 0 or use.max() >= len(frames)):
        raise InvalidInputError(f"use holds frame numbers outside 0..{len(frames) - 1}")
    if use.size < 2:
        raise InsufficientDataError(f"glass shading needs at least 2 frames, got {use.size}")
    sx, sy = (smooth_px, smooth_px) if np.ndim(smooth_px) == 0 else tuple(smooth_px)
    for name, v in (("smooth_px", sx), ("smooth_px", sy), ("contrast", contrast), ("floor_fraction", floor_fraction)):
        if not (np.isfinite(v) and v > 0):
            raise InvalidInputError(f"{name} must be positive, got {smooth_px if name == 'smooth_px' else v!r}")
    if not (np.isfinite(min_motion_ratio) and min_motion_ratio >= 0):
        raise InvalidInputError(f"min_motion_ratio must be non-negative, got {min_motion_ratio!r}")
    first = np.asarray(frames[int(use[0])])
    if first.ndim != 2 or first.dtype != np.uint8:
        raise InvalidInputError(f"frames must be 2-D uint8 arrays, got {first.dtype} {first.shape}")
    stacked = isinstance(frames, np.ndarray) and frames.ndim == 3
    if not stacked:
        for k in use.tolist():
            f = np.asarray(frames[k])
            if f.shape != first.shape or f.dtype != np.uint8:
                raise InvalidInputError(f"frames[{k}] is {f.dtype} {f.shape}, expected uint8 {first.shape}")
    total, total_sq = _sequence_sums(frames, use, first.shape)
    n = float(use.size)
    mean = total / n
    std = np.sqrt(np.maximum(total_sq / n - mean * mean, 0.0))
    if along_shape_px is not None:
        if np.ndim(smooth_px) != 0 or not (np.isfinite(along_shape_px) and along_shape_px > 0):
            raise InvalidInputError(
                f"along_shape_px needs a positive value and a single smooth_px, got {along_shape_px!r}, {smooth_px!r}"
            )
        # A ruled surface's shading varies across the shape only: smooth much more along it (less of the
        # fingerprint left in the maps), whichever image axis that is.
        along_x = float(np.var(mean.mean(axis=1))) > float(np.var(mean.mean(axis=0)))
        sx, sy = (along_shape_px, smooth_px) if along_x else (smooth_px, along_shape_px)
    # How far the skin moved is judged on the temporal spread smoothed as little as the maps are across the shape:
    # smoothing along the shape lowers the spread's median too, and would turn the judgement with it.
    fine = min(sx, sy)
    spread = cv2.GaussianBlur(std.astype(np.float32), (0, 0), sigmaX=float(fine), sigmaY=float(fine))
    # The gain comes from the spread of all the samples the smoothing pools (frames, and pixels along the shape,
    # which share one offset and gain by the model) about their common mean, not from each pixel's own spread: a
    # print's ridges that run along the slide barely change at a pixel as the skin moves, and the texture's
    # variation along the shape then counts too. (28 ridge and valley clips, 12-60 frames, our print and eight
    # real ones, both methods: 11-frame edge strain lower on 40 runs of 56, higher on 5 by at most 0.008 %;
    # displacement lower on 40, higher on 6 by at most 0.0002 px; profile correlation unchanged on average.)
    second = cv2.GaussianBlur((total_sq / n).astype(np.float32), (0, 0), sigmaX=float(sx), sigmaY=float(sy))
    mean = cv2.GaussianBlur(mean.astype(np.float32), (0, 0), sigmaX=float(sx), sigmaY=float(sy))
    std = np.sqrt(np.maximum(second - mean * mean, 0.0)).astype(np.float32)
    # Spatial contrast of the texture in the first frame (local std over ~ a ridge period).
    f0 = first.astype(np.float32)
    m0 = cv2.blur(f0, (15, 15))
    spatial = np.sqrt(np.maximum(cv2.blur(f0 * f0, (15, 15)) - m0 * m0, 0.0))
    skin = spatial > 0.5 * float(np.percentile(spatial, 90))
    if not skin.any():
        raise InsufficientDataError("glass shading: no textured skin in the first frame")
    ratio = float(np.median(spread[skin]) / np.median(spatial[skin]))
    if ratio < min_motion_ratio:
        raise InsufficientDataError(
            f"glass shading: the skin moved too little over the sequence (temporal/spatial contrast {ratio:.2f} "
            f"< {min_motion_ratio}); its statistics would hold the fingerprint itself"
        )
    floor = floor_fraction * float(np.percentile(std, 90))
    gain = (contrast / np.maximum(std, max(floor, 1e-3))).astype(np.float32)
    return GlassShading(offset=mean, gain=gain, level=float(level), motion_ratio=ratio)


def _sequence_sums(frames, use: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel sum and sum of squares of ``frames[use]`` (exact: integers, returned as float64), on two
    threads (row halves; the kernel releases the GIL). A sequence that is not one array is stacked 64 frames at a
    time."""
    total = np.zeros(shape, np.float64)
    total_sq = np.zeros(shape, np.float64)
    if isinstance(frames, np.ndarray) and frames.ndim == 3:
        blocks = [(np.ascontiguousarray(frames), use)]
    else:
        blocks = (
            (np.stack([np.asarray(frames[k]) for k in use[i : i + 64].tolist()]), np.arange(min(64, use.size - i)))
            for i in range(0, use.size, 64)
        )
    h = shape[0]
    halves = [(0, h // 2), (h // 2, h)]
    with ThreadPoolExecutor(max_workers=2) as pool:
        for block, rows in blocks:
            list(pool.map(lambda r: _add_sums(block, rows, r[0], r[1], total, total_sq), halves))
    return total, total_sq


@njit(nogil=True)
def _add_sums(frames, use, y0, y1, total, total_sq):  # pragma: no cover - compiled
    """Add the sums over ``frames[use]`` of rows ``y0:y1`` to ``total`` and ``total_sq``; 16 rows at a time, their
    integer accumulators staying in cache while every frame passes (~10 ms for 180 frames of 640x484, against
    ~30-70 ms for OpenCV's accumulate into float64 maps)."""
    w = frames.shape[2]
    band = 16
    acc = np.zeros((band, w), np.int64)
    acc2 = np.zeros((band, w), np.int64)
    for yb in range(y0, y1, band):
        ye = min(yb + band, y1)
        acc[:] = 0
        acc2[:] = 0
        for k in use:
            for y in range(yb, ye):
                for x in range(w):
                    v = np.int64(frames[k, y, x])
                    acc[y - yb, x] += v
                    acc2[y - yb, x] += v * v
        for y in range(yb, ye):
            for x in range(w):
                total[y, x] += acc[y - yb, x]
                total_sq[y, x] += acc2[y - yb, x]


def remove_glass_shading(frame: np.ndarray, shading: GlassShading) -> np.ndarray:
    """``level + gain * (frame - offset)``, rounded and clipped to uint8 (see :func:`glass_shading`)."""
    frame = np.asarray(frame)
    if frame.ndim != 2 or frame.dtype != np.uint8 or frame.shape != shading.offset.shape:
        raise InvalidInputError(
            f"frame must be a uint8 array of shape {shading.offset.shape}, got {frame.dtype} {frame.shape}"
        )
    return _remove(frame, shading.offset, shading.gain, float(shading.level))


@njit(nogil=True)
def _remove(frame, offset, gain, level):  # pragma: no cover - compiled
    """One pass: ``(frame - offset) * gain`` in float32, ``+ level`` in float64, rounded half to even and
    saturated to uint8 (what OpenCV's subtract, multiply and add to CV_8U give, at a third of their time)."""
    h, w = frame.shape
    out = np.empty((h, w), np.uint8)
    for y in range(h):
        for x in range(w):
            v = np.rint(np.float64((np.float32(frame[y, x]) - offset[y, x]) * gain[y, x]) + level)
            out[y, x] = 0 if v < 0 else (255 if v > 255 else np.uint8(v))
    return out
