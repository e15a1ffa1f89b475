"""Fingertip motion and the visibility window (seed 5.2).

The fingertip's displacement between two frames is the average of the tracked feature displacements (seed 5.2,
Figure 54). The visibility window is the part of the first image that stays in view through the whole sequence
as the fingertip moves (Figure 55); it then follows the fingertip, and the tactile display is centred on it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from skinstretch.processing.errors import InsufficientDataError, InvalidInputError
from skinstretch.processing.tracking import MotionSample


@dataclass(frozen=True)
class FingertipMotion:
    """Fingertip displacement per consecutive frame pair, and its cumulated position.

    Attributes
    ----------
    displacement : (N-1, 2) float64
        Mean displacement (dx, dy) px from frame k to k+1; 0 where ``valid`` is False.
    n_features : (N-1,) int64
        Number of displacements averaged.
    valid : (N-1,) bool
        At least ``min_features`` displacements were available. An invalid pair contributes no motion, so the
        cumulated position holds still across it (flagged here, never NaN).
    position : (N, 2) float64
        Cumulated displacement since frame 0 (position of a skin point that was at the origin in frame 0).
    """

    displacement: np.ndarray
    n_features: np.ndarray
    valid: np.ndarray
    position: np.ndarray

    @property
    def n_frames(self) -> int:
        return int(self.position.shape[0])


def fingertip_motion(
    samples: Sequence[MotionSample], *, n_frames: int, min_features: int = 3, trim_fraction: float = 0.0
) -> FingertipMotion:
    """Fingertip motion from the displacements of consecutive frame pairs (seed 5.2).

    Parameters
    ----------
    samples : sequence of MotionSample
        One per consecutive pair, ``samples[k]`` from frame k to k+1 (``len(samples) == n_frames - 1``).
    n_frames : int
    min_features : int
        Fewer displacements than this leave the pair flagged invalid.
    trim_fraction : float
        Fraction of displacements trimmed at each end (per axis) before averaging; 0 = the seed's plain mean.

    Examples
    --------
    >>> import numpy as np
    >>> s = MotionSample(0, 1, np.zeros((4, 2)), np.tile([2.0, -1.0], (4, 1)), np.arange(4))
    >>> fingertip_motion([s], n_frames=2).position.tolist()
    [[0.0, 0.0], [2.0, -1.0]]
    """
    if n_frames < 1:
        raise InvalidInputError(f"n_frames must be >= 1, got {n_frames!r}")
    if len(samples) != n_frames - 1:
        raise InvalidInputError(f"expected {n_frames - 1} consecutive-pair samples, got {len(samples)}")
    if not 0 <= trim_fraction < 0.5:
        raise InvalidInputError(f"trim_fraction must be in [0, 0.5), got {trim_fraction!r}")
    disp = np.zeros((max(n_frames - 1, 0), 2))
    count = np.zeros(max(n_frames - 1, 0), np.int64)
    for k, s in enumerate(samples):
        if s.frame_a != k or s.frame_b != k + 1:
            raise InvalidInputError(f"samples[{k}] is frames {s.frame_a}->{s.frame_b}, expected {k}->{k + 1}")
        d = np.asarray(s.displacement, dtype=np.float64)
        d = d[np.all(np.isfinite(d), axis=1)]
        count[k] = d.shape[0]
        if d.shape[0] >= min_features:
            if trim_fraction > 0:
                lo = int(d.shape[0] * trim_fraction)
                d = np.sort(d, axis=0)[lo : d.shape[0] - lo]
            disp[k] = d.mean(axis=0)
    valid = count >= min_features
    position = np.vstack([np.zeros((1, 2)), np.cumsum(disp, axis=0)])
    return FingertipMotion(disp, count, valid, position)


@dataclass(frozen=True)
class VisibilityWindow:
    """Part of frame 0 visible in every frame (seed 5.2, Figure 55), and where it is in each frame.

    Attributes
    ----------
    x0, y0, x1, y1 : float
        Bounds (px, inclusive) of the window in frame 0.
    centers : (N, 2) float64
        Centre of the window in each frame (it follows the fingertip).
    """

    x0: float
    y0: float
    x1: float
    y1: float
    centers: np.ndarray

    @property
    def width(self) -> float:
        return self.x1 - self.x0

    @property
    def height(self) -> float:
        return self.y1 - self.y0


def visibility_window(motion: FingertipMotion, *, image_shape: tuple[int, int]) -> VisibilityWindow:
    """The part of the first image that stays in view through the sequence, following the fingertip.

    A skin point at ``p`` in frame 0 is at ``p + position[k]`` in frame k; it is visible throughout when that
    stays inside the image for every k. Raises InsufficientDataError when no such point exists (the fingertip
    moved further than the field of view).
    """
    if len(image_shape) != 2 or min(image_shape) <= 0:
        raise InvalidInputError(f"image_shape must be (height, width) > 0, got {image_shape!r}")
    h, w = image_shape
    pos = motion.position
    x0 = max(0.0, -float(pos[:, 0].min()))
    x1 = min(w - 1.0, w - 1.0 - float(pos[:, 0].max()))
    y0 = max(0.0, -float(pos[:, 1].min()))
    y1 = min(h - 1.0, h - 1.0 - float(pos[:, 1].max()))
    if x1 <= x0 or y1 <= y0:
        raise InsufficientDataError(
            f"no part of the first frame stays in view: the fingertip moves {np.ptp(pos[:, 0]):.0f} x "
            f"{np.ptp(pos[:, 1]):.0f} px in a {w} x {h} px image"
        )
    center0 = np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0])
    return VisibilityWindow(x0, y0, x1, y1, center0 + pos)
