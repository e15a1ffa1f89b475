"""A DIC-Challenge-like "star" image pair: a speckle pattern and the same pattern under a sinusoidal vertical
displacement whose period grows along x, with its exact displacement. The layout is the DIC Challenge 2.0 Star
images' (Reu et al. 2022; checked against a pair of them): 4000 x 501 px, ``v(x, y) = A cos(2 pi (y - y_c) / p(x))``
with ``A`` = 0.5 px, ``y_c`` the centre row (250) and the period growing linearly from 10 px at the left edge to
300 px at the right (``p(x) = 10 + 290 x / 4000``), ``u = 0``. Lines of constant phase fan out from the centre row
like a star; on the centre row ``v = A`` everywhere, so the measured amplitude there, against the true one, gives
the bias at each period (the DIC community's spatial resolution: the period at which the bias reaches 10 %), and
its scatter along the long-period end gives the noise. The speckle is our own, matched to the Challenge images'
statistics (grey levels about 50-190 around 115, std 38; intensity autocorrelation falling to half at 2.3 px;
gradient energy; noise 2 grey levels): we do not ship the Challenge's files.

Speckle: random Gaussian dots (sigma ``dot_sigma_px``, ``dot_density`` per px^2, random strengths) composed as
``I = dark + (bright - dark) (1 - exp(-S))`` with ``S`` the sum of the dots; both images are that function sampled
at pixel centres, the second at the skin point now there (the displacement inverted by fixed-point iteration, a
contraction since ``|dv/dy| <= 2 pi A / min_period < 1``), so the pair is exact up to the added Gaussian noise and
8-bit quantisation. The dots are nearly band-limited (sigma 1.3 px: their spectrum at the Nyquist frequency is
2e-4 of its peak), so point sampling needs no pixel integration.

Hand-written: no library renders a speckle pair under a given displacement field exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from pydantic import Field, model_validator

from skinstretch.processing.errors import InvalidInputError
from skinstretch.processing.validated_dataclass import (
    FiniteFloat,
    NonNegativeFloat,
    PositiveFloat,
    validated_dataclass,
)


@validated_dataclass
class StarLayout:
    """Size and displacement of a star pair (px, grey levels); the defaults are the DIC Challenge 2.0 Star
    images' layout (a narrower ``width`` keeps the period range: the period then grows faster along x and the
    fringes slant more, for tests)."""

    width: int = Field(default=4000, ge=256)
    height: int = Field(default=501, ge=64)
    amplitude_px: PositiveFloat = 0.5
    min_period_px: PositiveFloat = 10.0
    max_period_px: PositiveFloat = 300.0
    dot_sigma_px: FiniteFloat = Field(default=1.3, ge=1.0)
    dot_density: PositiveFloat = 0.08
    dark: FiniteFloat = 50.0
    bright: FiniteFloat = 205.0
    noise_sigma: NonNegativeFloat = 2.0

    @model_validator(mode="after")
    def _periods_invert(self) -> "StarLayout":
        if not self.min_period_px < self.max_period_px:
            raise InvalidInputError("need 0 < min_period_px < max_period_px")
        if not 2 * np.pi * self.amplitude_px / self.min_period_px < 1:
            raise InvalidInputError("amplitude_px must be below min_period_px / (2 pi) (the warp must invert)")
        return self

    @property
    def center_row(self) -> float:
        return (self.height - 1) / 2.0

    def period(self) -> np.ndarray:
        """Period p(x) in px for every column (linear from ``min_period_px`` at x = 0)."""
        x = np.arange(self.width, dtype=np.float64)
        return self.min_period_px + (self.max_period_px - self.min_period_px) * x / self.width

    def frequency(self) -> np.ndarray:
        """1 / p(x) in cycles per px, for every column."""
        return 1.0 / self.period()

    def displacement(self) -> np.ndarray:
        """True v (H, W) px of the skin point at each pixel of the *first* image (u is 0)."""
        y = np.arange(self.height, dtype=np.float64)[:, None] - self.center_row
        return self.amplitude_px * np.cos(2.0 * np.pi * y * self.frequency()[None, :])

    @property
    def border_px(self) -> int:
        """Columns left out at each end (64 px: what a DIC code's subsets need; windows up to 127 px fit)."""
        return 64

    @property
    def star_columns(self) -> slice:
        """Columns over which the resolution is scanned (all but the borders)."""
        return slice(self.border_px, self.width - self.border_px)

    @property
    def noise_columns(self) -> slice:
        """The long-period end (periods from about 190 px on the Challenge's layout, up to the border), where the
        noise is measured."""
        return slice(int(round(0.625 * self.width)), self.width - self.border_px)


@dataclass(frozen=True)
class StarPair:
    """Two 8-bit images and the truth: ``v_true`` (H, W) px, the vertical displacement from image a to image b of
    the point at each pixel of image a (``u`` is 0)."""

    layout: StarLayout
    image_a: np.ndarray
    image_b: np.ndarray
    v_true: np.ndarray


def render_star_pair(layout: StarLayout | None = None, *, seed: int = 0) -> StarPair:
    """Render a star pair (see the module doc); the same seed gives the same bytes."""
    lay = layout or StarLayout()
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(7,)))
    h, w = lay.height, lay.width
    pad = 6.0 * lay.dot_sigma_px
    n = int(round(lay.dot_density * (w + 2 * pad) * (h + 2 * pad)))
    dots_x = rng.uniform(-pad, w - 1 + pad, n)
    dots_y = rng.uniform(-pad, h - 1 + pad, n)
    strength = rng.uniform(0.3, 1.2, n)
    f = lay.frequency()[None, :]
    # Image b at pixel (x, y) shows the point (x, Y) with Y + v(x, Y) = y: fixed point (a contraction by
    # 2 pi A / min_period at most, ~0.31: 40 steps reach 1e-20).
    rows_a = np.broadcast_to(np.arange(h, dtype=np.float64)[:, None], (h, w)).copy()
    rows_b = rows_a.copy()
    for _ in range(40):
        rows_b = rows_a - lay.amplitude_px * np.cos(2.0 * np.pi * (rows_b - lay.center_row) * f)
    sums = []
    for rows in (rows_a, rows_b):
        s = np.zeros((h, w))
        _add_dots(s, rows, dots_x, dots_y, strength, float(lay.dot_sigma_px))
        sums.append(s)
    images = []
    for s in sums:
        img = lay.dark + (lay.bright - lay.dark) * (1.0 - np.exp(-s))
        img = img + rng.normal(0.0, lay.noise_sigma, img.shape) if lay.noise_sigma > 0 else img
        images.append(np.clip(np.round(img), 0, 255).astype(np.uint8))
    return StarPair(lay, images[0], images[1], lay.displacement())


@numba.njit(cache=True)
def _add_dots(out, rows, dots_x, dots_y, strength, sigma):  # pragma: no cover - compiled
    """out[y, x] += strength_i exp(-((x - x_i)^2 + (rows[y, x] - y_i)^2) / (2 sigma^2)) for every dot i (the
    point shown at pixel (x, y) is (x, rows[y, x]); rows differ from y by less than 1 px)."""
    h, w = out.shape
    reach = int(np.ceil(5.0 * sigma)) + 2
    inv = 0.5 / (sigma * sigma)
    for i in range(dots_x.size):
        cx, cy = dots_x[i], dots_y[i]
        x0, x1 = max(int(cx) - reach, 0), min(int(cx) + reach + 1, w)
        y0, y1 = max(int(cy) - reach, 0), min(int(cy) + reach + 1, h)
        for y in range(y0, y1):
            for x in range(x0, x1):
                dx = x - cx
                dy = rows[y, x] - cy
                out[y, x] += strength[i] * np.exp(-(dx * dx + dy * dy) * inv)
