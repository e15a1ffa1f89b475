"""Resolution and noise of a displacement field measured on a star pair
(:mod:`skinstretch.simulators.star_pattern`), the DIC community's two numbers:

- **resolution**: the period at which the bias on the amplitude reaches 10 %. On the centre rows (within 2 px of
  the centre, where ``v = A`` at every period) the measured and the true ``v`` are averaged over the same rows and
  over 15 columns; ``bias = |1 - measured / true|``. Scanning the star from its longest period to its shortest, the
  resolution is the period at the first column where the bias reaches 10 % (a column where the method gives no
  value counts as unresolved).
- **noise**: the standard deviation of the error of ``v`` over the flat part (a uniform shift), 32 rows from the top
  and bottom left out.
- **error in the star** (ours, not the DIC Challenge's): the RMS error (bias and noise) on the centre rows where
  the period is 150-300 px. A method whose smoothing adapts to the field (ours) may be quieter on the flat part
  than where the field varies: this says how much.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d

from skinstretch.processing.errors import InvalidInputError
from skinstretch.simulators.star_pattern import StarPair

BIAS_LIMIT = 0.10
_CENTRE_ROWS_PX = 2.0
_SMOOTH_COLUMNS = 15
_BORDER_ROWS = 32


@dataclass(frozen=True)
class StarScore:
    """``resolution_px``: period at 10 % bias (``min_period`` when never reached, inf when reached at once);
    ``noise_px`` (flat part), ``error_in_star_px`` (RMS, centre rows, periods 150-300 px); ``periods`` and ``bias`` along the star (centre rows, smoothed); ``missing_fraction``: star
    columns without a value."""

    resolution_px: float
    noise_px: float
    error_in_star_px: float
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


def score_star(v_measured: np.ndarray, pair: StarPair) -> StarScore:
    """Score a measured vertical displacement (H, W) px (NaN where the method gives none) on ``pair``."""
    v = np.asarray(v_measured, dtype=np.float64)
    lay = pair.layout
    if v.shape != pair.v_true.shape:
        raise InvalidInputError(f"v_measured has shape {v.shape}, the star pair {pair.v_true.shape}")
    rows = np.abs(np.arange(lay.height) - lay.center_row) <= _CENTRE_ROWS_PX
    cols = lay.star_columns
    meas = v[rows, cols]
    true = pair.v_true[rows, cols]
    have = np.all(np.isfinite(meas), axis=0)
    m = uniform_filter1d(np.where(have, meas.mean(axis=0), 0.0), _SMOOTH_COLUMNS, mode="nearest")
    t = uniform_filter1d(true.mean(axis=0), _SMOOTH_COLUMNS, mode="nearest")
    ok = uniform_filter1d(have.astype(np.float64), _SMOOTH_COLUMNS, mode="nearest") > 0.999
    bias = np.where(ok, np.abs(1.0 - m / t), 1.0)
    periods = lay.period()[cols]
    over = np.nonzero(bias >= BIAS_LIMIT)[0]
    if over.size == 0:
        resolution = float(periods[-1])
    elif over[0] == 0:
        resolution = math.inf
    else:
        resolution = float(periods[over[0]])
    flat = v[_BORDER_ROWS : lay.height - _BORDER_ROWS, lay.flat_columns]
    err = flat - pair.v_true[_BORDER_ROWS : lay.height - _BORDER_ROWS, lay.flat_columns]
    err = err[np.isfinite(err)]
    noise = float(np.std(err)) if err.size > 100 else math.nan
    long = (periods >= 150) & (periods <= 300)
    e_star = (meas - true)[:, long]
    e_star = e_star[np.isfinite(e_star)]
    error_star = float(np.sqrt(np.mean(e_star**2))) if e_star.size > 20 else math.nan
    return StarScore(resolution, noise, error_star, periods, bias, float(1.0 - have.mean()))
