"""Resolution and noise of a displacement field measured on a star pair
(:mod:`skinstretch.simulators.star_pattern`, the DIC Challenge 2.0 Star layout), the DIC community's two numbers:

- **resolution**: the period at which the bias on the amplitude reaches 10 %. On the centre rows (within 2 px of
  the centre, where ``v`` is close to ``A`` at every period) the measured and the true ``v`` are averaged over the
  same rows and over 15 columns; ``bias = |1 - measured / true|``.
  Scanning the star from its longest period to its shortest, the resolution is the period at the first column
  where the bias reaches 10 % (a column where the method gives no value counts as unresolved).
- **noise**: the standard deviation of ``v`` along the centre row over the long-period end
  (:attr:`StarLayout.noise_columns`), less a quadratic trend in x (the slowly varying bias there belongs to the
  resolution, not to the noise). The true ``v`` is constant along that row.
- **error at long periods** (ours, not the DIC Challenge's): the RMS error (bias and noise) of ``v`` over every
  row of the long-period end, 32 rows from the top and bottom left out: what a method does off the centre row,
  where the displacement takes every sub-pixel value.

``score_star`` takes the layout alone, so the same code scores a field measured on the Challenge's own images (its
layout is :class:`StarLayout`'s default).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.star_pattern import StarLayout, StarPair

BIAS_LIMIT = 0.10
_CENTRE_ROWS_PX = 2.0
_SMOOTH_COLUMNS = 15
_BORDER_ROWS = 32


@dataclass(frozen=True)
class StarScore:
    """``resolution_px``: period at 10 % bias (the shortest period scanned when never reached, inf when reached at
    once); ``noise_px`` (centre row, long-period end), ``error_long_px`` (RMS over the long-period end's rows);
    ``periods`` and ``bias`` along the centre rows (long period first, smoothed); ``missing_fraction``: columns
    of the centre rows without a value."""

    resolution_px: float
    noise_px: float
    error_long_px: float
    periods: np.ndarray
    bias: np.ndarray
    missing_fraction: float

    @property
    def resolution_text(self) -> str:
        """The resolution, with ``<=`` when the bias never reached the limit and ``>`` when it did at once."""
        if not math.isfinite(self.resolution_px):
            return f"> {self.periods[0]:.0f}"
        if self.resolution_px <= self.periods[-1] and np.all(self.bias < BIAS_LIMIT):
            return f"<= {self.resolution_px:.0f}"
        return f"{self.resolution_px:.0f}"


def star_pair_from_images(image_a: np.ndarray, image_b: np.ndarray, *, source: str = "the star images") -> StarPair:
    """A star pair from two 8-bit grey images of the DIC Challenge 2.0 Star layout (the Challenge's own images, or
    any rendered the same way): the truth is the layout's. One line naming ``source`` when they cannot be one."""
    lay = StarLayout()
    want = (lay.height, lay.width)
    for img in (image_a, image_b):
        if img.ndim != 2 or img.dtype != np.uint8:
            raise InvalidInputError(f"{source}: need two 8-bit grey images, got {img.dtype} of shape {img.shape}")
        if img.shape != want:
            raise InvalidInputError(f"{source}: {img.shape[1]} x {img.shape[0]} px; the DIC Challenge 2.0 Star layout "
                                    f"is {want[1]} x {want[0]} px (0.5 px vertical sine, periods "
                                    f"{lay.min_period_px:.0f} to {lay.max_period_px:.0f} px)")
    return StarPair(lay, image_a, image_b, lay.displacement())


def score_star(v_measured: np.ndarray, star: StarLayout | StarPair) -> StarScore:
    """Score a measured vertical displacement (H, W) px (NaN where the method gives none) on a star layout (or
    pair: its layout)."""
    lay = star.layout if isinstance(star, StarPair) else star
    v = np.asarray(v_measured, dtype=np.float64)
    v_true = lay.displacement()
    if v.shape != v_true.shape:
        raise InvalidInputError(f"v_measured has shape {v.shape}, the star {v_true.shape}")
    rows = np.abs(np.arange(lay.height) - lay.center_row) <= _CENTRE_ROWS_PX
    cols = lay.star_columns
    meas = v[rows, cols][:, ::-1]  # long period first
    true = v_true[rows, cols][:, ::-1]
    have = np.all(np.isfinite(meas), axis=0)
    m = uniform_filter1d(np.where(have, meas.mean(axis=0), 0.0), _SMOOTH_COLUMNS, mode="nearest")
    t = uniform_filter1d(true.mean(axis=0), _SMOOTH_COLUMNS, mode="nearest")
    ok = uniform_filter1d(have.astype(np.float64), _SMOOTH_COLUMNS, mode="nearest") > 0.999
    bias = np.where(ok, np.abs(1.0 - m / t), 1.0)
    periods = lay.period()[cols][::-1]
    over = np.nonzero(bias >= BIAS_LIMIT)[0]
    if over.size == 0:
        resolution = float(periods[-1])
    elif over[0] == 0:
        resolution = math.inf
    else:
        resolution = float(periods[over[0]])
    # The centre row (the mean of the two middle rows when the height is even).
    line = v[np.abs(np.arange(lay.height) - lay.center_row) <= 0.5, lay.noise_columns].mean(axis=0)
    good = np.isfinite(line)
    if good.sum() > 50:
        x = np.arange(line.size, dtype=np.float64)[good]
        trend = np.polyval(np.polyfit(x, line[good], 2), x)
        noise = float(np.std(line[good] - trend))
    else:
        noise = math.nan
    err = (v - v_true)[_BORDER_ROWS : lay.height - _BORDER_ROWS, lay.noise_columns]
    err = err[np.isfinite(err)]
    error_long = float(np.sqrt(np.mean(err**2))) if err.size > 100 else math.nan
    return StarScore(resolution, noise, error_long, periods, bias, float(1.0 - have.mean()))
